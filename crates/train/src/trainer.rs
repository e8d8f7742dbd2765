//! The training loop: AdamW (weight-decay and no-decay groups), warmup + cosine schedule, global-norm
//! clipping, periodic validation, checkpoints every N steps with exact resume, CSV + JSON logs.
//!
//! Determinism: the frame order of epoch `e` is a permutation drawn from `(seed, e)`, and the
//! augmentation of step `s` from `(seed, s)`, so a run resumed from a checkpoint sees the same data as
//! an uninterrupted one.

use crate::dataset::{collate, Dataset, Sample};
use crate::error::TrainError;
use crate::grads::{clip_global_norm, split_no_decay};
use crate::schedule::WarmupCosine;
use burn::module::AutodiffModule;
use burn::optim::{AdamWConfig, GradientsParams, Optimizer};
use burn::prelude::*;
use burn::record::{BinFileRecorder, FullPrecisionSettings, Recorder};
use burn::tensor::backend::AutodiffBackend;
use occ_model::OccNetwork;
use rand::seq::SliceRandom;
use rand::SeedableRng;
use rand_chacha::ChaCha8Rng;
use rayon::prelude::*;
use serde::{Deserialize, Serialize};
use std::io::Write;
use std::path::{Path, PathBuf};
use std::time::Instant;

/// Optimisation settings (the `[train]` section of a config).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct TrainConfig {
    /// Optimizer steps.
    pub steps: usize,
    /// Frames per step.
    #[serde(default = "one")]
    pub batch_size: usize,
    /// Peak learning rate.
    pub lr: f64,
    /// AdamW weight decay (not applied to biases, norms, embeddings, queries).
    #[serde(default = "wd")]
    pub weight_decay: f64,
    /// Linear warmup steps.
    #[serde(default)]
    pub warmup_steps: usize,
    /// Final learning rate as a fraction of `lr` (cosine decay).
    #[serde(default = "min_ratio")]
    pub min_lr_ratio: f64,
    /// Maximum global gradient norm (paper: 35).
    #[serde(default = "clip")]
    pub clip_norm: f64,
    /// Save a checkpoint every N steps (and at the end).
    #[serde(default = "ckpt")]
    pub checkpoint_every: usize,
    /// Log every N steps.
    #[serde(default = "one")]
    pub log_every: usize,
    /// Random seed.
    #[serde(default)]
    pub seed: u64,
    /// Training image augmentation (random resize/crop/flip/rotate).
    #[serde(default)]
    pub augment: bool,
}

fn one() -> usize {
    1
}
fn wd() -> f64 {
    0.01
}
fn min_ratio() -> f64 {
    0.01
}
fn clip() -> f64 {
    35.0
}
fn ckpt() -> usize {
    100
}

/// One logged step.
#[derive(Clone, Debug, Serialize, Deserialize)]
pub struct StepLog {
    /// Optimizer step (1-based).
    pub step: usize,
    /// Learning rate used.
    pub lr: f64,
    /// Total loss.
    pub loss: f64,
    /// Loss terms.
    pub terms: Vec<(String, f64)>,
    /// Gradient norm before clipping.
    pub grad_norm: f64,
    /// Wall time of the step in seconds.
    pub seconds: f64,
}

/// The state saved beside the weights.
#[derive(Clone, Debug, Serialize, Deserialize)]
pub struct TrainState {
    /// Steps completed.
    pub step: usize,
    /// Training seconds so far.
    pub train_seconds: f64,
}

/// What a run did.
#[derive(Clone, Debug, Serialize, Deserialize)]
pub struct TrainSummary {
    /// Steps completed.
    pub steps: usize,
    /// Seconds spent training (this process plus resumed runs).
    pub train_seconds: f64,
    /// Mean loss of the first and last logged tenth of the run.
    pub first_loss: f64,
    /// See `first_loss`.
    pub last_loss: f64,
    /// Resumed from step.
    pub resumed_from: Option<usize>,
}

fn io_err(path: &Path) -> impl FnOnce(std::io::Error) -> TrainError + '_ {
    move |source| TrainError::Io {
        path: path.to_path_buf(),
        source,
    }
}

/// Paths of a checkpoint inside a run folder.
pub struct CheckpointPaths {
    /// `RUN/checkpoint`.
    pub dir: PathBuf,
}

impl CheckpointPaths {
    /// Under `run`.
    pub fn new(run: &Path) -> Self {
        Self {
            dir: run.join("checkpoint"),
        }
    }
    /// Model weights (burn binary record, `.bin` added by the recorder).
    pub fn model(&self) -> PathBuf {
        self.dir.join("model")
    }
    fn optim(&self, which: &str) -> PathBuf {
        self.dir.join(format!("optim_{which}"))
    }
    /// Training state JSON.
    pub fn state(&self) -> PathBuf {
        self.dir.join("state.json")
    }
}

