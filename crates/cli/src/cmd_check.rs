//! `sparseocc check-backend`: checks the backend this binary was built for (CUDA with
//! `--features cuda`, WebGPU with `--features wgpu`, which runs on lavapipe on a machine without a
//! GPU) against the NdArray CPU reference computed in f64 (the device in f32), on the same inputs
//! and weights:
//!
//! - kernel maps: the gather tables the backend builds on its device from deferred maps, entry for
//!   entry against the host's (`map_tables`);
//! - sparse convolutions (submanifold 3x3x3, strided regular, transposed) forward, and the gradient
//!   with respect to the input features and weights through autodiff, on deferred maps (so on
//!   device-built tables where the backend builds them);
//! - the image encoder (ResNet + FPN), weights copied through a checkpoint file; its convolutions
//!   (forward, dx, dw, db, as the model computes them, with burn's own conv2d reported beside) and
//!   its other ops (nearest upsampling, max pool, BatchNorm) one by one;
//! - the DCA sampling op, forward and the gradients of its values, offsets, weights and gate;
//! - the row scatter-add and gather of `occ_sparse::rows` (forward and gradients), column sums;
//! - one SparseOcc++ forward pass (weights copied through a checkpoint file): the same voxels and
//!   logits; then the compile count of the shipped configuration (cubecl backends only): a first
//!   frame run twice (the warm-up: burn-fusion's second pass over the same operations can compile a
//!   few kernels, `compiles.same_frame_again`), then `--frames - 1` frames of other images, each
//!   with its own voxel count, whose counts are `compiles.new_frames` (the first of them is
//!   `compiles_after_warmup`, which must not exceed `--max-compiles-after-warmup`);
//!   `--compiles-only` runs this part alone; the model's weights are seeded (`--seed`), and the
//!   count fails when no new frame changed the voxel count;
//! - one SparseOcc++ training step on a smaller grid: every loss term and parameter gradient; a
//!   gradient beyond the tolerance that the reference's own rounding sensitivity explains (a ReLU
//!   on its kink, `KinkSensitivity`) is reported, not failed; where gradients still differ, each
//!   kind of loss term back-propagated alone, and where the image encoder's differ, its backward
//!   cut apart (whole, backbone, neck, each residual block alone);
//! - the sparse convolution throughput (submanifold 3x3x3, C = 64, driving-like input) there.
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
use occ_sparse::backend::SparseConvBackend;
use occ_sparse::kernel_map::{conv_map, conv_map_deferred, MapKind};
use occ_sparse::{ConvGeometry, CoordSet, RowBucket};
use std::sync::Arc;
use std::time::Instant;

/// The reference: f64, so that the comparison measures the device's error, not the sum of two
/// f32 roundings. Measured on lavapipe (2026-12-05): the training step's gradients are within
/// 9.2e-5 of the f64 reference, while two f32 CPU references that differed only in their GEMM
/// (matrixmultiply, then the `gemm` crate) were 5.4e-4 and 2.5e-3 away. On a CPU build the
/// backend itself is `NdArray<f32>` on the same device, and burn 0.21 keeps one float type per
/// NdArray device, so there the reference stays f32 (the command compares NdArray with itself).
#[cfg(any(feature = "cuda", feature = "wgpu"))]
type Cpu = NdArray<f64>;
/// The reference (see above): f32 on a CPU build.
#[cfg(not(any(feature = "cuda", feature = "wgpu")))]
type Cpu = NdArray<f32>;

/// Arguments of `sparseocc check-backend`.
#[derive(clap::Args, Debug)]
pub struct CheckArgs {
    /// Relative tolerance (max |a - b| / max |b|), a finite number above 0.
    #[arg(long, default_value_t = 1e-3, value_parser = crate::util::positive_finite)]
    pub tol: f64,
    /// Write the results as JSON here.
    #[arg(long)]
    pub json: Option<std::path::PathBuf>,
    /// Kernels the shipped configuration may compile for a second frame after the warm-up before
    /// the check fails. The goal is 0 (a stream of frames compiles nothing); a gate may allow the
    /// count measured so far, so that only a regression beyond it fails.
    #[arg(long, default_value_t = 0)]
    pub max_compiles_after_warmup: u64,
    /// Frames of the compile count, at least 2 (the first warms up; `compiles_after_warmup` is
    /// the second's count, `compiles_per_frame` lists every one after the first).
    #[arg(long, default_value_t = 2, value_parser = crate::util::at_least(2))]
    pub frames: usize,
    /// Run the compile count alone (no comparison with the reference).
    #[arg(long)]
    pub compiles_only: bool,
    /// Seed of the compile count's model weights (which voxels a frame keeps follows them). The
    /// count fails when no new frame changed the voxel count: then it tested nothing.
    #[arg(long, default_value_t = 3)]
    pub seed: u64,
    /// Seed of the model weights of the warm-up runs only (default: `--seed`): kernels follow
    /// shapes and configurations, not weight values, so warming up with weights that keep other
    /// voxels (`21` keeps the whole grid) tests whether a warm-up's voxel set leaves kernels
    /// uncompiled.
    #[arg(long)]
    pub warmup_seed: Option<u64>,
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
    let mut d = 0f64;
    for (x, y) in a.iter().zip(b) {
        let e = (x - y).abs() as f64;
        // `f64::max` would skip a NaN: any NaN, on either side, is a disagreement.
        if e.is_nan() {
            return f64::INFINITY;
        }
        d = d.max(e);
    }
    d / scale
}

/// Builds the maps of every kind of convolution (submanifold, regular, strided, transposed with
/// output padding, dilated; each map and its transpose) deferred, on a dense scene and on a sparse
/// one, and compares each gather table the backend builds on its device with the host's, entry
/// for entry, and the pair count read from that table (what profiling counts MACs with) with the
/// host's. Returns the entries that differ, the counts that differ and the tables compared (0
/// where the backend has no device tables: the CPU build).
fn map_table_mismatches<B: SparseConvBackend>(dev: &B::Device) -> Result<(usize, usize, usize)> {
    let dense = scene();
    let mut rnd = lcg(5);
    let mut sparse: Vec<[i32; 4]> = (0..3000)
        .map(|_| {
            let mut r = |n: f32| ((rnd() * 0.5 + 0.5) * n).clamp(0.0, n - 1.0) as i32;
            [r(2.0), r(300.0), r(280.0), r(24.0)]
        })
        .collect();
    sparse.sort_unstable();
    sparse.dedup();
    let kinds = [
        (MapKind::Submanifold, ConvGeometry::new([3, 3, 3])),
        (
            MapKind::Submanifold,
            ConvGeometry::new([5, 3, 1]).with_dilation([2, 1, 1]),
        ),
        (
            MapKind::Regular,
            ConvGeometry::new([3, 3, 3]).with_padding([1; 3]),
        ),
        (
            MapKind::Regular,
            ConvGeometry::new([3, 3, 3])
                .with_stride([2; 3])
                .with_padding([1; 3]),
        ),
        (
            MapKind::Regular,
            ConvGeometry::new([2, 2, 2]).with_stride([2; 3]),
        ),
        (
            MapKind::Transposed {
                output_padding: [1, 0, 1],
            },
            ConvGeometry::new([3, 2, 3])
                .with_stride([2, 2, 1])
                .with_padding([1, 0, 1]),
        ),
    ];
    let (mut mismatches, mut bad_counts, mut tables) = (0, 0, 0);
    for (coords, shape, batch) in [(dense, [128, 128, 16], 1), (sparse, [300, 280, 24], 2)] {
        for (kind, geom) in kinds {
            let host_set = Arc::new(CoordSet::new(coords.clone(), shape, batch)?);
            let device_set = Arc::new(CoordSet::new(coords.clone(), shape, batch)?);
            let (_, host) = conv_map(&host_set, kind, geom)?;
            let (_, deferred) = conv_map_deferred(&device_set, kind, geom)?;
            for (h, d) in [
                (host.clone(), deferred.clone()),
                (host.transposed(), deferred.transposed()),
            ] {
                let Some(table) = B::device_gather_table(&d, dev) else {
                    return Ok((0, 0, 0));
                };
                let count = B::device_pair_count(&d, dev)
                    .context("a deferred map with a device table has a device pair count")?;
                bad_counts += usize::from(count() != h.num_pairs());
                if d.has_host_pairs() {
                    bail!("map_tables: the table of {kind:?} {geom:?} came from host pairs");
                }
                let want = h.gather_table().context("a conv map has a gather table")?;
                mismatches += if table.len() == want.len() {
                    table.iter().zip(want).filter(|(a, b)| a != b).count()
                } else {
                    table.len().max(want.len())
                };
                tables += 1;
            }
        }
    }
    Ok((mismatches, bad_counts, tables))
}

fn to_vec<B: Backend, const D: usize>(t: Tensor<B, D>) -> Vec<f32> {
    t.into_data()
        .convert::<f32>()
        .to_vec::<f32>()
        .unwrap_or_default()
}

/// Panics seen in any thread since [`count_panics`]: a cubecl device server runs on its own thread,
/// and a kernel that fails there (an allocation beyond the device's limit, say) panics that thread
/// while the caller reads whatever the output buffer holds.
static PANICS: std::sync::atomic::AtomicUsize = std::sync::atomic::AtomicUsize::new(0);

/// Counts panics in every thread (keeping the default report).
fn count_panics() {
    let report = std::panic::take_hook();
    std::panic::set_hook(Box::new(move |info| {
        PANICS.fetch_add(1, std::sync::atomic::Ordering::SeqCst);
        report(info);
    }));
}

