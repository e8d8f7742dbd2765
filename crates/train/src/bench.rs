//! One model's benchmark run, as `sparseocc bench` measures it: latency, FPS, peak memory, active
//! voxels and work per stage of one model on one synthetic frame ([`run_model`]), the machine's f32
//! matrix-product rate to compare the stages' rates with ([`sgemm_gflops`]), and the result types
//! the command prints and writes as JSON ([`BenchResult`], [`StageProfile`]).
//!
//! The input is one frame of the synthetic preset that matches the config's grid ([`preset_for`]),
//! loaded and resized by the test-time pipeline to the config's input size; the weights are random
//! and seeded (timing does not depend on them, except through the number of voxels a trained model
//! keeps). Image decoding is excluded from the timings; the forward pass includes everything from
//! the image tensor to the class logits, and the dense class grid.
//!
//! FLOPs: the profiled passes also count every stage's multiply-adds ([`occ_model::profile`]; sparse
//! convs from their pair counts, dense convs and linears from shapes, DCA from its samples, attention
//! from its sizes), reported as GFLOP = 2 x MACs / 1e9, so that a stage's GFLOP/s compares with the
//! machine's sgemm rate.
//!
//! Memory is read from `/proc/self/status` (the process's peak resident set, `VmHWM`): a front end
//! runs each model in a process of its own so that the peak is that model's. Nothing here prints.

use crate::dataset::{collate, Dataset, DatasetFormat};
use crate::error::TrainError;
use crate::RunConfig;
use burn::module::Module;
use burn::tensor::backend::Backend;
use occ_data::synthetic::Preset;
use occ_model::{ModelBackend, OccNet};
use serde::{Deserialize, Serialize};
use std::path::Path;
use std::time::Instant;

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
    /// Kernel launches per timed frame, when the backend counts them (`SPARSEOCC_COUNT_LAUNCHES` on
    /// a cubecl backend): each launch costs the device a few microseconds whatever its size, so
    /// this times a few microseconds bounds a frame from below.
    #[serde(default)]
    pub launches_per_frame: Option<f64>,
    /// The most launched kernels per timed frame (at most [`TOP_KERNELS`]), most first.
    #[serde(default)]
    pub launches_by_kernel: Vec<(String, f64)>,
}

/// How many kernels [`BenchResult::launches_by_kernel`] lists.
pub const TOP_KERNELS: usize = 25;

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
pub const FINAL_KEYS: [&str; 3] = ["final", "out.sites", "dense.voxels"];

impl BenchResult {
    /// The voxels the model predicts on: the count of the last stage named in [`FINAL_KEYS`], if
    /// the model reported one.
    pub fn final_voxels(&self) -> Option<usize> {
        self.stages
            .iter()
            .rev()
            .find(|(k, _)| FINAL_KEYS.contains(&k.as_str()))
            .map(|(_, v)| *v)
    }
}

/// What [`run_model`] runs and how it reads the backend's counters; the backend itself is the
/// caller's choice (its type parameter and device).
pub struct BenchRun<'a> {
    /// The synthetic dataset to read (one frame of [`preset_for`]'s preset).
    pub data: &'a Path,
    /// Divide the grid by this factor (1: the config's grid; 0 counts as 1).
    pub grid_divisor: usize,
    /// Warm-up frames (not timed).
    pub warmup: usize,
    /// Timed frames (at least one runs).
    pub frames: usize,
    /// Device and precision, as the result names them.
    pub device_name: String,
    /// Whether the process's device memory is read from `nvidia-smi` (the CUDA backend).
    pub nvidia_smi: bool,
    /// Kernels compiled so far, read after a device sync once the count has settled; `None` on
    /// backends that compile nothing.
    pub kernel_compilations: &'a dyn Fn() -> Option<u64>,
    /// Kernels launched so far, by name, read the same way; `None` where launches are not counted.
    pub kernel_launches: &'a dyn Fn() -> Option<Vec<(String, u64)>>,
}

