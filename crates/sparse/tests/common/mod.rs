//! Shared test helpers: seeded random sparse inputs, dense references, `.npy` reading (the fixtures
//! folder itself is found by `occ_testdata`).
#![allow(dead_code)]

use burn::backend::{Autodiff, NdArray};
use burn::prelude::*;
use burn::tensor::TensorData;
use occ_sparse::Coord;
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;
use std::collections::HashSet;

/// f64 autodiff backend used for reference comparisons.
pub type B64 = Autodiff<NdArray<f64>>;

pub fn rng(seed: u64) -> ChaCha8Rng {
    ChaCha8Rng::seed_from_u64(seed)
}

/// `n` distinct random sites over `batch` items of `shape`, sorted.
pub fn random_coords(r: &mut ChaCha8Rng, shape: [usize; 3], batch: usize, n: usize) -> Vec<Coord> {
    let mut set = HashSet::new();
    let total = batch * shape.iter().product::<usize>();
    let n = n.min(total);
    while set.len() < n {
        set.insert([
            r.random_range(0..batch) as i32,
            r.random_range(0..shape[0]) as i32,
            r.random_range(0..shape[1]) as i32,
            r.random_range(0..shape[2]) as i32,
        ]);
    }
    let mut v: Vec<Coord> = set.into_iter().collect();
    v.sort();
    v
}

pub fn random_vec(r: &mut ChaCha8Rng, n: usize) -> Vec<f64> {
    (0..n).map(|_| r.random_range(-1.0..1.0)).collect()
}

pub fn t2(v: Vec<f64>, shape: [usize; 2]) -> Tensor<B64, 2> {
    Tensor::from_data(TensorData::new(v, shape), &Default::default())
}

pub fn t5(v: Vec<f64>, shape: [usize; 5]) -> Tensor<B64, 5> {
    Tensor::from_data(TensorData::new(v, shape), &Default::default())
}

pub fn to_vec<const D: usize>(t: Tensor<B64, D>) -> Vec<f64> {
    t.into_data().convert::<f64>().to_vec::<f64>().unwrap()
}

pub fn to_vec_inner<const D: usize>(t: Tensor<NdArray<f64>, D>) -> Vec<f64> {
    t.into_data().convert::<f64>().to_vec::<f64>().unwrap()
}

/// Dense `[B, C, X, Y, Z]` array from sparse rows.
pub fn densify(
    coords: &[Coord],
    feats: &[f64],
    c: usize,
    shape: [usize; 3],
    batch: usize,
) -> Vec<f64> {
    let [sx, sy, sz] = shape;
    let mut d = vec![0.0; batch * c * sx * sy * sz];
    for (r, co) in coords.iter().enumerate() {
        for ch in 0..c {
            let idx = ((((co[0] as usize * c + ch) * sx + co[1] as usize) * sy + co[2] as usize)
                * sz)
                + co[3] as usize;
            d[idx] = feats[r * c + ch];
        }
    }
    d
}

/// Reads rows of a dense `[B, C, X, Y, Z]` array at sites.
pub fn sample(dense: &[f64], coords: &[Coord], c: usize, shape: [usize; 3]) -> Vec<f64> {
    let [sx, sy, sz] = shape;
    let mut out = Vec::with_capacity(coords.len() * c);
    for co in coords {
        for ch in 0..c {
            let idx = ((((co[0] as usize * c + ch) * sx + co[1] as usize) * sy + co[2] as usize)
                * sz)
                + co[3] as usize;
            out.push(dense[idx]);
        }
    }
    out
}

pub fn max_abs_diff(a: &[f64], b: &[f64]) -> f64 {
    assert_eq!(a.len(), b.len(), "length mismatch");
    a.iter()
        .zip(b)
        .map(|(x, y)| (x - y).abs())
        .fold(0.0, f64::max)
}