pub fn run(args: &CheckArgs) -> Result<()> {
    count_panics();
    let dev = backend::device();
    if args.compiles_only {
        let compiles = compile_counts(&dev, args.frames, args.seed, args.warmup_seed)?;
        let after_warmup = compiles.new_frames.first().copied().flatten();
        if let Some(p) = &args.json {
            crate::util::write_json(
                p,
                &serde_json::json!({"device": backend::describe(),
                    "compiles_after_warmup": after_warmup, "compiles": compiles,
                    "kernel_compilations": backend::kernel_compilations()}),
            )?;
        }
        return check_compiles(after_warmup, &compiles, args);
    }
    let cpu_dev = Default::default();
    let coords = scene();
    let n = coords.len();
    let c = 32usize;
    let mut rnd = lcg(11);
    let feats: Vec<f32> = (0..n * c).map(|_| rnd()).collect();
    let set = Arc::new(CoordSet::new(coords.clone(), [128, 128, 16], 1)?);
    // The device's maps are deferred (no host pairs), so a cubecl backend builds their tables
    // itself, as the models get them; the reference's are built on the host.
    let device_set = Arc::new(CoordSet::new(coords, [128, 128, 16], 1)?);
    let mut results = Vec::new();
    let mut worst = 0f64;
    let (mismatches, bad_counts, map_cases) = map_table_mismatches::<Train>(&dev)?;
    if map_cases > 0 {
        eprintln!(
            "map_tables: {map_cases} gather tables built on the device, {mismatches} entries and {bad_counts} pair counts differ from the host's"
        );
        worst = worst.max(if mismatches + bad_counts == 0 {
            0.0
        } else {
            1.0
        });
        results.push(serde_json::json!({"case": "map_tables", "tables": map_cases, "mismatches": mismatches, "pair_count_mismatches": bad_counts}));
    }
    // (name, map kind, geometry, transposed, C_in, C_out); 19 -> 37 channels leaves partial tiles
    // in the cubecl kernels (16 x 16).
    let cases = [
        (
            "subm_k333",
            MapKind::Submanifold,
            ConvGeometry::new([3, 3, 3]),
            false,
            c,
            c,
        ),
        (
            "subm_k333_c19_c37",
            MapKind::Submanifold,
            ConvGeometry::new([3, 3, 3]),
            false,
            19,
            37,
        ),
        (
            "conv_k333_s2_p1",
            MapKind::Regular,
            ConvGeometry::new([3, 3, 3])
                .with_stride([2; 3])
                .with_padding([1; 3]),
            false,
            c,
            c,
        ),
        (
            "transposed_k222_s2",
            MapKind::Regular,
            ConvGeometry::new([2, 2, 2]).with_stride([2; 3]),
            true,
            c,
            c,
        ),
    ];
    for (name, kind, geom, transposed, cin, cout) in cases {
        let (_, map) = conv_map(&set, kind, geom)?;
        let map = if transposed { map.transposed() } else { map };
        let (_, device_map) = conv_map_deferred(&device_set, kind, geom)?;
        let device_map = if transposed {
            device_map.transposed()
        } else {
            device_map
        };
        let kv = geom.volume();
        let w: Vec<f32> = (0..cin * kv * cout).map(|_| rnd() * 0.1).collect();
        let n_in = if transposed { map.n_in() } else { n };
        let x_data = TensorData::new(feats[..n_in * cin].to_vec(), [n_in, cin]);
        let w_shape = if transposed {
            [cin, kv, cout]
        } else {
            [cout, kv, cin]
        };
        let w_data = TensorData::new(w, w_shape);
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
        let yt = sparse_conv(xt.clone(), wt.clone(), device_map, transposed);
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

    // Column sums over a long voxel axis (the losses' reductions), against f64 sums on the host.
    for (rows, cols) in [(31_814usize, 3usize), (254_512, 3), (254_512, 20)] {
        let mut r = lcg(rows as u64 + cols as u64);
        let v: Vec<f32> = (0..rows * cols).map(|_| 0.5 + 0.5 * r()).collect();
        let mut host = vec![0f64; cols];
        for (i, x) in v.iter().enumerate() {
            host[i % cols] += *x as f64;
        }
        let t = Tensor::<Infer, 2>::from_data(TensorData::new(v, [rows, cols]), &dev);
        let host: Vec<f32> = host.iter().map(|&x| x as f32).collect();
        let e = rel_err(&to_vec(occ_sparse::sum_rows(t.clone())), &host);
        // burn's own `sum_dim(0)`, which the model avoids on long axes (occ_sparse::sum_rows):
        // reported, not checked (one thread per column; lavapipe stops its loop at 65,532 rows).
        let e_burn = rel_err(&to_vec(t.sum_dim(0)), &host);
        eprintln!("sum_rows of [{rows}, {cols}]: rel err {e:.2e} (burn sum_dim(0): {e_burn:.2e})");
        worst = worst.max(e);
        results.push(
            serde_json::json!({"case": format!("sum_rows_{rows}x{cols}"), "forward": e,
            "burn_sum_dim0": e_burn}),
        );
    }

    // Row scatter-add, gather and padding (occ_sparse::rows), forward and gradients, on more
    // rows than one shader loop may visit on lavapipe (65,532).
    for (h, n_out, cols) in [(300_000usize, 70_000usize, 8usize), (254_512, 254_512, 3)] {
        let (e, case) = rows_case(h, n_out, cols, &cpu_dev, &dev)?;
        worst = worst.max(e);
        results.push(case);
    }

    // The image convolutions of the tiny encoder (128x416 input), forward and backward: a 7x7
    // stride-2 stem, 3x3 convs at strides 4, 8 and 16, a stride-2 3x3, the 1x1 lateral.
    for (cin, cout, h, w, k, stride) in [
        (3, 16, 128, 416, 7, 2),
        (16, 16, 32, 104, 3, 1),
        (16, 32, 32, 104, 3, 2),
        (64, 64, 8, 26, 3, 1),
        (64, 32, 8, 26, 1, 1),
        (32, 32, 8, 26, 3, 1),
        // ResNet's shortcut downsampling (layer2.0, layer3.0 of the tiny encoder).
        (16, 32, 32, 104, 1, 2),
        (32, 64, 16, 52, 1, 2),
        // An unfolding of 1,152 x 30,720 values: two column blocks (`conv2d_cube::MAX_COLS_ELEMS`)
        // in the im2col training op's forward and backward.
        (128, 16, 160, 192, 3, 1),
    ] {
        let shape = Conv2dShape {
            cin,
            cout,
            h,
            w,
            k,
            stride,
        };
        let (e, case) = conv2d_case(shape, &cpu_dev, &dev);
        worst = worst.max(e);
        results.push(case);
    }

    let (e, case) = encoder_ops_case(&cpu_dev, &dev);
    worst = worst.max(e);
    results.push(case);

    for case in conv2d_inference_cases(&cpu_dev, &dev) {
        worst = worst.max(case["forward"].as_f64().unwrap_or(f64::INFINITY));
        results.push(case);
    }

    // DCA sampling (forward and gradients of values, offsets, weights and gate).
    let (e, case) = dca_case(&cpu_dev, &dev)?;
    worst = worst.max(e);
    results.push(case);

    // A whole SparseOcc++ forward pass on the backend against the reference, weights copied through
    // a checkpoint file, then a second frame (another image, so another set of voxels): kernels
    // compiled for it are the ones a steady stream of frames would keep compiling.
    let mut cfg =
        occ_train::RunConfig::from_toml(occ_train::config::SYNTHETIC_TINY, "synthetic_tiny")?;
    // Every anchor candidate kept: the top-k of the anchor scores is a host-side choice, and two
    // backends whose scores differ in the 7th digit may keep different voxels where scores tie
    // (measured on lavapipe: after the level-2 top-k, anchor rows 4,604-5,011 of 5,242 were
    // shifted and 13,624 logits moved, while every stage before it agreed to 1.4e-6). With nothing
    // pruned, every stage compares the same rows.
    if let Some(pp) = cfg.model.sparseocc_pp.as_mut() {
        pp.keep_ratios = vec![1.0; 3];
    }
    <Cpu as Backend>::seed(&cpu_dev, 5);
    let cpu_model = cfg.model.init::<Cpu>(&cpu_dev)?;
    let cpu_batch = tiny_batch::<Cpu>(frame(21), None, &cpu_dev);
    occ_model::profile::capture(true);
    let reference = cpu_model.forward(&cpu_batch)?;
    let reference_stages = occ_model::profile::take_captures();
    let tmp = occ_data::formats::io::temp_sibling(&std::env::temp_dir().join("sparseocc-check"));
    cpu_model.save_file(tmp.clone(), &rec)?;
    let model = cfg
        .model
        .init::<Infer>(&dev)?
        .load_file(tmp.clone(), &rec, &dev)
        .context("loading the SparseOcc++ weights on the backend")?;
    let t0 = Instant::now();
    let out = model.forward(&tiny_batch(frame(21), None, &dev))?;
    let logits = to_vec(out.logits.clone());
    let first_ms = t0.elapsed().as_secs_f64() * 1e3;
    let stages = occ_model::profile::take_captures();
    occ_model::profile::capture(false);
    // Stage by stage (each stage's output against the reference's), to see where they part.
    let mut stage_cases = Vec::new();
    for ((name, got), (ref_name, want)) in stages.iter().zip(&reference_stages) {
        if name != ref_name || got.len() != want.len() {
            eprintln!(
                "  stage {name}: {} values, reference {ref_name}: {}",
                got.len(),
                want.len()
            );
            stage_cases.push(serde_json::json!({"stage": name, "values": got.len(),
                "reference_values": want.len()}));
            continue;
        }
        let scale = want
            .iter()
            .fold(0f64, |m, v| m.max(v.abs() as f64))
            .max(1e-12);
        let off: Vec<usize> = (0..got.len())
            .filter(|&i| ((got[i] - want[i]).abs() as f64) > args.tol * scale)
            .collect();
        let e = rel_err(got, want);
        eprintln!(
            "  stage {name}: {} values, rel err {e:.2e}, {} beyond the tolerance{}",
            got.len(),
            off.len(),
            off.first().map_or(String::new(), |i| format!(
                " (first at {i}, last at {})",
                off[off.len() - 1]
            ))
        );
        stage_cases.push(
            serde_json::json!({"stage": name, "values": got.len(), "rel_err": e,
            "beyond_tolerance": off.len()}),
        );
    }
    let finite = logits.iter().all(|v| v.is_finite());
    let same_voxels = out.coords == reference.coords;
    let (e_model, beyond) = if same_voxels {
        let r = to_vec(reference.logits);
        let scale = r.iter().fold(0f64, |m, v| m.max(v.abs() as f64)).max(1e-12);
        let beyond = logits
            .iter()
            .zip(&r)
            .filter(|(a, b)| ((**a - **b).abs() as f64) > args.tol * scale)
            .count();
        (rel_err(&logits, &r), beyond)
    } else {
        (f64::INFINITY, logits.len())
    };
    eprintln!(
        "SparseOcc++ (synthetic_tiny) forward: {} voxels (reference {}), same voxels: {same_voxels}, \
         logits rel err {e_model:.2e} ({beyond} of {} beyond the tolerance), finite: {finite}, \
         {first_ms:.1} ms (first call)",
        out.coords.len(),
        reference.coords.len(),
        logits.len(),
    );
    worst = worst.max(e_model);
    results.push(
        serde_json::json!({"case": "sparseocc++_forward", "voxels": out.coords.len(),
        "reference_voxels": reference.coords.len(), "same_voxels": same_voxels, "forward": e_model,
        "logits_beyond_tolerance": beyond, "stages": stage_cases,
        "finite": finite, "first_call_ms": first_ms}),
    );
    let compiles = compile_counts(&dev, args.frames, args.seed, args.warmup_seed)?;
    let compiles_after_warmup = compiles.new_frames.first().copied().flatten();

    // One SparseOcc++ training step (forward with labels, the losses, backward) against the
    // reference: the loss and the gradient of every trainable parameter, with the same weights on a
    // smaller grid (`train_grid`). On the full grid the sub-voxel head has 262,144 rows, and burn's
    // own kernels behind the backward (the column sums of a broadcast bias's gradient, the matmul
    // of a weight gradient) loop over the rows in one shader loop, which lavapipe stops after
    // 65,532 iterations: measured on the full grid, `pp.head.bias` came out with rel err 0.750 =
    // 1 - 65,532/262,144 and every upstream gradient was off. The forward above checks the long row
    // axis; this step checks the backward on at most 8 x 6,144 = 49,152 rows.
    let mut train_cfg = cfg.clone();
    let grid = train_grid();
    train_cfg.model.full_dims = grid.dims;
    // The anchor embeddings are sized by the grid: weights of their own, copied as above.
    let _ = std::fs::remove_file(tmp.with_extension("bin"));
    // Both sides load the file: on the CPU, the module that was saved (a clone of it, rather)
    // gave other losses than its loaded copy, so the saved module itself is not used.
    <Cpu as Backend>::seed(&cpu_dev, 6);
    train_cfg
        .model
        .init::<Cpu>(&cpu_dev)?
        .save_file(tmp.clone(), &rec)?;
    let load = |what: &str| format!("loading the SparseOcc++ weights for training ({what})");
    let cpu_train = train_cfg
        .model
        .init::<Autodiff<Cpu>>(&cpu_dev)?
        .load_file(tmp.clone(), &rec, &cpu_dev)
        .with_context(|| load("reference"))?;
    let dev_train = train_cfg
        .model
        .init::<Train>(&dev)?
        .load_file(tmp.clone(), &rec, &dev)
        .with_context(|| load("backend"))?;
    let _ = std::fs::remove_file(tmp.with_extension("bin"));
    let labels = tiny_labels(grid.dims);
    let batch_r = occ_model::Batch {
        grid,
        ..tiny_batch(frame(23), Some(labels.clone()), &cpu_dev)
    };
    let batch_t = occ_model::Batch {
        grid,
        ..tiny_batch(frame(23), Some(labels), &dev)
    };
    let step_r = train_grads(&cpu_train, &batch_r, None)?;
    let step_t = train_grads(&dev_train, &batch_t, None)?;
    let (loss_r, loss_t, grads_t) = (step_r.loss, step_t.loss, &step_t.grads);
    for ((name, t), (_, r)) in step_t.terms.iter().zip(&step_r.terms) {
        eprintln!("  loss term {name}: {t:.6} (reference {r:.6})");
    }
    let e_loss = rel_err(&[loss_t], &[loss_r]);
    let errs = grad_errors(&step_t.grads, &step_r.grads);
    let (e_grad, worst_param) = worst_grad(&errs);
    // Gradients beyond the tolerance that the reference's own rounding sensitivity explains (a
    // ReLU input within rounding of its kink, see `KinkSensitivity`) are reported, not failed.
    let sensitivity = if e_grad > args.tol {
        KinkSensitivity::measure(&cpu_train, &batch_r, &step_r.grads)?
    } else {
        KinkSensitivity::default()
    };
    let mut beyond_params = Vec::new();
    let mut judged = errs.clone();
    for ((name, e, max_ref), j) in errs.iter().zip(&mut judged) {
        if *e <= args.tol {
            continue;
        }
        let sens = sensitivity.of(name);
        let explained = KinkSensitivity::explains(*e, sens, args.tol);
        eprintln!(
            "  gradient of {name}: rel err {e:.2e} (largest reference value {max_ref:.3e}; the \
             reference moves by {sens:.2e} under rounding-size weight perturbations: {})",
            if explained {
                "explained by a kink within rounding"
            } else {
                "not explained"
            }
        );
        if explained {
            j.1 = 0.0;
        }
        beyond_params.push(serde_json::json!({"param": name, "rel_err": e,
            "max_abs_reference": max_ref, "reference_rounding_sensitivity": sens,
            "explained_by_kink": explained}));
    }
    let (e_judged, judged_param) = worst_grad(&judged);
    eprintln!(
        "SparseOcc++ training step: loss {loss_t:.6} (reference {loss_r:.6}, rel err {e_loss:.2e}), \
         {} parameter gradients, worst rel err {e_grad:.2e} ({worst_param}), worst not explained \
         by a kink {e_judged:.2e} ({judged_param}; reference rounding sensitivity {:.2e}, {} \
         perturbed reference steps)",
        grads_t.len(),
        sensitivity.of(&judged_param),
        sensitivity.runs
    );
    worst = worst.max(e_loss).max(e_judged);
    // Where gradients disagree: each kind of loss term back-propagated alone, to find the
    // backward that differs (one more forward and backward per kind on each backend).
    let mut by_kind = Vec::new();
    if e_judged > args.tol {
        let mut kinds: Vec<&str> = step_r.terms.iter().map(|(k, _)| term_kind(k)).collect();
        kinds.sort_unstable();
        kinds.dedup();
        for kind in kinds {
            let r = train_grads(&cpu_train, &batch_r, Some(kind))?;
            let t = train_grads(&dev_train, &batch_t, Some(kind))?;
            let (e, param) = worst_grad(&grad_errors(&t.grads, &r.grads));
            eprintln!("  loss terms *.{kind} alone: worst gradient rel err {e:.2e} ({param})");
            by_kind.push(serde_json::json!({"kind": kind, "grad": e, "grad_worst_param": param}));
        }
    }
    // Where the image encoder's gradients disagree: its backward alone, cut in three (whole
    // encoder, backbone alone, neck alone), over the levels the model reads and over all levels.
    let mut encoder_cut_cases = Vec::new();
    if judged
        .iter()
        .any(|(name, e, _)| name.starts_with("encoder.") && *e > args.tol)
    {
        let image = frame(24);
        let all: Vec<usize> = (0..cpu_train.encoder.strides().len()).collect();
        for (what, levels) in [("levels 1 and 2", vec![1usize, 2]), ("all levels", all)] {
            let r = encoder_cuts(&cpu_train.encoder, &image, &levels, &cpu_dev);
            let t = encoder_cuts(&dev_train.encoder, &image, &levels, &dev);
            for ((cut, gt), (_, gr)) in t.iter().zip(&r) {
                let errs = grad_errors(gt, gr);
                let (e, param) = worst_grad(&errs);
                let off: Vec<&str> = errs
                    .iter()
                    .filter(|(_, e, _)| *e > args.tol)
                    .map(|(n, _, _)| n.as_str())
                    .collect();
                eprintln!(
                    "  encoder backward alone, {cut}, {what}: worst gradient rel err {e:.2e} \
                     ({param}); {} of {} beyond the tolerance: {}",
                    off.len(),
                    errs.len(),
                    off.join(" ")
                );
                encoder_cut_cases.push(serde_json::json!({"cut": cut, "levels": levels,
                    "grad": e, "grad_worst_param": param, "beyond_tolerance": off}));
            }
        }
    }
    results.push(
        serde_json::json!({"case": "sparseocc++_train_step", "loss": e_loss,
        "grad_params": grads_t.len(), "grad": e_grad, "grad_worst_param": worst_param,
        "grad_not_explained_by_kink": e_judged, "grad_not_explained_worst_param": judged_param,
        "rounding_perturbations": sensitivity.runs,
        "grads_beyond_tolerance": beyond_params, "grads_by_loss_kind": by_kind,
        "encoder_cuts": encoder_cut_cases}),
    );
    if let Some(p) = &args.json {
        crate::util::write_json(
            p,
            &serde_json::json!({"device": backend::describe(), "tolerance": args.tol, "worst": worst,
                "compiles_after_warmup": compiles_after_warmup,
                "compiles": compiles,
                "panics": PANICS.load(std::sync::atomic::Ordering::SeqCst),
                "kernel_compilations": backend::kernel_compilations(), "results": results}),
        )?;
    }
    let panics = PANICS.load(std::sync::atomic::Ordering::SeqCst);
    if panics > 0 {
        bail!(
            "{}: {panics} panic(s) in the backend's threads (reported above); its results cannot be trusted",
            backend::describe()
        );
    }
    if !finite {
        bail!(
            "SparseOcc++ produced non-finite logits on {}",
            backend::describe()
        );
    }
    check_compiles(compiles_after_warmup, &compiles, args)?;
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

/// Fails when the second frame compiled more kernels than `--max-compiles-after-warmup` allows.
fn check_compiles(
    compiles_after_warmup: Option<u64>,
    compiles: &CompileCounts,
    args: &CheckArgs,
) -> Result<()> {
    if compiles_after_warmup.is_some() && !compiles.voxel_count_changed() {
        bail!(
            "{}: no new frame changed the voxel count ({:?}), so the compile count tested no new \
             count; choose another --seed",
            backend::describe(),
            compiles.voxels
        );
    }
    if let Some(c) = compiles_after_warmup.filter(|&c| c > args.max_compiles_after_warmup) {
        bail!(
            "{}: {c} kernel(s) compiled for a second frame after the warm-up, more than the {} \
             allowed (set SPARSEOCC_LOG_COMPILES=1 to list them, =full for their ids)",
            backend::describe(),
            args.max_compiles_after_warmup
        );
    }
    Ok(())
}

/// Kernels compiled by the shipped configuration (`synthetic_tiny`: anchors pruned, so each image
/// gives its own voxel count) after its first frame.
#[derive(Debug, Clone, serde::Serialize)]
struct CompileCounts {
    /// The first frame run again: what burn-fusion's second pass over the same operations compiles
    /// (the first pass explores and stores execution plans; later passes run the stored plans,
    /// which can cut the stream into other fused blocks). Part of the warm-up.
    same_frame_again: Option<u64>,
    /// Each later frame (another image, so another voxel count) after that warm-up; the first of
    /// them is `compiles_after_warmup`.
    new_frames: Vec<Option<u64>>,
    /// Voxels of each run: the first frame, the first frame again, then the new frames.
    voxels: Vec<usize>,
}

impl CompileCounts {
    /// Whether some new frame had another voxel count than the warm-up frame.
    fn voxel_count_changed(&self) -> bool {
        self.voxels.iter().skip(2).any(|&v| v != self.voxels[0])
    }
}

/// Runs the first frame twice (the warm-up), then `frames - 1` frames of other images, counting
/// the kernels compiled for each run. `None`s on the CPU backend (nothing is compiled).
fn compile_counts(
    dev: &burn::tensor::Device<Infer>,
    frames: usize,
    seed: u64,
    warmup_seed: Option<u64>,
) -> Result<CompileCounts> {
    let default_cfg =
        occ_train::RunConfig::from_toml(occ_train::config::SYNTHETIC_TINY, "synthetic_tiny")?;
    // Seeded weights: which voxels a frame keeps follows the weights, and a run-to-run difference
    // there made the count differ between runs (2026-12-06: 2 of 3 unseeded full checks compiled
    // 2-3 kernels on a frame of about 262,100 voxels, none of 4 compile-only runs did).
    <Infer as Backend>::seed(dev, seed);
    let model = default_cfg.model.init::<Infer>(dev)?;
    let warm = match warmup_seed.filter(|&w| w != seed) {
        Some(w) => {
            <Infer as Backend>::seed(dev, w);
            Some(default_cfg.model.init::<Infer>(dev)?)
        }
        None => None,
    };
    let warm = warm.as_ref().unwrap_or(&model);
    let log = std::env::var_os("SPARSEOCC_LOG_COMPILES").is_some();
    let first = warm.forward(&tiny_batch(frame(21), None, dev))?;
    let mut voxels = first.coords.len();
    let mut voxel_counts = vec![voxels];
    let _ = to_vec(first.logits);
    let mut before = backend::settled_kernel_compilations();
    let mut counts = Vec::new();
    // Image seeds: the first again, then new ones.
    let seeds = std::iter::once(21).chain(22..21 + frames.max(2) as u64);
    for (run, seed) in seeds.enumerate() {
        if log {
            eprintln!(
                "-- run {} (image {seed}): kernels compiled from here on are counted --",
                run + 2
            );
        }
        let t0 = Instant::now();
        let net = if run == 0 { warm } else { &model };
        let out = net.forward(&tiny_batch(frame(seed), None, dev))?;
        let _ = to_vec(out.logits);
        let ms = t0.elapsed().as_secs_f64() * 1e3;
        let after = backend::settled_kernel_compilations();
        let count = before.zip(after).map(|(a, b)| b - a);
        eprintln!(
            "shipped configuration, run {} ({}): {} voxels (previous {voxels}), {ms:.1} ms, kernels compiled: {}",
            run + 2,
            if run == 0 { "the first frame again" } else { "a new frame" },
            out.coords.len(),
            count.map_or("n/a (CPU backend)".to_string(), |c| c.to_string())
        );
        voxels = out.coords.len();
        voxel_counts.push(voxels);
        before = after;
        counts.push(count);
    }
    Ok(CompileCounts {
        same_frame_again: counts[0],
        new_frames: counts[1..].to_vec(),
        voxels: voxel_counts,
    })
}

/// A 128x416 random image, seeded.
fn frame(seed: u64) -> Vec<f32> {
    let mut r = lcg(seed);
    (0..3 * 128 * 416).map(|_| r()).collect()
}

/// A one-frame batch of the `synthetic_tiny` setting (kitti-small grid, one 128x416 camera).
fn tiny_batch<Bk: Backend>(
    img: Vec<f32>,
    target: Option<Vec<Vec<u8>>>,
    device: &burn::tensor::Device<Bk>,
) -> occ_model::Batch<Bk> {
    occ_model::Batch {
        images: Tensor::from_data(TensorData::new(img, [1, 1, 3, 128, 416]), device),
        cameras: vec![vec![demo_camera()]],
        grid: occ_data::synthetic::Preset::KittiSmall.grid(),
        target,
        points: None,
    }
}

/// The training-step check's grid: the front 64x48x16 voxels of the kitti-small grid (0.4 m), the
/// camera's view centred in y.
fn train_grid() -> occ_geometry::VoxelGrid {
    let full = occ_data::synthetic::Preset::KittiSmall.grid();
    let dims = [64, 48, 16];
    let half_width_m = dims[1] as f64 * full.voxel_size_m / 2.0;
    occ_geometry::VoxelGrid {
        origin_m: [full.origin_m[0], -half_width_m, full.origin_m[2]],
        dims,
        ..full
    }
}

/// Labels for the training-step check on `dims`: a ground layer (class 9), a box (class 1) ahead
/// of the camera and an ignored column (255) in an empty scene (0).
fn tiny_labels(dims: [usize; 3]) -> Vec<Vec<u8>> {
    let (bx, by) = (dims[0] / 3, dims[1] / 2);
    let mut grid = vec![0u8; dims[0] * dims[1] * dims[2]];
    for x in 0..dims[0] {
        for y in 0..dims[1] {
            for z in 0..dims[2] {
                let i = (x * dims[1] + y) * dims[2] + z;
                grid[i] = if z < 2 {
                    9
                } else if (bx..bx + 12).contains(&x) && (by - 4..by + 4).contains(&y) && z < 5 {
                    1
                } else if x == bx + 14 && y == by + 6 {
                    255
                } else {
                    0
                };
            }
        }
    }
    vec![grid]
}

/// One training step's loss and parameter gradients; with `kind`, only the loss terms of that kind
/// (the name after the last `.`, e.g. `ce` for `occ.ce` and `anchor0.ce`) are back-propagated.
fn train_grads<Bk>(
    model: &occ_model::OccNet<Bk>,
    batch: &occ_model::Batch<Bk>,
    kind: Option<&str>,
) -> Result<TrainStep>
where
    Bk: burn::tensor::backend::AutodiffBackend + occ_model::kernels::ModelBackend,
{
    let out = model.forward(batch)?;
    let terms = out
        .losses
        .iter()
        .map(|(k, l)| {
            (
                k.to_string(),
                to_vec(l.clone()).first().copied().unwrap_or(f32::NAN),
            )
        })
        .collect();
    let loss = out
        .losses
        .iter()
        .filter(|(k, _)| kind.is_none_or(|kind| term_kind(&k.to_string()) == kind))
        .map(|(_, l)| l.clone())
        .reduce(|a, b| a + b)
        .context("the training step computed no loss")?;
    let loss_v = to_vec(loss.clone()).first().copied().unwrap_or(f32::NAN);
    let grads = loss.backward();
    Ok(TrainStep {
        loss: loss_v,
        terms,
        grads: param_grads(model, &grads),
    })
}

/// Gradients by parameter path, in a module's visiting order; `None` where one got no gradient.
type ParamGrads = Vec<(String, Option<Vec<f32>>)>;

/// The gradient of every trainable parameter of `module`, by path (`encoder.backbone.conv1.weight`),
/// in the module's visiting order; `None` where the parameter got no gradient.
fn param_grads<Bk, M>(module: &M, grads: &Bk::Gradients) -> ParamGrads
where
    Bk: burn::tensor::backend::AutodiffBackend,
    M: burn::module::Module<Bk>,
{
    struct Grads<'a, Bk: burn::tensor::backend::AutodiffBackend> {
        grads: &'a Bk::Gradients,
        path: Vec<String>,
        out: Vec<(String, Option<Vec<f32>>)>,
    }
    impl<Bk: burn::tensor::backend::AutodiffBackend> burn::module::ModuleVisitor<Bk> for Grads<'_, Bk> {
        fn enter_module(&mut self, name: &str, _container_type: &str) {
            self.path.push(name.to_string());
        }
        fn exit_module(&mut self, _name: &str, _container_type: &str) {
            self.path.pop();
        }
        fn visit_float<const D: usize>(&mut self, param: &burn::module::Param<Tensor<Bk, D>>) {
            // Batch-norm running statistics are state, not trainable parameters.
            if param.val().is_require_grad() {
                let g = param.val().grad(self.grads).map(to_vec);
                self.out.push((self.path.join("."), g));
            }
        }
    }
    let mut v = Grads::<Bk> {
        grads,
        path: Vec::new(),
        out: Vec::new(),
    };
    module.visit(&mut v);
    v.out
}