/// Loads the samples of `idx` in parallel.
fn load_samples(
    ds: &Dataset,
    idx: &[usize],
    augment_seed: Option<u64>,
) -> Result<Vec<Sample>, TrainError> {
    idx.par_iter()
        .enumerate()
        .map(|(j, &i)| match augment_seed {
            Some(s) => {
                let mut r = ChaCha8Rng::seed_from_u64(s ^ (j as u64).wrapping_mul(0x9E37_79B9));
                ds.load(i, Some(&mut r))
            }
            None => ds.load::<ChaCha8Rng>(i, None),
        })
        .collect()
}

/// Frame indices for step `step` (0-based) of a run over `n` frames.
fn batch_indices(n: usize, batch: usize, seed: u64, step: usize) -> Vec<usize> {
    let per_epoch = n.div_ceil(batch).max(1);
    let epoch = step / per_epoch;
    let mut order: Vec<usize> = (0..n).collect();
    order.shuffle(&mut ChaCha8Rng::seed_from_u64(
        seed.wrapping_add(epoch as u64 * 7919),
    ));
    let k = (step % per_epoch) * batch;
    (0..batch).map(|j| order[(k + j) % n]).collect()
}

/// Trains `model` on `ds`, writing checkpoints and logs under `run`. With `resume`, continues from
/// `run/checkpoint` if one exists. `on_step(step, total, &log)` reports progress.
pub fn train<B, M>(
    mut model: M,
    cfg: &TrainConfig,
    ds: &Dataset,
    run: &Path,
    resume: bool,
    device: &B::Device,
    on_step: &mut dyn FnMut(usize, usize, &StepLog),
) -> Result<(M, TrainSummary), TrainError>
where
    B: AutodiffBackend,
    M: AutodiffModule<B> + OccNetwork<B>,
{
    if cfg.steps == 0 || cfg.batch_size == 0 || cfg.lr.is_nan() || cfg.lr <= 0.0 {
        return Err(TrainError::Config(format!(
            "steps ({}), batch_size ({}) and lr ({}) must be positive",
            cfg.steps, cfg.batch_size, cfg.lr
        )));
    }
    std::fs::create_dir_all(run).map_err(io_err(run))?;
    let ck = CheckpointPaths::new(run);
    let recorder = BinFileRecorder::<FullPrecisionSettings>::new();
    let mut opt_decay = AdamWConfig::new()
        .with_weight_decay(cfg.weight_decay as f32)
        .with_epsilon(1e-8)
        .init::<B, M>();
    let mut opt_plain = AdamWConfig::new()
        .with_weight_decay(0.0)
        .with_epsilon(1e-8)
        .init::<B, M>();
    let mut start = 0usize;
    let mut prior_seconds = 0.0;
    let mut resumed_from = None;
    if resume && ck.state().exists() {
        let text = std::fs::read_to_string(ck.state()).map_err(io_err(&ck.state()))?;
        let state: TrainState = serde_json::from_str(&text)
            .map_err(|e| TrainError::Checkpoint(format!("{}: {e}", ck.state().display())))?;
        model = occ_model::load_checked(model, &ck.model(), device)
            .map_err(|e| TrainError::Checkpoint(e.to_string()))?;
        for (which, opt) in [("decay", &mut opt_decay), ("plain", &mut opt_plain)] {
            let p = ck.optim(which);
            let rec = recorder
                .load(p.clone(), device)
                .map_err(|e| TrainError::Checkpoint(format!("{}: {e}", p.display())))?;
            *opt = std::mem::replace(opt, AdamWConfig::new().init::<B, M>()).load_record(rec);
        }
        start = state.step;
        prior_seconds = state.train_seconds;
        resumed_from = Some(start);
    }
    let schedule = WarmupCosine {
        lr: cfg.lr,
        warmup_steps: cfg.warmup_steps,
        total_steps: cfg.steps,
        min_lr_ratio: cfg.min_lr_ratio,
        warmup_start_ratio: 0.1,
    };
    let log_path = run.join("train_log.csv");
    let mut log = std::fs::OpenOptions::new()
        .create(true)
        .append(true)
        .open(&log_path)
        .map_err(io_err(&log_path))?;
    if start == 0 {
        writeln!(log, "step,lr,loss,grad_norm,seconds,terms").map_err(io_err(&log_path))?;
    }
    let t_run = Instant::now();
    let mut losses = Vec::new();
    for step in start..cfg.steps {
        let t0 = Instant::now();
        let idx = batch_indices(ds.len(), cfg.batch_size, cfg.seed, step);
        let aug_seed = cfg
            .augment
            .then(|| cfg.seed ^ (step as u64).wrapping_mul(0x2545_F491_4F6C_DD1D));
        let samples = load_samples(ds, &idx, aug_seed)?;
        let batch = collate::<B>(&samples, ds.grid(), device)?;
        if batch.target.is_none() {
            return Err(TrainError::Data(format!(
                "frame {}/{} has no voxels/*.label: cannot train on it",
                samples[0].frame.sequence, samples[0].frame.frame
            )));
        }
        let out = model.forward_batch(&batch)?;
        let mut terms = Vec::new();
        for (name, l) in &out.losses {
            let v: f64 = l.clone().into_scalar().elem();
            terms.push((name.clone(), v));
        }
        let loss = out
            .total_loss()
            .ok_or_else(|| TrainError::Data("the model returned no loss terms".into()))?;
        let loss_v: f64 = loss.clone().into_scalar().elem();
        if !loss_v.is_finite() {
            let detail = terms
                .iter()
                .map(|(n, v)| format!("{n}={v}"))
                .collect::<Vec<_>>()
                .join(", ");
            return Err(TrainError::NonFiniteLoss {
                step: step + 1,
                detail,
            });
        }
        let mut grads = GradientsParams::from_grads(loss.backward(), &model);
        let grad_norm = clip_global_norm::<B, M>(&model, &mut grads, cfg.clip_norm);
        let plain = split_no_decay::<B, M>(&model, &mut grads);
        let lr = schedule.lr_at(step);
        model = opt_decay.step(lr, model, grads);
        model = opt_plain.step(lr, model, plain);
        let entry = StepLog {
            step: step + 1,
            lr,
            loss: loss_v,
            terms,
            grad_norm,
            seconds: t0.elapsed().as_secs_f64(),
        };
        losses.push(loss_v);
        if (step + 1) % cfg.log_every.max(1) == 0 || step + 1 == cfg.steps {
            let t = entry
                .terms
                .iter()
                .map(|(n, v)| format!("{n}={v:.5}"))
                .collect::<Vec<_>>()
                .join(";");
            writeln!(
                log,
                "{},{:.3e},{:.6},{:.4},{:.3},{}",
                entry.step, lr, loss_v, grad_norm, entry.seconds, t
            )
            .map_err(io_err(&log_path))?;
        }
        on_step(step + 1, cfg.steps, &entry);
        if (step + 1) % cfg.checkpoint_every.max(1) == 0 || step + 1 == cfg.steps {
            save_checkpoint(
                &model,
                &opt_decay,
                &opt_plain,
                &ck,
                &recorder,
                TrainState {
                    step: step + 1,
                    train_seconds: prior_seconds + t_run.elapsed().as_secs_f64(),
                },
            )?;
        }
    }
    let tenth = (losses.len() / 10).max(1);
    let mean = |s: &[f64]| {
        if s.is_empty() {
            f64::NAN
        } else {
            s.iter().sum::<f64>() / s.len() as f64
        }
    };
    let summary = TrainSummary {
        steps: cfg.steps,
        train_seconds: prior_seconds + t_run.elapsed().as_secs_f64(),
        first_loss: mean(&losses[..tenth.min(losses.len())]),
        last_loss: mean(&losses[losses.len().saturating_sub(tenth)..]),
        resumed_from,
    };
    Ok((model, summary))
}

