//! `sparseocc bench`: latency, FPS, peak memory and active voxels per stage of the three models on
//! the same input, side by side; optionally a memory-vs-resolution scan (grid scale 1/4, 1/2, 1)
//! written as JSON and a PNG plot.
//!
//! Each (model, grid scale) runs in its own child process (`sparseocc bench --single ...`) so that its
//! peak resident memory (`VmHWM`) is its own. The input is one synthetic frame of the preset that
//! matches the config's grid (SemanticKITTI: 256x256x32 with a 1226x370 image), generated once,
//! loaded and resized by the test-time pipeline to the config's input size; the weights are random
//! (timing does not depend on them, except through the number of voxels a trained model keeps — see
//! the notes in BENCHMARKS.md). Image decoding is excluded from the timings; the forward pass
//! includes everything from the image tensor to the class logits, and the dense class grid.
//!
//! FLOPs: the profiled passes also count every stage's multiply-adds ([`occ_model::profile`]; sparse
//! convs from their pair counts, dense convs and linears from shapes, DCA from its samples, attention
//! from its sizes), reported as GFLOP = 2 x MACs / 1e9, so that a stage's GFLOP/s compares with the
//! machine's sgemm rate, measured in the same run by [`sgemm_gflops`].

use crate::backend::{self, Infer};
use crate::util::ModelArg;
use anyhow::{bail, Context, Result};
use occ_data::synthetic::{self, Preset, SynthConfig};
use occ_model::OccNet;
use occ_train::dataset::{collate, Dataset, DatasetFormat};
use occ_train::RunConfig;
use occ_viz::plot::{line_plot, PlotSpec, Series};
use serde::{Deserialize, Serialize};
use std::path::{Path, PathBuf};
use std::time::Instant;

/// Arguments of `sparseocc bench`.
#[derive(clap::Args, Debug)]
pub struct BenchArgs {
    /// Run configuration (TOML) giving the input size, backbone and grid.
    #[arg(long)]
    pub config: PathBuf,
    /// Models to compare (comma-separated).
    #[arg(
        long,
        value_delimiter = ',',
        default_value = "sparseocc++,sparseocc,dense"
    )]
    pub models: Vec<ModelArg>,
    /// Timed frames per model (after the warm-up).
    #[arg(long, default_value_t = 5)]
    pub frames: usize,
    /// Warm-up frames (not timed).
    #[arg(long, default_value_t = 1)]
    pub warmup: usize,
    /// Write the results as JSON here.
    #[arg(long)]
    pub json: Option<PathBuf>,
    /// Also scan peak memory against grid scale 1/4, 1/2, 1; writes PREFIX.json and PREFIX.png.
    #[arg(long)]
    pub scan: Option<PathBuf>,
    /// Frames per point of the scan.
    #[arg(long, default_value_t = 1)]
    pub scan_frames: usize,
    /// Internal: run one model in this process and print its JSON.
    #[arg(long, hide = true)]
    pub single: bool,
    /// Internal: divide the grid by this factor.
    #[arg(long, hide = true, default_value_t = 1)]
    pub grid_divisor: usize,
    /// Internal: the synthetic dataset to read (made by the parent).
    #[arg(long, hide = true)]
    pub data: Option<PathBuf>,
}

