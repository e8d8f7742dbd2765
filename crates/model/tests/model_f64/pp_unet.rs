//! Sparse U-Net: keeps the input sites (and their order), is differentiable (autodiff gradients
//! against central finite differences in f64), handles odd grid sizes.

use crate::pp_common;

use burn::prelude::*;
use occ_model::sparseocc_pp::unet::SparseUNetConfig;
use occ_sparse::SparseTensor;
use pp_common::*;
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;

fn random_sites(seed: u64, batch: usize, dims: [usize; 3], per_item: usize) -> Vec<[i32; 4]> {
    let mut rng = ChaCha8Rng::seed_from_u64(seed);
    let mut set = std::collections::BTreeSet::new();
    for b in 0..batch {
        let mut n = 0;
        while n < per_item {
            let c = [
                b as i32,
                rng.random_range(0..dims[0]) as i32,
                rng.random_range(0..dims[1]) as i32,
                rng.random_range(0..dims[2]) as i32,
            ];
            if set.insert(c) {
                n += 1;
            }
        }
    }
    // A shuffled order, to check that the output keeps the input order.
    let mut v: Vec<_> = set.into_iter().collect();
    for i in (1..v.len()).rev() {
        v.swap(i, rng.random_range(0..=i));
    }
    v
}

#[test]
fn unet_keeps_sites_and_all_parameters_get_gradients() {
    let device = Default::default();
    for (dims, seed) in [([16, 16, 4], 1u64), ([10, 6, 5], 2)] {
        let unet = SparseUNetConfig::new(6, vec![8, 8, 16, 16]).init::<AD>(&device);
        let coords = random_sites(seed, 2, dims, 60);
        let n = coords.len();
        let feats = randn::<AD, 2>([n, 6], seed + 10, &device).require_grad();
        let x = SparseTensor::new(coords.clone(), feats.clone(), dims, 2).unwrap();
        let y = unet.forward(x).unwrap();
        assert_eq!(y.coords(), coords.as_slice());
        assert_eq!(y.feats().dims(), [n, 8]);
        let r = randn::<AD, 2>([n, 8], seed + 20, &device);
        let grads = (y.into_feats() * r).sum().backward();
        assert_all_grads(&unet, &grads);
        let g = feats.grad(&grads).expect("input gradient");
        assert!(to_f64(&g).iter().all(|v| v.is_finite()));
    }
}

#[test]
fn unet_gradient_matches_finite_differences() {
    let device = Default::default();
    let dims = [8, 8, 4];
    let unet = SparseUNetConfig::new(3, vec![4, 4, 6, 6]).init::<AD>(&device);
    let coords = random_sites(5, 1, dims, 40);
    let n = coords.len();
    let base = to_f64(&randn::<AD, 2>([n, 3], 6, &device));
    let r = randn::<AD, 2>([n, 4], 7, &device);
    let loss = |v: &[f64], grad: bool| -> (f64, Vec<f64>) {
        let f =
            Tensor::<AD, 2>::from_data(burn::tensor::TensorData::new(v.to_vec(), [n, 3]), &device);
        let f = if grad { f.require_grad() } else { f };
        let x = SparseTensor::new(coords.clone(), f.clone(), dims, 1).unwrap();
        let l = (unet.forward(x).unwrap().into_feats() * r.clone()).sum();
        let value = to_f64(&l)[0];
        if grad {
            let grads = l.backward();
            (value, to_f64(&f.grad(&grads).unwrap()))
        } else {
            (value, Vec::new())
        }
    };
    let (_, g) = loss(&base, true);
    let eps = 1e-6;
    for i in [0usize, 7, 20, 3 * n / 2, 3 * n - 1] {
        let mut plus = base.clone();
        plus[i] += eps;
        let mut minus = base.clone();
        minus[i] -= eps;
        let fd = (loss(&plus, false).0 - loss(&minus, false).0) / (2.0 * eps);
        assert!(
            (fd - g[i]).abs() < 1e-5 * (1.0 + fd.abs()),
            "entry {i}: finite difference {fd} vs autodiff {}",
            g[i]
        );
    }
}

#[test]
fn unet_rejects_bad_config() {
    assert!(SparseUNetConfig::new(4, vec![]).validate().is_err());
    assert!(SparseUNetConfig::new(4, vec![4, 0]).validate().is_err());
    assert!(SparseUNetConfig::new(4, vec![4, 8, 8, 16])
        .validate()
        .is_ok());
}