/// The image encoder's backward alone, in three cuts, each against the reference (a diagnostic
/// for gradients that differ in the training step): `Σ_l ⟨out_l, r_l⟩` over the FPN levels in
/// `levels` through the whole encoder, over every backbone output through the backbone alone, and
/// through the neck alone from the backbone outputs as leaves (their gradients included, as
/// `input{l}`), and through each residual block alone from its input as a leaf. Returns, per cut,
/// its name and the gradients by path.
fn encoder_cuts<Bk>(
    enc: &occ_model::encoder::fpn::ImageEncoder<Bk>,
    image: &[f32],
    levels: &[usize],
    dev: &burn::tensor::Device<Bk>,
) -> Vec<(String, ParamGrads)>
where
    Bk: burn::tensor::backend::AutodiffBackend + occ_model::kernels::ModelBackend,
{
    let img = || Tensor::<Bk, 4>::from_data(TensorData::new(image.to_vec(), [1, 3, 128, 416]), dev);
    let weights = |seed: u64, dims: [usize; 4]| {
        let mut r = lcg(seed);
        let v: Vec<f32> = (0..dims.iter().product::<usize>()).map(|_| r()).collect();
        Tensor::<Bk, 4>::from_data(TensorData::new(v, dims), dev)
    };
    let loss_over = |outs: Vec<Tensor<Bk, 4>>, keep: &dyn Fn(usize) -> bool| {
        outs.into_iter()
            .enumerate()
            .filter(|(l, _)| keep(*l))
            .map(|(l, t)| (t.clone() * weights(80 + l as u64, t.dims())).sum())
            .reduce(|a, b| a + b)
    };
    let mut cuts = Vec::new();
    if let Some(loss) = loss_over(enc.forward(img()), &|l| levels.contains(&l)) {
        cuts.push(("encoder".into(), param_grads(enc, &loss.backward())));
    }
    if let Some(loss) = loss_over(enc.backbone.forward(img()), &|_| true) {
        cuts.push((
            "backbone".into(),
            param_grads(&enc.backbone, &loss.backward()),
        ));
    }
    // Each residual block alone, from its input (the previous block's output) as a leaf.
    let bb = &enc.backbone;
    let stem = occ_model::encoder::backbone::stem_forward(bb, img());
    let mut x = Tensor::<Bk, 4>::from_data(stem.into_data(), dev);
    let stages = [&bb.layer1, &bb.layer2, &bb.layer3, &bb.layer4];
    for (si, stage) in stages.into_iter().enumerate() {
        for (bi, block) in stage.iter().enumerate() {
            let leaf = x.clone().require_grad();
            let y = block.forward(leaf.clone());
            let loss = (y.clone() * weights(90 + 10 * si as u64 + bi as u64, y.dims())).sum();
            let grads = loss.backward();
            let mut g = param_grads(block, &grads);
            g.push(("input".into(), leaf.grad(&grads).map(to_vec)));
            cuts.push((format!("layer{}.{bi}", si + 1), g));
            x = Tensor::from_data(y.into_data(), dev);
        }
    }
    let leaves: Vec<Tensor<Bk, 4>> = enc
        .backbone
        .forward(img())
        .into_iter()
        .map(|t| Tensor::from_data(t.into_data(), dev).require_grad())
        .collect();
    if let Ok(outs) = enc.neck.forward(leaves.clone()) {
        if let Some(loss) = loss_over(outs, &|l| levels.contains(&l)) {
            let grads = loss.backward();
            let mut g = param_grads(&enc.neck, &grads);
            for (l, t) in leaves.iter().enumerate() {
                g.push((format!("input{l}"), t.grad(&grads).map(to_vec)));
            }
            cuts.push(("neck".into(), g));
        }
    }
    cuts
}