/// One model's measurements.
#[derive(Clone, Debug, Serialize, Deserialize)]
pub struct BenchResult {
    /// Model name.
    pub model: String,
    /// Device and precision.
    pub device: String,
    /// Grid the model predicts for (full resolution).
    pub full_dims: [usize; 3],
    /// Network input `(width, height)`.
    pub image: (usize, usize),
    /// Backbone depth.
    pub resnet_depth: usize,
    /// Parameters.
    pub params: usize,
    /// Per-frame forward latency (ms), in order.
    pub latency_ms: Vec<f64>,
    /// Median latency (ms).
    pub median_ms: f64,
    /// 10th / 90th percentile (ms).
    pub p10_ms: f64,
    /// See `p10_ms`.
    pub p90_ms: f64,
    /// Frames per second at the median latency.
    pub fps: f64,
    /// Peak resident set of the process (MiB; `VmHWM`).
    pub peak_rss_mib: f64,
    /// Resident set before the model was built (MiB).
    pub base_rss_mib: f64,
    /// Device memory used by the process after the runs (MiB; CUDA only, from nvidia-smi).
    pub device_mem_mib: Option<f64>,
    /// Active voxels (and other counts) per stage, from the last frame.
    pub stages: Vec<(String, usize)>,
    /// What the timing covers.
    pub timing_covers: String,
    /// Where the time goes: mean ms per stage over the profiled frames (a separate pass that
    /// synchronises after each stage; not part of the latency figures above).
    pub profile_ms: Vec<(String, f64)>,
    /// Counted work of one forward pass: GFLOP (2 FLOPs per multiply-add).
    pub gflops: f64,
    /// `gflops` over the median latency (GFLOP/s).
    pub gflops_per_s: f64,
    /// `gflops` over the profiled passes' mean total time (GFLOP/s; comparable with the stages').
    pub profile_gflops_per_s: f64,
    /// Per stage of the profiled passes: mean ms, GFLOP, GFLOP/s and the shares of the total.
    pub profile_stages: Vec<StageProfile>,
    /// GFLOP of one forward pass by kind of op (`linear`, `conv2d`, `sparse_conv`, `dca_sampling`, ...).
    pub gflops_by_op: Vec<(String, f64)>,
    /// Kernels compiled during the timed frames, after the warm-up (cubecl backends; `None` on the
    /// CPU, which compiles nothing). Anything above 0 is a compilation inside a frame's latency.
    pub compiles_after_warmup: Option<u64>,
}

/// One stage of the profiled passes.
#[derive(Clone, Debug, Serialize, Deserialize)]
pub struct StageProfile {
    /// Stage name.
    pub stage: String,
    /// Mean wall time (ms).
    pub ms: f64,
    /// Counted work (GFLOP, 2 per multiply-add).
    pub gflops: f64,
    /// `gflops` over `ms` (GFLOP/s).
    pub gflops_per_s: f64,
    /// Share of the pass's time.
    pub time_share: f64,
    /// Share of the pass's FLOPs.
    pub flop_share: f64,
}

/// Stage names under which the models report the voxels they predict on.
const FINAL_KEYS: [&str; 3] = ["final", "out.sites", "dense.voxels"];

fn status_kib(key: &str) -> Option<f64> {
    let s = std::fs::read_to_string("/proc/self/status").ok()?;
    s.lines()
        .find(|l| l.starts_with(key))?
        .split_whitespace()
        .nth(1)?
        .parse()
        .ok()
}

fn gpu_mem_mib() -> Option<f64> {
    if !cfg!(feature = "cuda") {
        return None;
    }
    let out = std::process::Command::new("nvidia-smi")
        .args([
            "--query-compute-apps=pid,used_memory",
            "--format=csv,noheader,nounits",
        ])
        .output()
        .ok()?;
    let me = std::process::id().to_string();
    String::from_utf8_lossy(&out.stdout)
        .lines()
        .filter_map(|l| {
            let mut it = l.split(',').map(str::trim);
            (it.next()? == me).then(|| it.next()?.parse::<f64>().ok())?
        })
        .next()
}

fn percentile(sorted: &[f64], q: f64) -> f64 {
    if sorted.is_empty() {
        return f64::NAN;
    }
    let i = ((sorted.len() - 1) as f64 * q).round() as usize;
    sorted[i.min(sorted.len() - 1)]
}

/// The synthetic preset whose frame feeds the bench: the KITTI presets for the SemanticKITTI layout
/// (by grid), the six-camera `surround` preset for the nuScenes layouts (its cameras and images;
/// the grid is the config's: Occ3D's 200x200x16 in the ego frame or nuScenes-Occupancy's
/// 512x512x40 in the LiDAR frame).
fn preset_for(format: DatasetFormat, dims: [usize; 3]) -> Result<Preset> {
    if format != DatasetFormat::SemanticKitti {
        let g = format.default_grid();
        anyhow::ensure!(
            g.dims == dims,
            "model.full_dims {dims:?} is not the {} grid {:?}",
            format.name(),
            g.dims
        );
        return Ok(Preset::Surround);
    }
    for p in [Preset::Kitti, Preset::KittiSmall] {
        if p.grid().dims == dims {
            return Ok(p);
        }
    }
    bail!("model.full_dims {dims:?}: bench supports the SemanticKITTI grid (256x256x32) and kitti-small (128x128x16)")
}

