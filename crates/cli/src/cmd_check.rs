//! `sparseocc check-backend`: checks the backend this binary was built for (CUDA with
//! `--features cuda`) against the NdArray CPU reference, on the same inputs and weights:
//!
//! - sparse convolutions (submanifold 3x3x3, strided regular, transposed) forward, and the gradient
//!   with respect to the input features and weights through autodiff;
//! - the image encoder (ResNet + FPN), weights copied through a checkpoint file;
//! - one SparseOcc++ forward pass on the backend (runs, finite logits), and the sparse convolution
//!   throughput (submanifold 3x3x3, C = 64, driving-like input) there.
//!
//! Exits with an error when a difference exceeds the tolerance. On a CPU build it compares NdArray
//! with itself (a smoke test of the command).

use crate::backend::{self, Infer, Train};
use anyhow::{bail, Context, Result};
use burn::backend::{Autodiff, NdArray};
use burn::module::Module;
use burn::prelude::*;
use burn::record::{BinFileRecorder, FullPrecisionSettings};
use burn::tensor::TensorData;
use occ_model::encoder::backbone::ResNetConfig;
use occ_model::encoder::fpn::{FpnConfig, ImageEncoderConfig};
use occ_sparse::backend::sparse_conv;
use occ_sparse::kernel_map::{conv_map, MapKind};
use occ_sparse::{ConvGeometry, CoordSet};
use std::sync::Arc;
use std::time::Instant;

type Cpu = NdArray<f32>;

/// Arguments of `sparseocc check-backend`.
#[derive(clap::Args, Debug)]
pub struct CheckArgs {
    /// Relative tolerance (max |a - b| / max |b|).
    #[arg(long, default_value_t = 1e-3)]
    pub tol: f64,
    /// Write the results as JSON here.
    #[arg(long)]
    pub json: Option<std::path::PathBuf>,
}

fn lcg(seed: u64) -> impl FnMut() -> f32 {
    let mut s = seed
        .wrapping_mul(6364136223846793005)
        .wrapping_add(1442695040888963407);
    move || {
        s = s
            .wrapping_mul(6364136223846793005)
            .wrapping_add(1442695040888963407);
        ((s >> 40) as f32 / (1u64 << 24) as f32) * 2.0 - 1.0
    }
}

/// A driving-like voxel set in 128x128x16: a ground plane and box surfaces.
fn scene() -> Vec<[i32; 4]> {
    let mut r = lcg(3);
    let (sx, sy, sz) = (128i32, 128i32, 16i32);
    let mut occ = vec![false; (sx * sy * sz) as usize];
    let idx = |x: i32, y: i32, z: i32| ((x * sy + y) * sz + z) as usize;
    for x in 0..sx {
        for y in 0..sy {
            occ[idx(x, y, 2 + (x + y) / 90)] = true;
        }
    }
    for _ in 0..120 {
        let f = |r: &mut dyn FnMut() -> f32, lo: i32, hi: i32| {
            lo + (((r() + 1.0) * 0.5) * (hi - lo) as f32) as i32
        };
        let (w, l, h) = (f(&mut r, 2, 10), f(&mut r, 2, 14), f(&mut r, 2, 12));
        let (x0, y0) = (f(&mut r, 0, sx - w), f(&mut r, 0, sy - l));
        for x in x0..x0 + w {
            for y in y0..y0 + l {
                for z in 3..(3 + h).min(sz) {
                    if x == x0
                        || x == x0 + w - 1
                        || y == y0
                        || y == y0 + l - 1
                        || z == (3 + h).min(sz) - 1
                    {
                        occ[idx(x, y, z)] = true;
                    }
                }
            }
        }
    }
    let mut v = Vec::new();
    for x in 0..sx {
        for y in 0..sy {
            for z in 0..sz {
                if occ[idx(x, y, z)] {
                    v.push([0, x, y, z]);
                }
            }
        }
    }
    v
}

fn rel_err(a: &[f32], b: &[f32]) -> f64 {
    if a.len() != b.len() {
        return f64::INFINITY;
    }
    let scale = b.iter().fold(0f64, |m, v| m.max(v.abs() as f64)).max(1e-12);
    let d = a
        .iter()
        .zip(b)
        .fold(0f64, |m, (x, y)| m.max((x - y).abs() as f64));
    if d.is_nan() {
        f64::INFINITY
    } else {
        d / scale
    }
}

fn to_vec<B: Backend, const D: usize>(t: Tensor<B, D>) -> Vec<f32> {
    t.into_data()
        .convert::<f32>()
        .to_vec::<f32>()
        .unwrap_or_default()
}