/// The kind of a loss term: its name after the last `.`.
fn term_kind(name: &str) -> &str {
    name.rsplit('.').next().unwrap_or(name)
}

/// Each parameter gradient's relative error against the reference, with the largest reference
/// value: `(path, rel err, max |reference|)`. A parameter missing on one side, or steps with
/// different parameter lists, count as an infinite error.
fn grad_errors(t: &ParamGrads, r: &ParamGrads) -> Vec<(String, f64, f32)> {
    if t.len() != r.len() {
        return vec![("(different parameter lists)".into(), f64::INFINITY, 0.0)];
    }
    t.iter()
        .zip(r)
        .map(|((name, gt), (name_r, gr))| {
            let e = match (gt, gr) {
                _ if name != name_r => f64::INFINITY,
                (Some(a), Some(b)) => rel_err(a, b),
                (None, None) => 0.0,
                _ => f64::INFINITY,
            };
            let max_ref = gr
                .as_ref()
                .map_or(0.0, |b| b.iter().fold(0f32, |m, v| m.max(v.abs())));
            (name.clone(), e, max_ref)
        })
        .collect()
}

/// How much the reference's own gradients move when its weights move by a rounding-size amount:
/// the measure that tells a ReLU on its kink from a wrong backward.
///
/// The device computes the forward in f32 and the reference in f64; where a ReLU's input lies
/// within the f32 rounding of zero (measured on lavapipe, 2026-12-06: `+5.1e-7` in the reference,
/// `-6.6e-7` on the device, one hidden unit of the DCA block's FFN), the two sides take different
/// branches and the gradients of the layers around that unit differ by a whole row's contribution,
/// however right both backward passes are. An elementwise comparison cannot tell that from an
/// error. So where a gradient is beyond the tolerance, the reference's step is rerun
/// [`Self::RUNS`] times with every weight multiplied by `1 ± 2^-20` (a seeded sign per value:
/// rounding-size, like the f32 forward's own error); a gradient that moves under those
/// perturbations by at least half the device's difference sits on a kink at this step. A wrong
/// backward moves nothing in the reference and stays a failure, as does any difference beyond
/// [`Self::CEILING`] times the tolerance.
#[derive(Default)]
struct KinkSensitivity {
    /// Per parameter: the largest rel err of a perturbed reference gradient against the
    /// reference's.
    by_param: std::collections::HashMap<String, f64>,
    /// The perturbed reference steps run.
    runs: usize,
}