fn save_checkpoint<B, M, O1, O2>(
    model: &M,
    opt_decay: &O1,
    opt_plain: &O2,
    ck: &CheckpointPaths,
    recorder: &BinFileRecorder<FullPrecisionSettings>,
    state: TrainState,
) -> Result<(), TrainError>
where
    B: AutodiffBackend,
    M: AutodiffModule<B>,
    O1: Optimizer<M, B>,
    O2: Optimizer<M, B>,
{
    // Write into a temporary folder, then swap it in: an interrupted save never leaves a torn checkpoint.
    let tmp = ck.dir.with_extension("tmp");
    let _ = std::fs::remove_dir_all(&tmp);
    std::fs::create_dir_all(&tmp).map_err(io_err(&tmp))?;
    let t = CheckpointPaths { dir: tmp.clone() };
    model
        .clone()
        .save_file(t.model(), recorder)
        .map_err(|e| TrainError::Checkpoint(format!("{}: {e}", t.model().display())))?;
    recorder
        .record(opt_decay.to_record(), t.optim("decay"))
        .map_err(|e| TrainError::Checkpoint(format!("{}: {e}", t.optim("decay").display())))?;
    recorder
        .record(opt_plain.to_record(), t.optim("plain"))
        .map_err(|e| TrainError::Checkpoint(format!("{}: {e}", t.optim("plain").display())))?;
    let text =
        serde_json::to_string_pretty(&state).map_err(|e| TrainError::Checkpoint(e.to_string()))?;
    std::fs::write(t.state(), text).map_err(io_err(&t.state()))?;
    let old = ck.dir.with_extension("old");
    let _ = std::fs::remove_dir_all(&old);
    if ck.dir.exists() {
        std::fs::rename(&ck.dir, &old).map_err(io_err(&ck.dir))?;
    }
    std::fs::rename(&tmp, &ck.dir).map_err(io_err(&ck.dir))?;
    let _ = std::fs::remove_dir_all(&old);
    Ok(())
}
