//! Sparse convolution benchmark on a driving-like scene: a ground plane plus boxes in a 128x128x16 grid
//! (about 53,000 active voxels), C = 64 in and out. Prints one JSON line per layer (median of R runs).
//!
//! `cargo run --release -p occ-sparse --example bench_conv -- [--repeat R] [--channels C] [--save-dir D]`
//! With `--save-dir`, the input is written as coords.npy / feats.npy plus weights, for running the same
//! case through other implementations (e.g. spconv) with `conv_npy`'s argument layout.

use burn::backend::NdArray;
use burn::prelude::*;
use burn::tensor::TensorData;
use npyz::WriterBuilder;
use occ_sparse::backend::sparse_conv;
use occ_sparse::kernel_map::{conv_map, MapKind};
use occ_sparse::{ConvGeometry, CoordSet};
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;
use std::sync::Arc;
use std::time::Instant;

type B = NdArray<f32>;

mod scene;

/// Ground plane (z = 2..3 with gentle slope), plus 120 boxes (cars, buildings, poles), hollow like a
/// LiDAR-visible surface would be dense near the ground: about 53k voxels.
pub fn driving_scene(seed: u64) -> Vec<[i32; 4]> {
    let spec = scene::SceneSpec {
        shape: [128, 128, 16],
        ground_z: 2,
        slope: 90,
        boxes: 120,
        box_z: 3,
        extent: [(2, 10), (2, 14), (2, 12)],
    };
    scene::driving_scene(&spec, seed)
}

fn main() {
    let mut repeat = 5usize;
    let mut c = 64usize;
    let mut save: Option<std::path::PathBuf> = None;
    let mut args = std::env::args().skip(1);
    while let Some(a) = args.next() {
        match a.as_str() {
            "--repeat" => repeat = args.next().and_then(|v| v.parse().ok()).unwrap_or(5),
            "--channels" => c = args.next().and_then(|v| v.parse().ok()).unwrap_or(64),
            "--save-dir" => save = args.next().map(Into::into),
            _ => {}
        }
    }
    let coords = driving_scene(0);
    let n = coords.len();
    let mut r = ChaCha8Rng::seed_from_u64(1);
    let feats: Vec<f32> = (0..n * c).map(|_| r.random_range(-1.0..1.0)).collect();
    let dev = Default::default();
    let x = Tensor::<B, 2>::from_data(TensorData::new(feats.clone(), [n, c]), &dev);
    if let Some(dir) = &save {
        std::fs::create_dir_all(dir).expect("save dir");
        let flat: Vec<i32> = coords.iter().flat_map(|c| c.iter().copied()).collect();
        write(dir.join("coords.npy"), &flat, &[n as u64, 4]);
        write(dir.join("feats.npy"), &feats, &[n as u64, c as u64]);
    }
    let cases: Vec<(&str, MapKind, ConvGeometry)> = vec![
        (
            "subm_k333",
            MapKind::Submanifold,
            ConvGeometry::new([3, 3, 3]),
        ),
        (
            "subm_k331",
            MapKind::Submanifold,
            ConvGeometry::new([3, 3, 1]),
        ),
        (
            "conv_k333_s1_p1",
            MapKind::Regular,
            ConvGeometry::new([3, 3, 3]).with_padding([1; 3]),
        ),
        (
            "conv_k333_s2_p1",
            MapKind::Regular,
            ConvGeometry::new([3, 3, 3])
                .with_stride([2; 3])
                .with_padding([1; 3]),
        ),
    ];
    for (name, kind, geom) in cases {
        let kv = geom.volume();
        let w: Vec<f32> = (0..c * kv * c).map(|_| r.random_range(-0.1..0.1)).collect();
        if let Some(dir) = &save {
            let k = geom.kernel;
            write(
                dir.join(format!("{name}_weight.npy")),
                &w,
                &[c as u64, k[0] as u64, k[1] as u64, k[2] as u64, c as u64],
            );
        }
        let wt = Tensor::<B, 3>::from_data(TensorData::new(w, [c, kv, c]), &dev);
        let set = Arc::new(CoordSet::new(coords.clone(), [128, 128, 16], 1).expect("scene"));
        let t0 = Instant::now();
        let (_out, map) = conv_map(&set, kind, geom).expect("map");
        let ms_map = t0.elapsed().as_secs_f64() * 1e3;
        let mut times = Vec::new();
        for _ in 0..repeat {
            let t0 = Instant::now();
            let y = sparse_conv::<B>(x.clone(), wt.clone(), map.clone(), false);
            let _ = y.into_data();
            times.push(t0.elapsed().as_secs_f64() * 1e3);
        }
        times.sort_by(f64::total_cmp);
        let med = times[times.len() / 2];
        if std::env::var_os("BENCH_HOST_ONLY").is_some() {
            let xv = x.clone().into_data().to_vec::<f32>().expect("f32");
            let wv = wt.clone().into_data().to_vec::<f32>().expect("f32");
            let view = occ_sparse::host::WeightView {
                d0: c,
                k: kv,
                d2: c,
                transposed: false,
            };
            let mut ht = Vec::new();
            for _ in 0..repeat {
                let t0 = Instant::now();
                let y = occ_sparse::host::conv_forward(&xv, &wv, view, &map);
                std::hint::black_box(&y);
                ht.push(t0.elapsed().as_secs_f64() * 1e3);
            }
            ht.sort_by(f64::total_cmp);
            eprintln!("{name}: host-only median {:.2} ms", ht[ht.len() / 2]);
        }
        let gflop = map.num_pairs() as f64 * (c * c * 2) as f64 / 1e9;
        println!(
            "{{\"case\":\"{name}\",\"n_in\":{n},\"n_out\":{},\"pairs\":{},\"channels\":{c},\"ms_kernel_map\":{ms_map:.2},\"ms_compute_median\":{med:.2},\"ms_min\":{:.2},\"ms_max\":{:.2},\"gflops\":{:.1},\"threads\":{}}}",
            map.n_out(),
            map.num_pairs(),
            times[0],
            times[times.len() - 1],
            gflop / (med / 1e3),
            rayon::current_num_threads()
        );
    }
}

fn write<T: npyz::Serialize + npyz::AutoSerialize + Copy>(
    p: std::path::PathBuf,
    d: &[T],
    shape: &[u64],
) {
    let f = std::fs::File::create(&p).expect("create");
    let mut w = npyz::WriteOptions::<T>::new()
        .default_dtype()
        .shape(shape)
        .writer(std::io::BufWriter::new(f))
        .begin_nd()
        .expect("npy");
    w.extend(d.iter().copied()).expect("write");
    w.finish().expect("finish");
}