impl KinkSensitivity {
    /// Perturbed reference steps: each flips a kink within rounding with about even odds (a
    /// reference step of the check's model takes about a second on the CPU).
    const RUNS: usize = 6;
    /// The relative size of the weight perturbation (`2^-20`, about 8 f32 ulps).
    const DELTA: f64 = 1.0 / 1_048_576.0;
    /// Differences explained by a kink still fail beyond this many times the tolerance.
    const CEILING: f64 = 10.0;

    fn measure<Bk>(
        model: &occ_model::OccNet<Bk>,
        batch: &occ_model::Batch<Bk>,
        reference: &ParamGrads,
    ) -> Result<Self>
    where
        Bk: burn::tensor::backend::AutodiffBackend + occ_model::kernels::ModelBackend,
    {
        let mut out = Self::default();
        for run in 0..Self::RUNS {
            let t0 = Instant::now();
            let mut perturb = SignPerturbation {
                delta: Self::DELTA,
                rnd: lcg(100 + run as u64),
            };
            let perturbed = model.clone().map(&mut perturb);
            let step = train_grads(&perturbed, batch, None)?;
            for (name, e, _) in grad_errors(&step.grads, reference) {
                let s = out.by_param.entry(name).or_insert(0.0);
                *s = s.max(e);
            }
            out.runs += 1;
            eprintln!(
                "  reference step with weights x (1 ± 2^-20), seed {}: {:.1} s",
                100 + run,
                t0.elapsed().as_secs_f64()
            );
        }
        Ok(out)
    }

    /// The reference's sensitivity for parameter `name` (0 when not measured).
    fn of(&self, name: &str) -> f64 {
        self.by_param.get(name).copied().unwrap_or(0.0)
    }

    /// Whether a device difference `e` is what a kink within rounding makes, for a reference
    /// sensitivity `sens`.
    fn explains(e: f64, sens: f64, tol: f64) -> bool {
        e <= Self::CEILING * tol && 2.0 * sens >= e
    }
}