/// Launches per frame between two reads of [`BenchRun::kernel_launches`] `frames` frames apart:
/// the total and the [`TOP_KERNELS`] most launched kernels, most first (ties by name).
pub fn launches_per_frame(
    before: &[(String, u64)],
    after: &[(String, u64)],
    frames: usize,
) -> (f64, Vec<(String, f64)>) {
    let frames = frames.max(1) as f64;
    let mut by_kernel: Vec<(String, f64)> = after
        .iter()
        .map(|(k, n)| {
            let was = before.iter().find(|(b, _)| b == k).map_or(0, |(_, m)| *m);
            (k.clone(), n.saturating_sub(was) as f64 / frames)
        })
        .filter(|(_, n)| *n > 0.0)
        .collect();
    by_kernel.sort_by(|a, b| b.1.total_cmp(&a.1).then_with(|| a.0.cmp(&b.0)));
    let total = by_kernel.iter().map(|(_, n)| n).sum();
    by_kernel.truncate(TOP_KERNELS);
    (total, by_kernel)
}

/// A value of `/proc/self/status` in kiB (`key` with its colon, e.g. `"VmHWM:"`); `None` where the
/// file or the key is missing.
pub fn status_kib(key: &str) -> Option<f64> {
    let s = std::fs::read_to_string("/proc/self/status").ok()?;
    status_value_kib(&s, key)
}

fn status_value_kib(status: &str, key: &str) -> Option<f64> {
    status
        .lines()
        .find(|l| l.starts_with(key))?
        .split_whitespace()
        .nth(1)?
        .parse()
        .ok()
}

