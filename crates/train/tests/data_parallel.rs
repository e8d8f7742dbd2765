//! Data-parallel training (`train.devices`, crates/train/src/parallel.rs) on built-in synthetic
//! scenes: the same frames and seed on 2 workers of 1 frame and on 1 worker of 2 frames give the same
//! parameters (for a network whose loss is a mean over frames and that has no batch statistics), a
//! resumed data-parallel run equals an uninterrupted one, the real SparseOcc++ trains on 2 workers
//! with one checkpoint and one log, and a worker that fails stops the others with its error.
//!
//! The collective of a backend is one per process, so these tests take turns (`SERIAL`).

use burn::backend::{Autodiff, NdArray};
use burn::module::{Module, ModuleVisitor, Param};
use burn::nn::{Linear, LinearConfig};
use burn::optim::GradientsParams;
use burn::prelude::*;
use burn::tensor::activation::log_softmax;
use occ_data::synthetic::{generate, Preset, SynthConfig};
use occ_model::loss::LossKey;
use occ_model::{Batch, ModelError, ModelOutput, OccNetwork};
use occ_testdata::TempDir;
use occ_train::dataset::{collate, Dataset};
use occ_train::trainer::{train, TrainSummary};
use occ_train::{RunConfig, TrainError};
use std::path::Path;
use std::sync::Mutex;

type B = Autodiff<NdArray<f32>>;

static SERIAL: Mutex<()> = Mutex::new(());

fn serial() -> std::sync::MutexGuard<'static, ()> {
    SERIAL.lock().unwrap_or_else(|e| e.into_inner())
}

/// A small network whose loss is the mean over the batch of each frame's own loss, with no
/// normalisation: the mean colour of a frame's images -> class logits of the frame, scored by the
/// cross-entropy against the frame's class histogram (the mean over its labelled voxels).
#[derive(Module, Debug)]
struct FrameNet<B: Backend> {
    head: Linear<B>,
}

impl<B: Backend> OccNetwork<B> for FrameNet<B> {
    fn forward_batch(&self, batch: &Batch<B>) -> Result<ModelOutput<B>, ModelError> {
        let [b, v, c, h, w] = batch.images.dims();
        let x = batch
            .images
            .clone()
            .reshape([b, v, c, h * w])
            .mean_dim(3)
            .mean_dim(1);
        let logits = self.head.forward(x.reshape([b, c]));
        let classes = self.num_classes();
        let mut losses = Vec::new();
        if let Some(target) = &batch.target {
            let mut hist = vec![0f32; b * classes];
            for (i, t) in target.iter().enumerate() {
                let valid: Vec<&u8> = t.iter().filter(|&&y| (y as usize) < classes).collect();
                for &&y in &valid {
                    hist[i * classes + y as usize] += 1.0 / valid.len() as f32;
                }
            }
            let hist =
                Tensor::<B, 2>::from_data(TensorData::new(hist, [b, classes]), &logits.device());
            let loss = (log_softmax(logits.clone(), 1) * hist)
                .sum()
                .mul_scalar(-1.0 / b as f64);
            losses.push((LossKey::Ce, loss));
        }
        Ok(ModelOutput {
            coords: Vec::new(),
            logits,
            out_dims: [0, 0, 0],
            upsample: 1,
            losses,
            stats: Vec::new(),
        })
    }
    fn num_classes(&self) -> usize {
        self.head.weight.dims()[1]
    }
}

/// Synthetic SemanticKITTI-layout data (`frames` frames of sequence 00) and the demo's config.
fn data(root: &Path, frames: usize) -> (RunConfig, Dataset) {
    let s = SynthConfig::new(Preset::KittiSmall, 3, vec![("00".into(), frames)]);
    generate(root, &s, &mut |_, _| {}).unwrap();
    let text = std::fs::read_to_string(
        Path::new(env!("CARGO_MANIFEST_DIR")).join("../../configs/synthetic_tiny.toml"),
    )
    .unwrap();
    let mut cfg = RunConfig::from_toml(&text, "synthetic_tiny.toml").unwrap();
    cfg.data.val_sequences.clear();
    cfg.train.batch_size = 2;
    cfg.train.warmup_steps = 0;
    cfg.train.checkpoint_every = 2;
    cfg.train.log_every = 1;
    let ds = Dataset::open(root, &cfg.data, &["00".into()], &[]).unwrap();
    (cfg, ds)
}

/// Every float parameter, in visiting order.
fn params<M: Module<B>>(m: &M) -> Vec<Vec<f32>> {
    struct All(Vec<Vec<f32>>);
    impl ModuleVisitor<B> for All {
        fn visit_float<const D: usize>(&mut self, p: &Param<Tensor<B, D>>) {
            self.0.push(p.val().into_data().to_vec::<f32>().unwrap());
        }
    }
    let mut v = All(Vec::new());
    m.visit(&mut v);
    v.0
}