/// Multiplies every float parameter by `1 + delta` or `1 - delta` (a seeded sign per value),
/// keeping which parameters are trained.
struct SignPerturbation<R: FnMut() -> f32> {
    delta: f64,
    rnd: R,
}

impl<Bk, R> burn::module::ModuleMapper<Bk> for SignPerturbation<R>
where
    Bk: burn::tensor::backend::AutodiffBackend,
    R: FnMut() -> f32,
{
    fn map_float<const D: usize>(
        &mut self,
        param: burn::module::Param<Tensor<Bk, D>>,
    ) -> burn::module::Param<Tensor<Bk, D>> {
        param.map(|t| {
            let trained = t.is_require_grad();
            let inner = t.inner();
            let shape = inner.shape();
            let n = shape.num_elements();
            let factors: Vec<f64> = (0..n)
                .map(|_| {
                    if (self.rnd)() >= 0.0 {
                        1.0 + self.delta
                    } else {
                        1.0 - self.delta
                    }
                })
                .collect();
            let factors = Tensor::<Bk::InnerBackend, 1>::from_data(
                TensorData::new(factors, [n]),
                &inner.device(),
            )
            .reshape(shape);
            let t = Tensor::from_inner(inner * factors);
            if trained {
                t.require_grad()
            } else {
                t
            }
        })
    }
}

/// The worst of [`grad_errors`] and its parameter.
fn worst_grad(errs: &[(String, f64, f32)]) -> (f64, String) {
    errs.iter()
        .fold((0f64, String::new()), |(w, p), (name, e, _)| {
            if *e > w || p.is_empty() {
                (w.max(*e), name.clone())
            } else {
                (w, p)
            }
        })
}

