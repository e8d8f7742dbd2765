//! `sparseocc bench`: latency, FPS, peak memory and active voxels per stage of the three models on
//! the same input, side by side; optionally a memory-vs-resolution scan (grid scale 1/4, 1/2, 1)
//! written as JSON and a PNG plot.
//!
//! Each (model, grid scale) runs in its own child process (`sparseocc bench --single ...`) so that its
//! peak resident memory (`VmHWM`) is its own. The input is one synthetic frame of the preset that
//! matches the config's grid (SemanticKITTI: 256x256x32 with a 1226x370 image), generated once; the
//! weights are random (timing does not depend on them, except through the number of voxels a trained
//! model keeps — see the notes in BENCHMARKS.md). What one run measures, and how, is
//! [`occ_train::bench`]'s: this command chooses the backend, starts the children, prints the table
//! and writes the files.
//!
//! FLOPs are reported as GFLOP = 2 x MACs / 1e9, so that a stage's GFLOP/s compares with the
//! machine's sgemm rate, measured in the same run by [`occ_train::bench::sgemm_gflops`] on this
//! binary's backend.

use crate::backend::{self, Infer};
use crate::util::ModelArg;
use anyhow::{bail, Context, Result};
use occ_data::synthetic::{self, SynthConfig};
use occ_train::bench::{self, preset_for, BenchResult, BenchRun};
use occ_train::RunConfig;
use occ_viz::plot::{line_plot, PlotSpec, Series};
use std::path::{Path, PathBuf};

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
    /// Timed frames per model (after the warm-up), at least 1.
    #[arg(long, default_value_t = 5, value_parser = crate::util::at_least(1))]
    pub frames: usize,
    /// Warm-up frames (not timed); 2 on the cubecl backends, whose second pass over a frame can
    /// still compile kernels (burn-fusion runs its stored plans from then on).
    #[arg(long, default_value_t = crate::backend::DEFAULT_WARMUP)]
    pub warmup: usize,
    /// Write the results as JSON here.
    #[arg(long)]
    pub json: Option<PathBuf>,
    /// Also scan peak memory against grid scale 1/4, 1/2, 1; writes PREFIX.json and PREFIX.png.
    #[arg(long)]
    pub scan: Option<PathBuf>,
    /// Frames per point of the scan, at least 1.
    #[arg(long, default_value_t = 1, value_parser = crate::util::at_least(1))]
    pub scan_frames: usize,
    /// Internal: run one model in this process and print its JSON.
    #[arg(long, hide = true)]
    pub single: bool,
    /// Internal: divide the grid by this factor.
    #[arg(long, hide = true, default_value_t = 1, value_parser = crate::util::at_least(1))]
    pub grid_divisor: usize,
    /// Internal: the synthetic dataset to read (made by the parent).
    #[arg(long, hide = true)]
    pub data: Option<PathBuf>,
}

/// Runs one model in this process: the first of `--models`, on the backend this binary was built
/// for ([`occ_train::bench::run_model`]).
fn run_single(args: &BenchArgs) -> Result<BenchResult> {
    let mut cfg = RunConfig::load(&args.config)?;
    let Some(name) = args.models.first() else {
        bail!("--single needs one model");
    };
    cfg.model.kind = (*name).into();
    let data = args.data.as_ref().context("--single needs --data")?;
    let run = BenchRun {
        data,
        grid_divisor: args.grid_divisor,
        warmup: args.warmup,
        frames: args.frames,
        device_name: backend::describe(),
        nvidia_smi: cfg!(feature = "cuda"),
        kernel_compilations: &backend::settled_kernel_compilations,
        kernel_launches: &backend::kernel_launches,
    };
    Ok(bench::run_model::<Infer>(cfg, &run, &backend::device())?)
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
        let sgemm = bench::sgemm_gflops::<Infer>(SGEMM_N, SGEMM_REPS, &backend::device());
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
            let active = r.final_voxels().unwrap_or(0);
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
        let fin = r.final_voxels().map(|v| v.to_string()).unwrap_or_default();
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
        if let Some(n) = r.launches_per_frame {
            let top: Vec<String> = r
                .launches_by_kernel
                .iter()
                .take(8)
                .map(|(k, n)| format!("{k} {n:.0}"))
                .collect();
            println!(
                "    kernel launches per frame: {n:.0} (most: {}; counting slows the timed frames)",
                top.join(", ")
            );
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