/// Device memory this process uses (MiB), as `nvidia-smi` lists it; `None` without `nvidia-smi` or
/// when the process is not listed.
pub fn gpu_mem_mib() -> Option<f64> {
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

/// The value at quantile `q` (0..=1) of `sorted` (ascending): the element at the nearest rank,
/// `round((len - 1) q)`; NaN for an empty list.
pub fn percentile(sorted: &[f64], q: f64) -> f64 {
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
pub fn preset_for(format: DatasetFormat, dims: [usize; 3]) -> Result<Preset, TrainError> {
    if format != DatasetFormat::SemanticKitti {
        let g = format.default_grid();
        if g.dims != dims {
            return Err(TrainError::Bench(format!(
                "model.full_dims {dims:?} is not the {} grid {:?}",
                format.name(),
                g.dims
            )));
        }
        return Ok(Preset::Surround);
    }
    for p in [Preset::Kitti, Preset::KittiSmall] {
        if p.grid().dims == dims {
            return Ok(p);
        }
    }
    Err(TrainError::Bench(format!(
        "model.full_dims {dims:?}: bench supports the SemanticKITTI grid (256x256x32) and kitti-small (128x128x16)"
    )))
}

/// Runs the model `cfg.model.kind` names on the first frame of `run.data`: `run.warmup` untimed
/// and `run.frames` timed forward passes (batch 1, from the image tensor to the dense class grid),
/// then up to 3 profiled passes that synchronise after every stage and count its multiply-adds.
/// The weights are seeded with `train.seed`, so that every run builds the same network and does
/// the same work (an untrained SparseOcc++ keeps a weight-dependent number of voxels).
pub fn run_model<B: ModelBackend>(
    mut cfg: RunConfig,
    run: &BenchRun,
    device: &B::Device,
) -> Result<BenchResult, TrainError> {
    let base_rss = status_kib("VmRSS:").unwrap_or(0.0) / 1024.0;
    let seq = match cfg.data.format {
        DatasetFormat::SemanticKitti => "00",
        _ => "*",
    };
    let ds = Dataset::open(run.data, &cfg.data, &[seq.to_string()], &[])?;
    let div = run.grid_divisor.max(1);
    let grid = ds.grid().downsampled(div);
    cfg.model.full_dims = grid.dims;
    if grid.dims.iter().any(|d| d % 8 != 0) {
        return Err(TrainError::Bench(format!(
            "grid {:?} at divisor {div} is not a multiple of 8",
            grid.dims
        )));
    }
    // Seeded weights (the config's `train.seed`): the same random network in every run, so that
    // runs compare the same amount of work (an untrained SparseOcc++ keeps a weight-dependent
    // number of voxels after propagation).
    B::seed(device, cfg.train.seed);
    let model: OccNet<B> = cfg.model.init(device)?;
    let sample = ds.load::<rand_chacha::ChaCha8Rng>(0, None)?;
    let mut latency = Vec::new();
    let mut stages = Vec::new();
    let mut compiled_at_warmup = None;
    let mut launched_at_warmup = None;
    for i in 0..run.warmup + run.frames.max(1) {
        if i == run.warmup {
            compiled_at_warmup = (run.kernel_compilations)();
            launched_at_warmup = (run.kernel_launches)();
        }
        let t0 = Instant::now();
        let mut batch = collate::<B>(std::slice::from_ref(&sample), grid, device)?;
        batch.target = None;
        let out = model.forward(&batch)?;
        let dense = out.dense_prediction(1, grid.dims);
        // Synchronise: the dense grid is on the host, so every kernel has finished.
        std::hint::black_box(&dense);
        let ms = t0.elapsed().as_secs_f64() * 1e3;
        if i >= run.warmup {
            latency.push(ms);
        }
        stages = out.stats;
    }
    let compiles_after_warmup = match (compiled_at_warmup, (run.kernel_compilations)()) {
        (Some(a), Some(b)) => Some(b - a),
        _ => None,
    };
    let (launches_per_frame, launches_by_kernel) =
        match (launched_at_warmup, (run.kernel_launches)()) {
            (Some(a), Some(b)) => {
                let (n, by) = launches_per_frame(&a, &b, run.frames.max(1));
                (Some(n), by)
            }
            _ => (None, Vec::new()),
        };
    // Profiled pass: synchronise after every stage (this changes overlap, so it is kept apart), and
    // count the multiply-adds of every stage (the same in every pass: same input, same network).
    let mut sums: Vec<(String, f64, u64)> = Vec::new();
    let mut ops: Vec<(&'static str, u64)> = Vec::new();
    let nprof = run.frames.clamp(1, 3);
    for _ in 0..nprof {
        occ_model::profile::enable(true);
        let t0 = Instant::now();
        let mut batch = collate::<B>(std::slice::from_ref(&sample), grid, device)?;
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
        device: run.device_name.clone(),
        full_dims: grid.dims,
        image: (cfg.data.image_width, cfg.data.image_height),
        resnet_depth: cfg.model.encoder.resnet.depth,
        params: model.num_params(),
        latency_ms: latency,
        median_ms: median,
        p10_ms: percentile(&sorted, 0.1),
        p90_ms: percentile(&sorted, 0.9),
        fps: 1e3 / median,
        peak_rss_mib: status_kib("VmHWM:").unwrap_or(0.0) / 1024.0,
        base_rss_mib: base_rss,
        device_mem_mib: if run.nvidia_smi { gpu_mem_mib() } else { None },
        stages,
        timing_covers: "image tensor upload + forward + argmax to a dense class grid; image decoding and resizing excluded; batch 1".into(),
        profile_ms,
        gflops: total_gflops,
        gflops_per_s: total_gflops / (median / 1e3),
        profile_gflops_per_s: total_gflops / (total_ms / 1e3).max(1e-9),
        profile_stages,
        gflops_by_op,
        compiles_after_warmup,
        launches_per_frame,
        launches_by_kernel,
    })
}

/// The machine's f32 matrix-product rate (GFLOP/s, `2 n^3` per product): the median of `reps` timed
/// `[n, n] x [n, n]` products through backend `B`'s `matmul` (burn NdArray on the CPU, the product
/// the models' linear layers run), after one warm-up; each timing includes reading one value back,
/// so that the product has finished.
pub fn sgemm_gflops<B: Backend>(n: usize, reps: usize, device: &B::Device) -> f64 {
    use burn::prelude::*;
    let a = Tensor::<B, 2>::random([n, n], burn::tensor::Distribution::Default, device);
    let b = Tensor::<B, 2>::random([n, n], burn::tensor::Distribution::Default, device);
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

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn percentile_takes_the_nearest_rank() {
        let sorted = [1.0, 2.0, 3.0, 4.0, 10.0];
        assert_eq!(percentile(&sorted, 0.5), 3.0);
        // (5 - 1) x 0.1 = 0.4 rounds to rank 0, (5 - 1) x 0.6 = 2.4 to rank 2, (5 - 1) x 0.9 = 3.6
        // to rank 4.
        assert_eq!(percentile(&sorted, 0.1), 1.0);
        assert_eq!(percentile(&sorted, 0.6), 3.0);
        assert_eq!(percentile(&sorted, 0.9), 10.0);
        assert_eq!(percentile(&sorted, 1.0), 10.0);
        assert_eq!(percentile(&[7.5], 0.9), 7.5);
        assert!(percentile(&[], 0.5).is_nan());
    }

    #[test]
    fn presets_follow_the_layout_and_the_grid() {
        let kitti = DatasetFormat::SemanticKitti;
        assert_eq!(preset_for(kitti, [256, 256, 32]).unwrap(), Preset::Kitti);
        assert_eq!(
            preset_for(kitti, [128, 128, 16]).unwrap(),
            Preset::KittiSmall
        );
        assert!(preset_for(kitti, [64, 64, 8]).is_err());
        for format in [DatasetFormat::Occ3d, DatasetFormat::NuscenesOccupancy] {
            let dims = format.default_grid().dims;
            assert_eq!(preset_for(format, dims).unwrap(), Preset::Surround);
            assert!(preset_for(format, [256, 256, 32]).is_err());
        }
    }

    #[test]
    fn launches_per_frame_are_the_difference_over_the_frames() {
        let s = |v: &[(&str, u64)]| -> Vec<(String, u64)> {
            v.iter().map(|&(k, n)| (k.to_string(), n)).collect()
        };
        let before = s(&[("matmul", 10), ("fused", 4), ("gone", 3)]);
        // `fused` 4 -> 10, `matmul` 10 -> 16 (a tie, broken by name), `new` 0 -> 2; `gone` and
        // `same` launched nothing in between.
        let after = s(&[
            ("fused", 10),
            ("gone", 3),
            ("matmul", 16),
            ("new", 2),
            ("same", 0),
        ]);
        let (total, by) = launches_per_frame(&before, &after, 2);
        assert_eq!(total, 7.0);
        let want = vec![
            ("fused".to_string(), 3.0),
            ("matmul".to_string(), 3.0),
            ("new".to_string(), 1.0),
        ];
        assert_eq!(by, want);
        let many: Vec<(String, u64)> = (0..40).map(|i| (format!("k{i:02}"), i + 1)).collect();
        let (total, by) = launches_per_frame(&[], &many, 1);
        assert_eq!(
            total,
            (1..=40).sum::<u64>() as f64,
            "the total counts every kernel"
        );
        assert_eq!(by.len(), TOP_KERNELS);
        assert_eq!(by[0], ("k39".to_string(), 40.0));
    }

    #[test]
    fn status_values_are_read_in_kib() {
        let status = "Name:\tbench\nVmHWM:\t  204800 kB\nVmRSS:\t  102400 kB\n";
        assert_eq!(status_value_kib(status, "VmHWM:"), Some(204800.0));
        assert_eq!(status_value_kib(status, "VmRSS:"), Some(102400.0));
        assert_eq!(status_value_kib(status, "VmSwap:"), None);
        // This process has a resident set.
        assert!(status_kib("VmRSS:").unwrap() > 0.0);
    }

    #[test]
    fn final_voxels_are_the_last_final_stage() {
        let result = BenchResult {
            model: "dense".into(),
            device: "CPU".into(),
            full_dims: [16, 16, 8],
            image: (32, 16),
            resnet_depth: 18,
            params: 1,
            latency_ms: vec![1.0],
            median_ms: 1.0,
            p10_ms: 1.0,
            p90_ms: 1.0,
            fps: 1e3,
            peak_rss_mib: 1.0,
            base_rss_mib: 1.0,
            device_mem_mib: None,
            stages: vec![
                ("lss.voxels".into(), 500),
                ("out.sites".into(), 300),
                ("final".into(), 120),
                ("head.queries".into(), 4),
            ],
            timing_covers: String::new(),
            profile_ms: Vec::new(),
            gflops: 0.0,
            gflops_per_s: 0.0,
            profile_gflops_per_s: 0.0,
            profile_stages: Vec::new(),
            gflops_by_op: Vec::new(),
            compiles_after_warmup: None,
            launches_per_frame: None,
            launches_by_kernel: Vec::new(),
        };
        assert_eq!(result.final_voxels(), Some(120));
        let none = BenchResult {
            stages: vec![("lss.voxels".into(), 500)],
            ..result
        };
        assert_eq!(none.final_voxels(), None);
    }

    #[test]
    fn sgemm_rate_is_positive_and_finite() {
        let device = Default::default();
        let rate = sgemm_gflops::<burn::backend::NdArray<f32>>(64, 2, &device);
        assert!(rate.is_finite() && rate > 0.0, "{rate}");
    }
}