/// What [`train_grads`] measures of one training step.
struct TrainStep {
    /// The total loss.
    loss: f32,
    /// Each loss term, by name.
    terms: Vec<(String, f32)>,
    /// The gradient of every trainable parameter, by path, in the module's visiting order.
    grads: ParamGrads,
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

/// The inputs of the DCA sampling check, on the host: 600 queries seen by one or two of two
/// 128x416 images, 2 levels (strides 8 and 16), 4 heads, 4 points, width 32.
struct DcaCase {
    hits: occ_model::kernels::ViewHits,
    strides: [usize; 2],
    values: Vec<TensorData>,
    offsets: TensorData,
    weights: TensorData,
    gate: TensorData,
}

fn dca_inputs() -> DcaCase {
    let (n, m, l, p, d) = (600usize, 4usize, 2usize, 4usize, 32usize);
    let (h, w) = (128usize, 416usize);
    let strides = [8usize, 16];
    let mut r = lcg(17);
    let mut hits = occ_model::kernels::ViewHits {
        num_queries: n,
        num_images: 2,
        query: Vec::new(),
        image: Vec::new(),
        slot: Vec::new(),
        uv: Vec::new(),
        depth_m: Vec::new(),
        views_per_query: vec![0; n],
        max_per_image: 0,
    };
    for img in 0..2u32 {
        let mut slot = 0u32;
        for q in 0..n {
            if (q + img as usize).is_multiple_of(3) {
                continue;
            }
            hits.query.push(q as u32);
            hits.image.push(img);
            hits.slot.push(slot);
            hits.uv.push([
                (r() as f64 * 0.5 + 0.5) * (w - 1) as f64,
                (r() as f64 * 0.5 + 0.5) * (h - 1) as f64,
            ]);
            hits.depth_m.push(5.0 + 20.0 * (r() as f64 * 0.5 + 0.5));
            hits.views_per_query[q] += 1;
            slot += 1;
        }
        hits.max_per_image = hits.max_per_image.max(slot as usize);
    }
    let values = strides
        .iter()
        .map(|s| {
            let (hl, wl) = (h / s, w / s);
            TensorData::new(
                (0..2 * hl * wl * d).map(|_| r()).collect::<Vec<f32>>(),
                [2, hl, wl, d],
            )
        })
        .collect();
    let offsets = TensorData::new(
        (0..n * m * l * p * 2)
            .map(|_| 3.0 * r())
            .collect::<Vec<f32>>(),
        [n, m, l, p, 2],
    );
    let weights = TensorData::new(
        (0..n * m * l * p)
            .map(|_| 0.5 + 0.5 * r())
            .collect::<Vec<f32>>(),
        [n, m, l, p],
    );
    let gate = TensorData::new(
        (0..hits.query.len())
            .map(|_| 0.5 + 0.5 * r())
            .collect::<Vec<f32>>(),
        [hits.query.len()],
    );
    DcaCase {
        hits,
        strides,
        values,
        offsets,
        weights,
        gate,
    }
}

/// DCA sampling on the autodiff backend `Bk`: the output, then the gradients of `sum(y²)` with
/// respect to the two value maps, the offsets, the weights and the gate, all flattened.
fn dca_run<Bk>(
    case: &DcaCase,
    device: &burn::tensor::Device<Bk>,
    sample: impl Fn(occ_model::kernels::DcaSample<'_, Bk>) -> Tensor<Bk, 2>,
) -> Result<Vec<Vec<f32>>>
where
    Bk: burn::tensor::backend::AutodiffBackend + occ_model::kernels::ModelBackend,
{
    let values: Vec<Tensor<Bk, 4>> = case
        .values
        .iter()
        .map(|v| Tensor::from_data(v.clone(), device).require_grad())
        .collect();
    let offsets = Tensor::<Bk, 5>::from_data(case.offsets.clone(), device).require_grad();
    let weights = Tensor::<Bk, 4>::from_data(case.weights.clone(), device).require_grad();
    let gate = Tensor::<Bk, 1>::from_data(case.gate.clone(), device).require_grad();
    let y = sample(occ_model::kernels::DcaSample {
        hits: &case.hits,
        strides: &case.strides,
        values: occ_model::kernels::FeatureRows::from_channel_last(values.clone()),
        offsets: offsets.clone(),
        weights: weights.clone(),
        gate: Some(gate.clone()),
    });
    let grads = y.clone().powf_scalar(2.0).sum().backward();
    let mut out = vec![to_vec(y)];
    for v in &values {
        out.push(to_vec(
            v.grad(&grads).context("DCA: no gradient of a value map")?,
        ));
    }
    out.push(to_vec(
        offsets.grad(&grads).context("DCA: no offset gradient")?,
    ));
    out.push(to_vec(
        weights.grad(&grads).context("DCA: no weight gradient")?,
    ));
    out.push(to_vec(gate.grad(&grads).context("DCA: no gate gradient")?));
    Ok(out)
}

/// The DCA sampling forward on the inference backend `Bk` (no autodiff), flattened.
fn dca_forward<Bk: occ_model::kernels::ModelBackend>(
    case: &DcaCase,
    device: &burn::tensor::Device<Bk>,
) -> Vec<f32> {
    let y = Bk::dca_sample(occ_model::kernels::DcaSample {
        hits: &case.hits,
        strides: &case.strides,
        values: occ_model::kernels::FeatureRows::from_channel_last(
            case.values
                .iter()
                .map(|v| Tensor::from_data(v.clone(), device))
                .collect(),
        ),
        offsets: Tensor::from_data(case.offsets.clone(), device),
        weights: Tensor::from_data(case.weights.clone(), device),
        gate: Some(Tensor::from_data(case.gate.clone(), device)),
    });
    to_vec(y)
}

/// The DCA sampling op on the backend under test against the NdArray reference: the largest
/// relative error over the output and every gradient, and its JSON entry. Checked: the inference
/// forward (`inference_forward`), the shipped training path (`forward`, `grad_*`) and, on the
/// cubecl builds, the `#[cube]` training op whatever the shipped choice (`cube_train_*`).
fn dca_case(
    cpu_dev: &burn::tensor::Device<Cpu>,
    dev: &burn::tensor::Device<Infer>,
) -> Result<(f64, serde_json::Value)> {
    use occ_model::kernels::ModelBackend;
    let case = dca_inputs();
    let reference = dca_run::<Autodiff<Cpu>>(&case, cpu_dev, <Autodiff<Cpu>>::dca_sample)?;
    #[cfg_attr(not(any(feature = "cuda", feature = "wgpu")), allow(unused_mut))]
    let mut runs = vec![("", dca_run::<Train>(&case, dev, Train::dca_sample)?)];
    #[cfg(any(feature = "cuda", feature = "wgpu"))]
    runs.push((
        "cube_train_",
        dca_run::<Train>(&case, dev, backend::cube_dca_train)?,
    ));
    let names = [
        "forward",
        "grad_values_l0",
        "grad_values_l1",
        "grad_offsets",
        "grad_weights",
        "grad_gate",
    ];
    let mut entry = serde_json::json!({"case": "dca_sample", "hits": case.hits.len()});
    let e = rel_err(&dca_forward::<Infer>(&case, dev), &reference[0]);
    let mut worst = e;
    entry["inference_forward"] = serde_json::json!(e);
    let mut line = format!(", inference_forward {e:.2e}");
    for (prefix, tested) in &runs {
        for ((name, a), b) in names.iter().zip(tested).zip(&reference) {
            let e = rel_err(a, b);
            worst = worst.max(e);
            entry[format!("{prefix}{name}")] = serde_json::json!(e);
            line.push_str(&format!(", {prefix}{name} {e:.2e}"));
        }
    }
    eprintln!("dca_sample: {} hits{line}", case.hits.len());
    Ok((worst, entry))
}

/// Runs `scatter_add_rows`, `gather_rows` and `pad_rows` (to the cubecl row bucket) with their
/// gradients on `Bk`.
fn rows_run<Bk>(
    plan: &Arc<occ_sparse::RowPlan>,
    v: &[f32],
    x: &[f32],
    cols: usize,
    device: &burn::tensor::Device<Bk>,
) -> Result<Vec<Vec<f32>>>
where
    Bk: burn::tensor::backend::AutodiffBackend + occ_sparse::SparseConvBackend,
{
    let vt = Tensor::<Bk, 2>::from_data(TensorData::new(v.to_vec(), [plan.n_in(), cols]), device)
        .require_grad();
    let xt = Tensor::<Bk, 2>::from_data(TensorData::new(x.to_vec(), [plan.n_out(), cols]), device)
        .require_grad();
    // The pad's input: the gathered rows' values, a leaf of its own (its gradient apart).
    let pt = Tensor::<Bk, 2>::from_data(TensorData::new(x.to_vec(), [plan.n_out(), cols]), device)
        .require_grad();
    let s = occ_sparse::scatter_add_rows(vt.clone(), plan);
    let g = occ_sparse::gather_rows(xt.clone(), plan);
    let p = occ_sparse::pad_rows(pt.clone(), RowBucket::CUBECL.padded(plan.n_out()));
    // Non-uniform upstream gradients: squares (and a row-dependent weight on the pad, whose zero
    // rows the square would not see).
    let w = Tensor::<Bk, 1, Int>::arange(0..p.dims()[0] as i64, device)
        .float()
        .reshape([p.dims()[0], 1]);
    let grads = (s.clone().powf_scalar(2.0).sum()
        + g.clone().powf_scalar(2.0).sum()
        + (p.clone().powf_scalar(2.0) + p.clone() * w).sum())
    .backward();
    Ok(vec![
        to_vec(s),
        to_vec(g),
        to_vec(vt.grad(&grads).context("no grad of the scattered rows")?),
        to_vec(xt.grad(&grads).context("no grad of the gathered rows")?),
        to_vec(p),
        to_vec(pt.grad(&grads).context("no grad of the padded rows")?),
    ])
}

/// One image convolution of the encoder's kind: `[1, cin, h, w]` by a `k x k` kernel to `cout`
/// channels at `stride`, padding `k / 2`.
#[derive(Clone, Copy, Debug)]
struct Conv2dShape {
    cin: usize,
    cout: usize,
    h: usize,
    w: usize,
    k: usize,
    stride: usize,
}

/// `conv2d` with bias, and the gradients of `Σ y ⊙ r` with respect to input, weight and bias.
fn conv2d_run<Bk: burn::tensor::backend::AutodiffBackend + occ_model::kernels::ModelBackend>(
    c: Conv2dShape,
    inputs: [&[f32]; 4],
    ours: bool,
    dev: &burn::tensor::Device<Bk>,
) -> Vec<Vec<f32>> {
    let [x, w, b, r] = inputs;
    fn t<Bk: Backend, const D: usize>(
        v: &[f32],
        shape: [usize; D],
        dev: &burn::tensor::Device<Bk>,
    ) -> Tensor<Bk, D> {
        Tensor::from_data(TensorData::new(v.to_vec(), shape), dev)
    }
    let xt = t::<Bk, 4>(x, [1, c.cin, c.h, c.w], dev).require_grad();
    let wt = t::<Bk, 4>(w, [c.cout, c.cin, c.k, c.k], dev).require_grad();
    let bt = t::<Bk, 1>(b, [c.cout], dev).require_grad();
    let pad = c.k / 2;
    let y = if ours {
        // The model's path in training (`conv_bn` without BN: on the cubecl backends im2col +
        // matrix product with a col2im backward, `ModelBackend::conv2d_autodiff`).
        let mut conv = burn::nn::conv::Conv2dConfig::new([c.cin, c.cout], [c.k, c.k])
            .with_stride([c.stride; 2])
            .with_padding(burn::nn::PaddingConfig2d::Explicit(pad, pad, pad, pad))
            .init::<Bk>(dev);
        conv.weight = burn::module::Param::from_tensor(wt.clone());
        conv.bias = Some(burn::module::Param::from_tensor(bt.clone()));
        occ_model::kernels::conv2d_host::conv_bn(&conv, None, xt.clone(), false)
    } else {
        burn::tensor::module::conv2d(
            xt.clone(),
            wt.clone(),
            Some(bt.clone()),
            burn::tensor::ops::ConvOptions::new([c.stride; 2], [pad; 2], [1, 1], 1),
        )
    };
    let rt = t::<Bk, 4>(r, y.dims(), dev);
    let grads = (y.clone() * rt).sum().backward();
    // A missing gradient is a NaN, so that it cannot compare equal to another missing one.
    let grad = |g: Option<Vec<f32>>| g.unwrap_or_else(|| vec![f32::NAN]);
    vec![
        to_vec(y),
        grad(xt.grad(&grads).map(to_vec)),
        grad(wt.grad(&grads).map(to_vec)),
        grad(bt.grad(&grads).map(to_vec)),
    ]
}

/// An image convolution's forward and gradients on the backend under test, computed as the image
/// encoder computes it there in training (`conv_bn`), against the CPU reference (burn's own
/// conv2d and its backward); burn's own conv2d on the backend under test is reported beside it
/// (`burn_*`, not counted: the model avoids it where it is wrong, strided 1x1 convolutions).
fn conv2d_case(
    c: Conv2dShape,
    cpu_dev: &burn::tensor::Device<Cpu>,
    dev: &burn::tensor::Device<Infer>,
) -> (f64, serde_json::Value) {
    let mut r = lcg((c.cin * 1000 + c.h * 10 + c.k) as u64);
    let pad = c.k / 2;
    let (ho, wo) = (
        (c.h + 2 * pad - c.k) / c.stride + 1,
        (c.w + 2 * pad - c.k) / c.stride + 1,
    );
    let mut draw = |n: usize| (0..n).map(|_| r()).collect::<Vec<f32>>();
    let x = draw(c.cin * c.h * c.w);
    let w = draw(c.cout * c.cin * c.k * c.k);
    let b = draw(c.cout);
    let rr = draw(c.cout * ho * wo);
    let inputs = [&x[..], &w[..], &b[..], &rr[..]];
    let reference = conv2d_run::<Autodiff<Cpu>>(c, inputs, false, cpu_dev);
    let got = conv2d_run::<Train>(c, inputs, true, dev);
    let burns = conv2d_run::<Train>(c, inputs, false, dev);
    let name = format!(
        "conv2d_{}x{}_s{}_{}x{}x{}_to_{}",
        c.k, c.k, c.stride, c.cin, c.h, c.w, c.cout
    );
    let mut case = serde_json::json!({"case": name});
    let mut worst = 0f64;
    let mut line = String::new();
    for ((key, a), b) in ["forward", "dx", "dw", "db"]
        .iter()
        .zip(&got)
        .zip(&reference)
    {
        let e = rel_err(a, b);
        case[*key] = serde_json::json!(e);
        worst = worst.max(e);
        line.push_str(&format!(", {key} {e:.2e} ({} values)", a.len()));
    }
    line.push_str("; burn's own conv2d:");
    for ((key, a), b) in ["forward", "dx", "dw", "db"]
        .iter()
        .zip(&burns)
        .zip(&reference)
    {
        let e = rel_err(a, b);
        case[format!("burn_{key}")] = serde_json::json!(e);
        line.push_str(&format!(" {key} {e:.2e}"));
    }
    eprintln!("{name}: rel err{line}");
    (worst, case)
}

/// The image convolutions in inference as the model runs them on the backend
/// (`occ_model::kernels::conv2d_host::conv_bn`: on the cubecl backends im2col + matrix product)
/// against the CPU reference's: several images, asymmetric padding, dilation, a pointwise and a
/// strided pointwise convolution, and one whose unfolding runs in two column blocks.
fn conv2d_inference_cases(
    cpu_dev: &burn::tensor::Device<Cpu>,
    dev: &burn::tensor::Device<Infer>,
) -> Vec<serde_json::Value> {
    use burn::nn::conv::{Conv2d, Conv2dConfig};
    use burn::nn::PaddingConfig2d;
    use occ_model::kernels::conv2d_host::conv_bn;
    // (name, images, cin, cout, h, w, kernel, stride, padding (t, l, b, r), dilation)
    #[allow(clippy::type_complexity)]
    let cases: [(
        &str,
        usize,
        usize,
        usize,
        usize,
        usize,
        [usize; 2],
        [usize; 2],
        [usize; 4],
        [usize; 2],
    ); 5] = [
        (
            "conv2d_infer_b3_k3_s2_pad_asym",
            3,
            5,
            7,
            19,
            23,
            [3, 3],
            [2, 2],
            [1, 0, 2, 1],
            [1, 1],
        ),
        (
            "conv2d_infer_b2_k3x5_dil2",
            2,
            4,
            6,
            17,
            21,
            [3, 5],
            [1, 1],
            [2, 4, 2, 4],
            [2, 2],
        ),
        (
            "conv2d_infer_b3_pointwise",
            3,
            6,
            5,
            9,
            11,
            [1, 1],
            [1, 1],
            [0; 4],
            [1, 1],
        ),
        (
            "conv2d_infer_b2_pointwise_s2",
            2,
            6,
            5,
            9,
            11,
            [1, 1],
            [2, 2],
            [0; 4],
            [1, 1],
        ),
        // 576 unfolded rows x 60,000 positions: more than one block of 2^25 values.
        (
            "conv2d_infer_k3_two_blocks",
            1,
            64,
            8,
            200,
            300,
            [3, 3],
            [1, 1],
            [1; 4],
            [1, 1],
        ),
    ];
    let mut out = Vec::new();
    for (i, (name, n, cin, cout, h, w, k, stride, [t, l, b, r], dil)) in
        cases.into_iter().enumerate()
    {
        let mut rnd = lcg(900 + i as u64);
        let mut draw = |len: usize| (0..len).map(|_| rnd()).collect::<Vec<f32>>();
        let x = draw(n * cin * h * w);
        let wv = draw(cout * cin * k[0] * k[1]);
        let bv = draw(cout);
        fn conv<Bk: Backend>(
            cfg: &Conv2dConfig,
            w: &[f32],
            b: &[f32],
            dev: &burn::tensor::Device<Bk>,
        ) -> Conv2d<Bk> {
            let mut c = cfg.init::<Bk>(dev);
            let [o, i, kh, kw] = c.weight.dims();
            c.weight = burn::module::Param::from_tensor(Tensor::from_data(
                TensorData::new(w.to_vec(), [o, i, kh, kw]),
                dev,
            ));
            c.bias = Some(burn::module::Param::from_tensor(Tensor::from_data(
                TensorData::new(b.to_vec(), [o]),
                dev,
            )));
            c
        }
        let cfg = Conv2dConfig::new([cin, cout], k)
            .with_stride(stride)
            .with_dilation(dil)
            .with_padding(PaddingConfig2d::Explicit(t, l, b, r));
        let xs = [n, cin, h, w];
        let reference = conv_bn(
            &conv::<Cpu>(&cfg, &wv, &bv, cpu_dev),
            None,
            Tensor::<Cpu, 4>::from_data(TensorData::new(x.clone(), xs), cpu_dev),
            false,
        );
        let got = conv_bn(
            &conv::<Infer>(&cfg, &wv, &bv, dev),
            None,
            Tensor::<Infer, 4>::from_data(TensorData::new(x, xs), dev),
            false,
        );
        let (dims_ref, dims_got) = (reference.dims(), got.dims());
        let e = if dims_ref == dims_got {
            rel_err(&to_vec(got), &to_vec(reference))
        } else {
            f64::INFINITY
        };
        eprintln!("{name}: {dims_got:?} (reference {dims_ref:?}), rel err {e:.2e}");
        out.push(serde_json::json!({"case": name, "forward": e, "shape": dims_got}));
    }
    out
}

/// The other ops of the image encoder's backward, each on a seeded input with the gradient of
/// `Σ y ⊙ r`: the FPN's nearest upsampling by 2 (`resize_nearest`) from 4x13, 8x26 and 16x52, each
/// also with `r` laid out channels-last (`*_nhwc_dx`; burn's own `interpolate` there too, reported
/// as `burn_interpolate_*` and not counted: its backward is wrong on cubecl then), the stem's
/// 3x3 stride-2 max pool, and the two-level BatchNorm (`occ_sparse::norm::batch_norm`) with its
/// gamma and beta.
fn encoder_ops_run<Bk: burn::tensor::backend::AutodiffBackend + occ_sparse::SparseConvBackend>(
    dev: &burn::tensor::Device<Bk>,
) -> Vec<Vec<f32>> {
    use burn::tensor::module::{interpolate, max_pool2d};
    use burn::tensor::ops::{InterpolateMode, InterpolateOptions};
    let input = |seed: u64, shape: [usize; 4]| {
        let mut r = lcg(seed);
        let v: Vec<f32> = (0..shape.iter().product::<usize>()).map(|_| r()).collect();
        Tensor::<Bk, 4>::from_data(TensorData::new(v, shape), dev).require_grad()
    };
    let weights = |seed: u64, shape: [usize; 4]| {
        let mut r = lcg(seed);
        let v: Vec<f32> = (0..shape.iter().product::<usize>()).map(|_| r()).collect();
        Tensor::<Bk, 4>::from_data(TensorData::new(v, shape), dev)
    };
    let mut out = Vec::new();
    let nearest = |x: Tensor<Bk, 4>, size: [usize; 2], ours: bool| {
        if ours {
            occ_model::encoder::fpn::resize_nearest(x, size)
        } else {
            interpolate(
                x,
                size,
                InterpolateOptions::new(InterpolateMode::Nearest).with_align_corners(false),
            )
        }
    };
    for (i, (h, w)) in [(4usize, 13usize), (8, 26), (16, 52)]
        .into_iter()
        .enumerate()
    {
        // The model's upsampling, then, with the output gradient laid out channels-last (as a
        // convolution's backward can hand it over: `r` made `[1, 2h, 2w, 32]`, permuted to NCHW),
        // the model's and burn's `interpolate` (reported, not counted: the model does not use it).
        let x = input(40 + i as u64, [1, 32, h, w]);
        let y = nearest(x.clone(), [2 * h, 2 * w], true);
        let grads = (y.clone() * weights(50 + i as u64, y.dims()))
            .sum()
            .backward();
        out.push(to_vec(y));
        out.push(x.grad(&grads).map_or(vec![f32::NAN], to_vec));
        for ours in [true, false] {
            let x = input(40 + i as u64, [1, 32, h, w]);
            let y = nearest(x.clone(), [2 * h, 2 * w], ours);
            let r = weights(55 + i as u64, [1, 2 * h, 2 * w, 32]).permute([0, 3, 1, 2]);
            let grads = (y * r).sum().backward();
            out.push(x.grad(&grads).map_or(vec![f32::NAN], to_vec));
        }
    }
    let x = input(60, [1, 16, 64, 208]);
    let y = max_pool2d(x.clone(), [3, 3], [2, 2], [1, 1], [1, 1], false);
    let grads = (y.clone() * weights(61, y.dims())).sum().backward();
    out.push(to_vec(y));
    out.push(x.grad(&grads).map_or(vec![f32::NAN], to_vec));
    let bn = burn::nn::BatchNormConfig::new(32).init::<Bk>(dev);
    let x = input(70, [1, 32, 16, 52]);
    let y = occ_sparse::norm::batch_norm(&bn, x.clone());
    let grads = (y.clone() * weights(71, y.dims())).sum().backward();
    out.push(to_vec(y));
    out.push(x.grad(&grads).map_or(vec![f32::NAN], to_vec));
    out.push(bn.gamma.val().grad(&grads).map_or(vec![f32::NAN], to_vec));
    out.push(bn.beta.val().grad(&grads).map_or(vec![f32::NAN], to_vec));
    out
}

/// [`encoder_ops_run`] on the backend under test against the CPU reference.
fn encoder_ops_case(
    cpu_dev: &burn::tensor::Device<Cpu>,
    dev: &burn::tensor::Device<Infer>,
) -> (f64, serde_json::Value) {
    let reference = encoder_ops_run::<Autodiff<Cpu>>(cpu_dev);
    let got = encoder_ops_run::<Train>(dev);
    let names = [
        "upsample_4x13",
        "upsample_4x13_dx",
        "upsample_4x13_nhwc_dx",
        "burn_interpolate_4x13_nhwc_dx",
        "upsample_8x26",
        "upsample_8x26_dx",
        "upsample_8x26_nhwc_dx",
        "burn_interpolate_8x26_nhwc_dx",
        "upsample_16x52",
        "upsample_16x52_dx",
        "upsample_16x52_nhwc_dx",
        "burn_interpolate_16x52_nhwc_dx",
        "max_pool_3x3_s2",
        "max_pool_3x3_s2_dx",
        "batch_norm",
        "batch_norm_dx",
        "batch_norm_dgamma",
        "batch_norm_dbeta",
    ];
    let mut case = serde_json::json!({"case": "encoder_ops"});
    let mut worst = 0f64;
    let mut line = String::new();
    for ((name, a), b) in names.iter().zip(&got).zip(&reference) {
        let e = rel_err(a, b);
        case[*name] = serde_json::json!(e);
        if !name.starts_with("burn_") {
            worst = worst.max(e);
        }
        line.push_str(&format!(", {name} {e:.2e}"));
    }
    eprintln!("encoder ops: rel err{line}");
    (worst, case)
}

/// Scatter-add of `h` rows into `n_out` (random destinations), the gather back and the `n_out`
/// rows padded to their row bucket, on the backend under test against the CPU reference.
fn rows_case(
    h: usize,
    n_out: usize,
    cols: usize,
    cpu_dev: &burn::tensor::Device<Cpu>,
    dev: &burn::tensor::Device<Infer>,
) -> Result<(f64, serde_json::Value)> {
    let mut r = lcg(h as u64 ^ n_out as u64);
    let dest: Vec<u32> = (0..h)
        .map(|_| (((r() + 1.0) * 0.5 * n_out as f32) as usize).min(n_out - 1) as u32)
        .collect();
    let plan = Arc::new(occ_sparse::RowPlan::new(dest, n_out)?);
    let v: Vec<f32> = (0..h * cols).map(|_| r()).collect();
    let x: Vec<f32> = (0..n_out * cols).map(|_| r()).collect();
    let reference = rows_run::<Autodiff<Cpu>>(&plan, &v, &x, cols, cpu_dev)?;
    let got = rows_run::<Train>(&plan, &v, &x, cols, dev)?;
    let names = [
        "scatter",
        "gather",
        "grad_scatter",
        "grad_gather",
        "pad",
        "grad_pad",
    ];
    let mut case = serde_json::json!({
        "case": format!("rows_{h}_to_{n_out}x{cols}"),
        "max_segment": plan.max_segment(),
    });
    let mut worst = 0f64;
    for ((name, a), b) in names.iter().zip(&got).zip(&reference) {
        let e = rel_err(a, b);
        case[*name] = serde_json::json!(e);
        worst = worst.max(e);
    }
    eprintln!("rows {h} -> {n_out} x {cols}: {case}");
    Ok((worst, case))
}