/// The largest difference of two parameter sets, relative to each tensor's largest magnitude.
fn max_rel_diff(a: &[Vec<f32>], b: &[Vec<f32>]) -> f64 {
    assert_eq!(a.len(), b.len());
    a.iter()
        .zip(b)
        .map(|(x, y)| {
            assert_eq!(x.len(), y.len());
            let scale = x.iter().fold(1e-6f32, |m, v| m.max(v.abs())) as f64;
            let d = x.iter().zip(y).fold(0f32, |m, (p, q)| m.max((p - q).abs())) as f64;
            d / scale
        })
        .fold(0.0, f64::max)
}

/// A seeded `FrameNet`, its parameters drawn (burn initialises them lazily, and each clone of an
/// undrawn parameter would draw its own).
/// The gradient of the loss of frames `idx` as one batch, flattened in visiting order.
fn grads_of(model: &occ_model::OccNet<B>, ds: &Dataset, idx: &[usize]) -> Vec<f32> {
    let device = Default::default();
    let samples: Vec<_> = idx
        .iter()
        .map(|&i| ds.load::<rand_chacha::ChaCha8Rng>(i, None).unwrap())
        .collect();
    let batch = collate::<B>(&samples, ds.grid(), &device).unwrap();
    let loss = model.forward_batch(&batch).unwrap().total_loss().unwrap();
    let grads = GradientsParams::from_grads(loss.backward(), model);
    struct Flat<'a>(&'a GradientsParams, Vec<f32>);
    impl ModuleVisitor<B> for Flat<'_> {
        fn visit_float<const D: usize>(&mut self, p: &Param<Tensor<B, D>>) {
            let n = p.val().shape().num_elements();
            match self.0.get::<NdArray<f32>, D>(p.id) {
                Some(g) => self.1.extend(g.into_data().to_vec::<f32>().unwrap()),
                None => self.1.extend(std::iter::repeat_n(0.0, n)),
            }
        }
    }
    let mut v = Flat(&grads, Vec::new());
    model.visit(&mut v);
    v.1
}

fn frame_net() -> FrameNet<B> {
    let device = Default::default();
    <B as burn::tensor::backend::Backend>::seed(&device, 7);
    let m = FrameNet {
        head: LinearConfig::new(3, 20).init(&device),
    };
    params(&m);
    m
}

fn run<M>(
    model: M,
    cfg: &RunConfig,
    ds: &Dataset,
    out: &Path,
    resume: bool,
) -> Result<(M, TrainSummary), TrainError>
where
    M: burn::module::AutodiffModule<B> + OccNetwork<B>,
{
    train::<B, M>(
        model,
        &cfg.train,
        ds,
        out,
        resume,
        &Default::default(),
        &mut |_, _, _| {},
    )
}

#[test]
fn two_workers_of_one_frame_equal_one_worker_of_two() {
    let _g = serial();
    let t = TempDir::new("occ_train", "dp_equal");
    let (mut cfg, ds) = data(&t.0.join("data"), 4);
    cfg.train.steps = 3;
    let init = frame_net();
    let (one, _) = run(init.clone(), &cfg, &ds, &t.0.join("one"), false).unwrap();
    cfg.train.devices = 2;
    let (two, summary) = run(init.clone(), &cfg, &ds, &t.0.join("two"), false).unwrap();
    assert_eq!(summary.steps, 3);
    let moved = max_rel_diff(&params(&init), &params(&one));
    let d = max_rel_diff(&params(&one), &params(&two));
    eprintln!("2 workers x 1 frame vs 1 worker x 2 frames after 3 steps: max relative difference {d:.3e} (the steps moved the parameters by {moved:.3e})");
    assert!(
        moved > 1e-3,
        "training did not change the parameters ({moved})"
    );
    assert!(
        d <= 1e-5,
        "data-parallel run differs from the single-device run: {d}"
    );
    // One log with every step, one checkpoint.
    let log = std::fs::read_to_string(t.0.join("two/train_log.csv")).unwrap();
    assert_eq!(log.lines().count(), 4, "{log}");
    assert!(t.0.join("two/checkpoint/state.json").is_file());
}

#[test]
fn a_resumed_data_parallel_run_equals_an_uninterrupted_one() {
    let _g = serial();
    let t = TempDir::new("occ_train", "dp_resume");
    let (mut cfg, ds) = data(&t.0.join("data"), 4);
    cfg.train.devices = 2;
    cfg.train.steps = 4;
    // A constant learning rate: the 2-step run's schedule is then that of the 4-step run's start (a
    // killed run, which this stands for, would have had the 4-step schedule).
    cfg.train.min_lr_ratio = 1.0;
    let init = frame_net();
    let (whole, _) = run(init.clone(), &cfg, &ds, &t.0.join("whole"), false).unwrap();
    cfg.train.steps = 2;
    run(init.clone(), &cfg, &ds, &t.0.join("parts"), false).unwrap();
    cfg.train.steps = 4;
    let (resumed, summary) = run(init, &cfg, &ds, &t.0.join("parts"), true).unwrap();
    assert_eq!(summary.resumed_from, Some(2));
    assert_eq!(params(&whole), params(&resumed));
    let a = std::fs::read_to_string(t.0.join("whole/train_log.csv")).unwrap();
    let b = std::fs::read_to_string(t.0.join("parts/train_log.csv")).unwrap();
    let losses = |s: &str| -> Vec<String> {
        s.lines()
            .map(|l| l.split(',').take(3).collect::<Vec<_>>().join(","))
            .collect()
    };
    assert_eq!(losses(&a), losses(&b));
}