pub fn run(args: &CheckArgs) -> Result<()> {
    let dev = backend::device();
    let cpu_dev = Default::default();
    let coords = scene();
    let n = coords.len();
    let c = 32usize;
    let mut rnd = lcg(11);
    let feats: Vec<f32> = (0..n * c).map(|_| rnd()).collect();
    let set = Arc::new(CoordSet::new(coords, [128, 128, 16], 1)?);
    let mut results = Vec::new();
    let mut worst = 0f64;
    let cases = [
        (
            "subm_k333",
            MapKind::Submanifold,
            ConvGeometry::new([3, 3, 3]),
            false,
        ),
        (
            "conv_k333_s2_p1",
            MapKind::Regular,
            ConvGeometry::new([3, 3, 3])
                .with_stride([2; 3])
                .with_padding([1; 3]),
            false,
        ),
        (
            "transposed_k222_s2",
            MapKind::Regular,
            ConvGeometry::new([2, 2, 2]).with_stride([2; 3]),
            true,
        ),
    ];
    for (name, kind, geom, transposed) in cases {
        let (_, map) = conv_map(&set, kind, geom)?;
        let map = if transposed { map.transposed() } else { map };
        let kv = geom.volume();
        let w: Vec<f32> = (0..c * kv * c).map(|_| rnd() * 0.1).collect();
        let n_in = if transposed { map.n_in() } else { n };
        let x_data = TensorData::new(feats[..n_in * c].to_vec(), [n_in, c]);
        let w_data = TensorData::new(w, [c, kv, c]);
        // Reference on the CPU, with autodiff.
        let xr = Tensor::<Autodiff<Cpu>, 2>::from_data(x_data.clone(), &cpu_dev).require_grad();
        let wr = Tensor::<Autodiff<Cpu>, 3>::from_data(w_data.clone(), &cpu_dev).require_grad();
        let yr = sparse_conv(xr.clone(), wr.clone(), map.clone(), transposed);
        let gr = yr.clone().powf_scalar(2.0).sum().backward();
        let (yr_v, gxr, gwr) = (
            to_vec(yr),
            to_vec(xr.grad(&gr).context("no x grad")?),
            to_vec(wr.grad(&gr).context("no w grad")?),
        );
        // The backend under test.
        let xt = Tensor::<Train, 2>::from_data(x_data, &dev).require_grad();
        let wt = Tensor::<Train, 3>::from_data(w_data, &dev).require_grad();
        let yt = sparse_conv(xt.clone(), wt.clone(), map.clone(), transposed);
        let gt = yt.clone().powf_scalar(2.0).sum().backward();
        let (e_y, e_gx, e_gw) = (
            rel_err(&to_vec(yt), &yr_v),
            rel_err(&to_vec(xt.grad(&gt).context("no x grad")?), &gxr),
            rel_err(&to_vec(wt.grad(&gt).context("no w grad")?), &gwr),
        );
        eprintln!(
            "{name}: {} pairs, rel err forward {e_y:.2e}, dx {e_gx:.2e}, dw {e_gw:.2e}",
            map.num_pairs()
        );
        worst = worst.max(e_y).max(e_gx).max(e_gw);
        results.push(serde_json::json!({"case": name, "pairs": map.num_pairs(), "forward": e_y, "grad_x": e_gx, "grad_w": e_gw}));
    }

    // Throughput of the submanifold 3x3x3 layer at C = 64 on the backend under test.
    let c64 = 64usize;
    let (_, map) = conv_map(&set, MapKind::Submanifold, ConvGeometry::new([3, 3, 3]))?;
    let x = Tensor::<Infer, 2>::from_data(
        TensorData::new((0..n * c64).map(|_| rnd()).collect::<Vec<f32>>(), [n, c64]),
        &dev,
    );
    let w = Tensor::<Infer, 3>::from_data(
        TensorData::new(
            (0..c64 * 27 * c64)
                .map(|_| rnd() * 0.1)
                .collect::<Vec<f32>>(),
            [c64, 27, c64],
        ),
        &dev,
    );
    let mut times = Vec::new();
    for i in 0..12 {
        let t0 = Instant::now();
        let y = sparse_conv(x.clone(), w.clone(), map.clone(), false);
        let s: f32 = y.sum().into_scalar().elem();
        std::hint::black_box(s);
        if i >= 2 {
            times.push(t0.elapsed().as_secs_f64() * 1e3);
        }
    }
    times.sort_by(f64::total_cmp);
    let med = times[times.len() / 2];
    let gflops = map.num_pairs() as f64 * (c64 * c64 * 2) as f64 / 1e9 / (med / 1e3);
    eprintln!(
        "subm_k333 C=64 on {}: {} voxels, {} pairs, median {med:.2} ms ({gflops:.1} GFLOP/s)",
        backend::describe(),
        n,
        map.num_pairs()
    );
    results.push(serde_json::json!({"case": "subm_k333_c64_timing", "voxels": n, "pairs": map.num_pairs(), "median_ms": med, "gflops": gflops}));

    // Image encoder parity, weights copied through a checkpoint file.
    let enc_cfg = ImageEncoderConfig::new(
        ResNetConfig::new().with_base_width(16),
        FpnConfig::new().with_out_channels(32),
    );
    let cpu_enc = enc_cfg.init::<Cpu>(&cpu_dev)?;
    let (h, wd) = (128usize, 416usize);
    let img: Vec<f32> = (0..3 * h * wd).map(|_| rnd()).collect();
    // The forward pass first: burn initialises parameters lazily, and a clone of an uninitialised
    // parameter would draw its own random values.
    let a = cpu_enc.forward(Tensor::<Cpu, 4>::from_data(
        TensorData::new(img.clone(), [1, 3, h, wd]),
        &cpu_dev,
    ));
    let tmp = occ_data::formats::io::temp_sibling(&std::env::temp_dir().join("sparseocc-check"));
    let rec = BinFileRecorder::<FullPrecisionSettings>::new();
    cpu_enc.save_file(tmp.clone(), &rec)?;
    let dev_enc = enc_cfg
        .init::<Infer>(&dev)?
        .load_file(tmp.clone(), &rec, &dev)
        .context("loading the encoder weights on the backend")?;
    let _ = std::fs::remove_file(tmp.with_extension("bin"));
    let b = dev_enc.forward(Tensor::<Infer, 4>::from_data(
        TensorData::new(img, [1, 3, h, wd]),
        &dev,
    ));
    for (l, (fa, fb)) in a.into_iter().zip(b).enumerate() {
        let e = rel_err(&to_vec(fb), &to_vec(fa));
        eprintln!("image encoder level {l}: rel err {e:.2e}");
        worst = worst.max(e);
        results.push(serde_json::json!({"case": format!("encoder_level{l}"), "forward": e}));
    }

    // A whole SparseOcc++ forward pass on the backend.
    let cfg = occ_train::RunConfig::from_toml(occ_train::config::SYNTHETIC_TINY, "synthetic_tiny")?;
    let model = cfg.model.init::<Infer>(&dev)?;
    let grid = occ_data::synthetic::Preset::KittiSmall.grid();
    let batch = occ_model::Batch::<Infer> {
        images: Tensor::from_data(
            TensorData::new(
                (0..3 * 128 * 416).map(|_| rnd()).collect::<Vec<f32>>(),
                [1, 1, 3, 128, 416],
            ),
            &dev,
        ),
        cameras: vec![vec![demo_camera()]],
        grid,
        target: None,
        points: None,
    };
    let t0 = Instant::now();
    let out = model.forward(&batch)?;
    let logits = to_vec(out.logits.clone());
    let finite = logits.iter().all(|v| v.is_finite());
    eprintln!(
        "SparseOcc++ (synthetic_tiny) forward: {} voxels, logits finite: {finite}, {:.1} ms (first call)",
        out.coords.len(),
        t0.elapsed().as_secs_f64() * 1e3
    );
    results.push(serde_json::json!({"case": "sparseocc++_forward", "voxels": out.coords.len(), "finite": finite}));
    if let Some(p) = &args.json {
        crate::util::write_json(
            p,
            &serde_json::json!({"device": backend::describe(), "tolerance": args.tol, "worst": worst, "results": results}),
        )?;
    }
    if !finite {
        bail!(
            "SparseOcc++ produced non-finite logits on {}",
            backend::describe()
        );
    }
    if worst > args.tol {
        bail!(
            "{}: differs from the NdArray reference by {worst:.2e} (> {:.0e})",
            backend::describe(),
            args.tol
        );
    }
    eprintln!(
        "check-backend: {} agrees with the NdArray reference (worst rel err {worst:.2e})",
        backend::describe()
    );
    Ok(())
}

/// A forward-looking KITTI-like camera at 416x128.
fn demo_camera() -> occ_model::CameraInput {
    use occ_geometry::mat::{mat4_mul, Mat4};
    // cam: x right, y down, z forward; LiDAR: x forward, y left, z up.
    let cam_from_lidar: Mat4 = [
        [0.0, -1.0, 0.0, 0.0],
        [0.0, 0.0, -1.0, 0.0],
        [1.0, 0.0, 0.0, 0.0],
        [0.0, 0.0, 0.0, 1.0],
    ];
    let k: Mat4 = [
        [240.0, 0.0, 208.0, 0.0],
        [0.0, 240.0, 64.0, 0.0],
        [0.0, 0.0, 1.0, 0.0],
        [0.0, 0.0, 0.0, 1.0],
    ];
    occ_model::CameraInput {
        img_from_lidar: mat4_mul(&k, &cam_from_lidar),
        cam_from_lidar,
    }
}