/// Runs one model in this process.
fn run_single(args: &BenchArgs) -> Result<BenchResult> {
    let mut cfg = RunConfig::load(&args.config)?;
    let Some(name) = args.models.first() else {
        bail!("--single needs one model");
    };
    cfg.model.kind = (*name).into();
    let data = args.data.as_ref().context("--single needs --data")?;
    let base_rss = status_kib("VmRSS:").unwrap_or(0.0) / 1024.0;
    let seq = match cfg.data.format {
        DatasetFormat::SemanticKitti => "00",
        _ => "*",
    };
    let ds = Dataset::open(data, &cfg.data, &[seq.to_string()], &[])?;
    let div = args.grid_divisor.max(1);
    let grid = ds.grid().downsampled(div);
    cfg.model.full_dims = grid.dims;
    if grid.dims.iter().any(|d| d % 8 != 0) {
        bail!(
            "grid {:?} at divisor {div} is not a multiple of 8",
            grid.dims
        );
    }
    let device = backend::device();
    // Seeded weights (the config's `train.seed`): the same random network in every run, so that
    // runs compare the same amount of work (an untrained SparseOcc++ keeps a weight-dependent
    // number of voxels after propagation).
    <Infer as burn::tensor::backend::Backend>::seed(&device, cfg.train.seed);
    let model: OccNet<Infer> = cfg.model.init(&device)?;
    let sample = ds.load::<rand_chacha::ChaCha8Rng>(0, None)?;
    let mut latency = Vec::new();
    let mut stages = Vec::new();
    let mut compiled_at_warmup = None;
    for i in 0..args.warmup + args.frames.max(1) {
        if i == args.warmup {
            compiled_at_warmup = backend::settled_kernel_compilations();
        }
        let t0 = Instant::now();
        let mut batch = collate::<Infer>(std::slice::from_ref(&sample), grid, &device)?;
        batch.target = None;
        let out = model.forward(&batch)?;
        let dense = out.dense_prediction(1, grid.dims);
        // Synchronise: the dense grid is on the host, so every kernel has finished.
        std::hint::black_box(&dense);
        let ms = t0.elapsed().as_secs_f64() * 1e3;
        if i >= args.warmup {
            latency.push(ms);
        }
        stages = out.stats;
    }
    let compiles_after_warmup = match (compiled_at_warmup, backend::settled_kernel_compilations()) {
        (Some(a), Some(b)) => Some(b - a),
        _ => None,
    };
    // Profiled pass: synchronise after every stage (this changes overlap, so it is kept apart), and
    // count the multiply-adds of every stage (the same in every pass: same input, same network).
    let mut sums: Vec<(String, f64, u64)> = Vec::new();
    let mut ops: Vec<(&'static str, u64)> = Vec::new();
    let nprof = args.frames.clamp(1, 3);
    for _ in 0..nprof {
        occ_model::profile::enable(true);
        let t0 = Instant::now();
        let mut batch = collate::<Infer>(std::slice::from_ref(&sample), grid, &device)?;
        batch.target = None;
        let out = model.forward(&batch)?;
        let stages = occ_model::profile::take();
        let dense = out.dense_prediction(1, grid.dims);
        std::hint::black_box(&dense);
        let rest_macs = occ_model::profile::take_unmarked_macs();
        ops = occ_model::profile::take_ops();
        occ_model::profile::enable(false);
        let known: f64 = stages.iter().map(|s| s.ms).sum();
        let mut stages: Vec<(String, f64, u64)> = stages
            .into_iter()
            .map(|s| (s.stage.as_str().to_string(), s.ms, s.macs))
            .collect();
        stages.push((
            "other (upload, argmax, grid)".into(),
            t0.elapsed().as_secs_f64() * 1e3 - known,
            rest_macs,
        ));
        for (k, v, m) in stages {
            match sums.iter_mut().find(|(n, _, _)| *n == k) {
                Some(e) => {
                    e.1 += v;
                    e.2 = m;
                }
                None => sums.push((k, v, m)),
            }
        }
    }
    let gflop = |macs: u64| 2.0 * macs as f64 / 1e9;
    let profile_ms: Vec<(String, f64)> = sums
        .iter()
        .map(|(k, v, _)| (k.clone(), v / nprof as f64))
        .collect();
    let total_ms: f64 = profile_ms.iter().map(|s| s.1).sum();
    let total_gflops: f64 = sums.iter().map(|s| gflop(s.2)).sum();
    let profile_stages: Vec<StageProfile> = sums
        .iter()
        .zip(&profile_ms)
        .map(|((k, _, m), (_, ms))| StageProfile {
            stage: k.clone(),
            ms: *ms,
            gflops: gflop(*m),
            gflops_per_s: gflop(*m) / (ms / 1e3).max(1e-9),
            time_share: ms / total_ms.max(1e-9),
            flop_share: gflop(*m) / total_gflops.max(1e-12),
        })
        .collect();
    let gflops_by_op = ops
        .iter()
        .map(|&(k, m)| (k.to_string(), gflop(m)))
        .collect();
    let mut sorted = latency.clone();
    sorted.sort_by(f64::total_cmp);
    let median = percentile(&sorted, 0.5);
    Ok(BenchResult {
        model: cfg.model.kind.name().to_string(),
        device: backend::describe(),
        full_dims: grid.dims,
        image: (cfg.data.image_width, cfg.data.image_height),
        resnet_depth: cfg.model.encoder.resnet.depth,
        params: burn::module::Module::num_params(&model),
        latency_ms: latency,
        median_ms: median,
        p10_ms: percentile(&sorted, 0.1),
        p90_ms: percentile(&sorted, 0.9),
        fps: 1e3 / median,
        peak_rss_mib: status_kib("VmHWM:").unwrap_or(0.0) / 1024.0,
        base_rss_mib: base_rss,
        device_mem_mib: gpu_mem_mib(),
        stages,
        timing_covers: "image tensor upload + forward + argmax to a dense class grid; image decoding and resizing excluded; batch 1".into(),
        profile_ms,
        gflops: total_gflops,
        gflops_per_s: total_gflops / (median / 1e3),
        profile_gflops_per_s: total_gflops / (total_ms / 1e3).max(1e-9),
        profile_stages,
        gflops_by_op,
        compiles_after_warmup,
    })
}

fn run_child(
    args: &BenchArgs,
    model: &str,
    data: &Path,
    div: usize,
    frames: usize,
) -> Result<BenchResult> {
    let exe = std::env::current_exe().context("locating the sparseocc binary")?;
    let out = std::process::Command::new(exe)
        .arg("bench")
        .arg("--single")
        .arg("--config")
        .arg(&args.config)
        .arg("--models")
        .arg(model)
        .arg("--frames")
        .arg(frames.to_string())
        .arg("--warmup")
        .arg(args.warmup.to_string())
        .arg("--grid-divisor")
        .arg(div.to_string())
        .arg("--data")
        .arg(data)
        .stderr(std::process::Stdio::inherit())
        .output()
        .context("running the benchmark child process")?;
    if !out.status.success() {
        bail!("benchmark of {model} (grid /{div}) failed: {}", out.status);
    }
    let text = String::from_utf8_lossy(&out.stdout);
    let line = text.lines().last().unwrap_or_default();
    serde_json::from_str(line).with_context(|| format!("benchmark of {model}: bad output '{line}'"))
}

pub fn run(args: &BenchArgs) -> Result<()> {
    if args.single {
        let r = run_single(args)?;
        println!("{}", serde_json::to_string(&r)?);
        return Ok(());
    }
    let cfg = RunConfig::load(&args.config)?;
    let preset = preset_for(cfg.data.format, cfg.model.full_dims)?;
    let tmp = occ_data::formats::io::temp_sibling(&std::env::temp_dir().join("sparseocc-bench"));
    let synth = SynthConfig::new(preset, 7, vec![("00".to_string(), 1)]);
    synthetic::generate(&tmp, &synth, &mut |_, _| {})?;
    let result = (|| -> Result<()> {
        eprintln!("bench: sgemm rate ({SGEMM_N}x{SGEMM_N} f32 matmuls)");
        let sgemm = sgemm_gflops(SGEMM_N, SGEMM_REPS);
        let mut results = Vec::new();
        for m in args.models.iter().map(|m| m.name()) {
            eprintln!(
                "bench: {m} ({} warm-up + {} frames)",
                args.warmup, args.frames
            );
            results.push(run_child(args, m, &tmp, 1, args.frames)?);
        }
        print_table(&results, sgemm);
        let pp = results
            .iter()
            .find(|r| r.model == "sparseocc++")
            .map(|r| r.median_ms);
        let mut json = serde_json::json!({
            "config": args.config,
            "date": chrono_free_date(),
            "host": host_description(),
            "sgemm_gflops": sgemm,
            "sgemm_size": SGEMM_N,
            "results": results,
        });
        if let Some(pp) = pp {
            let ratios: serde_json::Map<String, serde_json::Value> = results
                .iter()
                .map(|r| (r.model.clone(), serde_json::json!(r.median_ms / pp)))
                .collect();
            json["latency_ratio_vs_sparseocc++"] = serde_json::Value::Object(ratios);
        }
        if let Some(p) = &args.json {
            crate::util::write_json(p, &json)?;
            eprintln!("wrote {}", p.display());
        }
        if let Some(prefix) = &args.scan {
            scan(args, &tmp, prefix)?;
        }
        Ok(())
    })();
    let _ = std::fs::remove_dir_all(&tmp);
    result
}

fn scan(args: &BenchArgs, data: &Path, prefix: &Path) -> Result<()> {
    let colors = [[220, 60, 40], [40, 110, 220], [90, 90, 90]];
    let mut all = Vec::new();
    let mut series = Vec::new();
    for (i, m) in args.models.iter().map(|m| m.name()).enumerate() {
        let mut pts = Vec::new();
        let base: [usize; 3] = RunConfig::load(&args.config)?.model.full_dims;
        for div in [4, 2, 1] {
            if base.iter().any(|d| d % div != 0 || (d / div) % 8 != 0) {
                eprintln!("scan: grid 1/{div} of {base:?} is not a multiple of 8, skipped");
                continue;
            }
            eprintln!("scan: {m} at grid 1/{div}");
            let r = run_child(args, m, data, div, args.scan_frames)?;
            let volume: usize = r.full_dims.iter().product();
            let active = r
                .stages
                .iter()
                .rev()
                .find(|(k, _)| FINAL_KEYS.contains(&k.as_str()))
                .map(|(_, v)| *v)
                .unwrap_or(0);
            pts.push((volume as f64, r.peak_rss_mib - r.base_rss_mib));
            all.push(serde_json::json!({
                "model": m, "grid_divisor": div, "full_dims": r.full_dims, "grid_voxels": volume,
                "active_voxels_final": active, "peak_rss_mib": r.peak_rss_mib,
                "base_rss_mib": r.base_rss_mib, "device_mem_mib": r.device_mem_mib,
                "median_ms": r.median_ms, "stages": r.stages,
            }));
        }
        let color = colors[i % colors.len()];
        series.push(Series {
            name: m.to_string(),
            color,
            points: pts,
        });
    }
    let json_p = prefix.with_extension("json");
    crate::util::write_json(
        &json_p,
        &serde_json::json!({"config": args.config, "host": host_description(), "device": backend::describe(), "points": all}),
    )?;
    let spec = PlotSpec {
        title: format!("peak memory vs grid size ({})", backend::describe()),
        x_label: "full-resolution grid voxels".into(),
        y_label: "peak RSS above start (MiB)".into(),
        log_x: true,
        log_y: false,
        series,
    };
    let img = line_plot(&spec, 900, 520)?;
    let png_p = prefix.with_extension("png");
    occ_data::image::write_png(&png_p, &img)?;
    eprintln!("wrote {} and {}", json_p.display(), png_p.display());
    Ok(())
}

/// Side of the square matrices of the sgemm measurement.
const SGEMM_N: usize = 2048;
/// Timed products of the sgemm measurement (after one warm-up).
const SGEMM_REPS: usize = 3;

/// The machine's f32 matrix-product rate (GFLOP/s, `2 n^3` per product): the median of `reps` timed
/// `[n, n] x [n, n]` products through the bench backend's `matmul` (burn NdArray on the CPU, the
/// product the models' linear layers run), after one warm-up; each timing includes reading one value
/// back, so that the product has finished.
pub fn sgemm_gflops(n: usize, reps: usize) -> f64 {
    use burn::prelude::*;
    let device = backend::device();
    let a = Tensor::<Infer, 2>::random([n, n], burn::tensor::Distribution::Default, &device);
    let b = Tensor::<Infer, 2>::random([n, n], burn::tensor::Distribution::Default, &device);
    let run = || {
        let t0 = Instant::now();
        let c = a.clone().matmul(b.clone());
        let v: f32 = c.slice([0..1, 0..1]).into_scalar().elem();
        std::hint::black_box(v);
        t0.elapsed().as_secs_f64()
    };
    run();
    let mut t: Vec<f64> = (0..reps.max(1)).map(|_| run()).collect();
    t.sort_by(f64::total_cmp);
    2.0 * (n as f64).powi(3) / 1e9 / percentile(&t, 0.5)
}

fn print_table(results: &[BenchResult], sgemm: f64) {
    let pp = results
        .iter()
        .find(|r| r.model == "sparseocc++")
        .map(|r| r.median_ms);
    println!(
        "{:<12} {:>10} {:>10} {:>8} {:>11} {:>9} {:>8} {:>8} {:>7}  final voxels",
        "model", "median ms", "p10-p90", "FPS", "peak MiB", "vs ++", "GFLOP", "GFLOP/s", "sgemm"
    );
    for r in results {
        let fin = r
            .stages
            .iter()
            .rev()
            .find(|(k, _)| FINAL_KEYS.contains(&k.as_str()))
            .map(|(_, v)| v.to_string())
            .unwrap_or_default();
        println!(
            "{:<12} {:>10.1} {:>10} {:>8.2} {:>11.0} {:>9} {:>8.1} {:>8.1} {:>6.0}%  {}",
            r.model,
            r.median_ms,
            format!("{:.0}-{:.0}", r.p10_ms, r.p90_ms),
            r.fps,
            r.peak_rss_mib,
            pp.map(|p| format!("{:.2}x", r.median_ms / p))
                .unwrap_or_default(),
            r.gflops,
            r.gflops_per_s,
            100.0 * r.gflops_per_s / sgemm,
            fin
        );
    }
    println!(
        "sgemm ({SGEMM_N}x{SGEMM_N} f32, this run): {sgemm:.1} GFLOP/s; GFLOP = 2 x multiply-adds"
    );
    for r in results {
        println!(
            "  {} per stage (profiled passes, synchronised after each stage):",
            r.model
        );
        println!(
            "    {:<30} {:>9} {:>7} {:>9} {:>7} {:>9} {:>7}",
            "stage", "ms", "time", "GFLOP", "FLOPs", "GFLOP/s", "sgemm"
        );
        for s in &r.profile_stages {
            println!(
                "    {:<30} {:>9.1} {:>6.1}% {:>9.2} {:>6.1}% {:>9.1} {:>6.0}%",
                s.stage,
                s.ms,
                100.0 * s.time_share,
                s.gflops,
                100.0 * s.flop_share,
                s.gflops_per_s,
                100.0 * s.gflops_per_s / sgemm
            );
        }
        let ms: f64 = r.profile_stages.iter().map(|s| s.ms).sum();
        println!(
            "    {:<30} {:>9.1} {:>6.1}% {:>9.2} {:>6.1}% {:>9.1} {:>6.0}%",
            "total",
            ms,
            100.0,
            r.gflops,
            100.0,
            r.profile_gflops_per_s,
            100.0 * r.profile_gflops_per_s / sgemm
        );
        let ops: Vec<String> = r
            .gflops_by_op
            .iter()
            .map(|(k, g)| format!("{k} {g:.2}"))
            .collect();
        println!("    GFLOP by op: {}", ops.join(", "));
        if let Some(c) = r.compiles_after_warmup {
            println!("    kernels compiled after the warm-up: {c}");
        }
    }
    if let Some(r) = results.first() {
        println!(
            "device: {}; input {}x{}, ResNet-{}, grid {:?}; {}",
            r.device, r.image.0, r.image.1, r.resnet_depth, r.full_dims, r.timing_covers
        );
    }
}

fn host_description() -> String {
    let cpu = std::fs::read_to_string("/proc/cpuinfo")
        .ok()
        .and_then(|s| {
            s.lines()
                .find(|l| l.starts_with("model name"))
                .and_then(|l| l.split(':').nth(1))
                .map(|s| s.trim().to_string())
        })
        .unwrap_or_else(|| "unknown CPU".into());
    format!(
        "{cpu}, {} threads",
        std::thread::available_parallelism()
            .map(|n| n.get())
            .unwrap_or(1)
    )
}

fn chrono_free_date() -> String {
    std::process::Command::new("date")
        .arg("-u")
        .arg("+%Y-%m-%dT%H:%M:%SZ")
        .output()
        .ok()
        .map(|o| String::from_utf8_lossy(&o.stdout).trim().to_string())
        .unwrap_or_default()
}