#[test]
fn sparseocc_pp_trains_on_two_workers() {
    let _g = serial();
    let t = TempDir::new("occ_train", "dp_real");
    let (mut cfg, ds) = data(&t.0.join("data"), 2);
    cfg.train.steps = 2;
    let device = Default::default();
    <B as burn::tensor::backend::Backend>::seed(&device, 0);
    let init: occ_model::OccNet<B> = cfg.model.init(&device).unwrap();
    params(&init);
    let (one, _) = run(init.clone(), &cfg, &ds, &t.0.join("one"), false).unwrap();
    cfg.train.devices = 2;
    let (two, summary) = run(init.clone(), &cfg, &ds, &t.0.join("two"), false).unwrap();
    assert_eq!(summary.steps, 2);
    assert!(summary.last_loss.is_finite());
    assert!(t.0.join("two/checkpoint/state.json").is_file());
    let log = std::fs::read_to_string(t.0.join("two/train_log.csv")).unwrap();
    assert_eq!(log.lines().count(), 3, "{log}");
    // Not equal to the single-device run (batch-mean losses and per-worker BatchNorm statistics,
    // see crates/train/src/parallel.rs): how far, for docs/data_parallel.md.
    let dist = |a: &[Vec<f32>], b: &[Vec<f32>]| -> f64 {
        a.iter()
            .flatten()
            .zip(b.iter().flatten())
            .map(|(p, q)| ((p - q) as f64).powi(2))
            .sum::<f64>()
            .sqrt()
    };
    let (p0, p1, p2) = (params(&init), params(&one), params(&two));
    eprintln!(
        "SparseOcc++, 2 steps: |two workers - one worker| / |one worker - init| = {:.3e} (L2 over all parameters)",
        dist(&p1, &p2) / dist(&p0, &p1)
    );
    // The objectives themselves: the gradient of the two frames as one batch against the mean of
    // each frame's own gradient (what 2 workers of 1 frame compute), at the initial weights.
    let whole = grads_of(&init, &ds, &[0, 1]);
    let f0 = grads_of(&init, &ds, &[0]);
    let f1 = grads_of(&init, &ds, &[1]);
    let mean: Vec<f32> = f0.iter().zip(&f1).map(|(a, b)| (a + b) / 2.0).collect();
    let dot: f64 = whole.iter().zip(&mean).map(|(a, b)| (a * b) as f64).sum();
    let norm = |v: &[f32]| v.iter().map(|a| (a * a) as f64).sum::<f64>().sqrt();
    let diff: Vec<f32> = whole.iter().zip(&mean).map(|(a, b)| a - b).collect();
    let cosine = dot / (norm(&whole) * norm(&mean));
    eprintln!(
        "SparseOcc++ gradient at the initial weights, batch of 2 vs mean of 2 single frames: cosine {cosine:.4}, |difference| / |batch| = {:.3e}",
        norm(&diff) / norm(&whole)
    );
    assert!(cosine > 0.5, "cosine {cosine}");
}

#[test]
fn a_failing_worker_stops_the_others_with_its_error() {
    let _g = serial();
    let t = TempDir::new("occ_train", "dp_fail");
    let root = t.0.join("data");
    let (mut cfg, ds) = data(&root, 2);
    cfg.train.devices = 2;
    cfg.train.steps = 2;
    // Every step holds both frames, one on each worker: a damaged label file fails one of them.
    let label = root.join("sequences/00/voxels/000001.label");
    let bytes = std::fs::read(&label).unwrap();
    std::fs::write(&label, &bytes[..bytes.len() / 2]).unwrap();
    let err = run(frame_net(), &cfg, &ds, &t.0.join("run"), false).unwrap_err();
    let msg = err.to_string();
    assert!(msg.contains("000001.label"), "{msg}");
    // The collective is usable again afterwards.
    std::fs::write(&label, &bytes).unwrap();
    run(frame_net(), &cfg, &ds, &t.0.join("run2"), false).unwrap();
}

#[test]
fn devices_must_divide_the_batch() {
    let _g = serial();
    let t = TempDir::new("occ_train", "dp_config");
    let (mut cfg, ds) = data(&t.0.join("data"), 2);
    cfg.train.devices = 3;
    let err = run(frame_net(), &cfg, &ds, &t.0.join("run"), false).unwrap_err();
    let msg = err.to_string();
    assert!(
        msg.contains("train.batch_size = 2") && msg.contains("train.devices = 3"),
        "{msg}"
    );
}
