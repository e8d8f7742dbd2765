//! The training loop: AdamW (weight-decay and no-decay groups), warmup + cosine schedule, global-norm
//! clipping, periodic validation, checkpoints every N steps with exact resume, CSV + JSON logs.
//!
//! Determinism: the frame order of epoch `e` is a permutation drawn from `(seed, e)`, and the
//! augmentation of step `s` from `(seed, s)`, so a run resumed from a checkpoint sees the same data as
//! an uninterrupted one.

use crate::config::RunConfig;
use crate::dataset::{collate, Dataset, Sample};
use crate::error::TrainError;
use crate::grads::{clip_global_norm, split_no_decay};
use crate::parallel::{abort_collective, all_reduce_grads, fingerprint, worker_device, Peer};
use crate::schedule::WarmupCosine;
use burn::module::AutodiffModule;
use burn::optim::{AdamWConfig, GradientsParams, Optimizer};
use burn::prelude::*;
use burn::record::{BinFileRecorder, FullPrecisionSettings, Recorder};
use burn::tensor::backend::AutodiffBackend;
use occ_geometry::VoxelGrid;
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
    /// Data-parallel workers (`sparseocc train --devices N`), each with its own replica of the
    /// network and a shard of `batch_size / devices` frames of every step ([`crate::parallel`]).
    /// On the CPU each worker gets `threads / devices` of the rayon threads.
    #[serde(default = "one", skip_serializing_if = "is_one")]
    pub devices: usize,
}

impl TrainConfig {
    /// Checks every setting: counts positive, every number finite and in its range. Errors name the
    /// key (`train.clip_norm`) and the value.
    pub fn validate(&self) -> Result<(), String> {
        let positive = [
            ("steps", self.steps),
            ("batch_size", self.batch_size),
            ("checkpoint_every", self.checkpoint_every),
            ("log_every", self.log_every),
            ("devices", self.devices),
        ];
        for (key, v) in positive {
            if v == 0 {
                return Err(format!("train.{key} = 0: must be at least 1"));
            }
        }
        // (key, value, what it must be, the check)
        type Range<'a> = (&'a str, f64, &'a str, fn(f64) -> bool);
        let ranges: [Range; 4] = [
            ("lr", self.lr, "a finite number > 0", |v| v > 0.0),
            (
                "weight_decay",
                self.weight_decay,
                "a finite number >= 0",
                |v| v >= 0.0,
            ),
            (
                "min_lr_ratio",
                self.min_lr_ratio,
                "a finite number in [0, 1]",
                |v| (0.0..=1.0).contains(&v),
            ),
            (
                "clip_norm",
                self.clip_norm,
                "a finite number > 0 (the largest gradient norm)",
                |v| v > 0.0,
            ),
        ];
        for (key, v, what, ok) in ranges {
            if !v.is_finite() || !ok(v) {
                return Err(format!("train.{key} = {v}: must be {what}"));
            }
        }
        if !self.batch_size.is_multiple_of(self.devices) {
            return Err(format!(
                "train.batch_size = {} is not a multiple of train.devices = {}: every worker trains on \
                 batch_size / devices frames",
                self.batch_size, self.devices
            ));
        }
        Ok(())
    }
}

fn one() -> usize {
    1
}
fn is_one(v: &usize) -> bool {
    *v == 1
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
    /// Frames of the step, over all workers (the global batch).
    pub frames: usize,
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
    /// The previous checkpoint, kept while a save swaps the new one in (`RUN/checkpoint.old`).
    pub fn old_dir(&self) -> PathBuf {
        self.dir.with_extension("old")
    }
}

/// Loads the samples of `idx` in parallel; `idx[j]` is frame `first + j` of the step's batch (its
/// augmentation is drawn from that position, so a worker's shard is augmented as on one device).
fn load_samples(
    ds: &Dataset,
    idx: &[usize],
    first: usize,
    augment_seed: Option<u64>,
) -> Result<Vec<Sample>, TrainError> {
    idx.par_iter()
        .enumerate()
        .map(|(j, &i)| (first + j, i))
        .map(|(j, i)| match augment_seed {
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

/// What every worker of a run shares: the settings, the data, the run folder and where it resumes.
struct Setup<'a, B: Backend> {
    cfg: &'a TrainConfig,
    ds: &'a Dataset,
    device: &'a B::Device,
    ck: CheckpointPaths,
    log_path: PathBuf,
    resume_state: Option<TrainState>,
}

/// One step's forward pass on a worker's frames: the total loss (to differentiate), its value and
/// its terms.
type StepLoss<B> = (Tensor<B, 1>, f64, Vec<(String, f64)>);

/// Trains `model` on `ds`, writing checkpoints and logs under `run`. With `resume`, continues from
/// `run/checkpoint` if one exists. `on_step(step, total, &log)` reports progress.
///
/// With `cfg.devices` > 1 the run is data-parallel ([`crate::parallel`]): that many workers on
/// threads of this process, each with a replica of `model` on `device` and its own rayon pool;
/// `on_step` is called on this thread with worker 0's log (the mean loss of all workers).
pub fn train<B, M>(
    model: M,
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
    cfg.validate().map_err(TrainError::Config)?;
    // Before anything is written: a resume needs a checkpoint to resume from.
    let ck = CheckpointPaths::new(run);
    let resume_state = if resume {
        match recover_checkpoint(run)? {
            Some(state) => Some(state),
            None => {
                return Err(TrainError::Checkpoint(format!(
                    "{}: no checkpoint to resume from (no {} with {}); drop --resume to start a new run",
                    run.display(),
                    ck.dir.display(),
                    ck.state().file_name().unwrap_or_default().to_string_lossy()
                )))
            }
        }
    } else {
        None
    };
    if let Some(state) = &resume_state {
        if state.step > cfg.steps {
            return Err(TrainError::Checkpoint(format!(
                "{}: the checkpoint is at step {} but the run has {} steps; give --steps {} or more",
                ck.state().display(),
                state.step,
                cfg.steps,
                state.step
            )));
        }
    }
    std::fs::create_dir_all(run).map_err(io_err(run))?;
    remove_stale_temporaries(&ck.dir);
    let log_path = run.join("train_log.csv");
    // The log holds each step once: a fresh run starts it anew; a resumed run keeps the header and
    // the rows up to the checkpoint's step (rows logged after it, by the interrupted process, are
    // redone and logged again).
    truncate_log(&log_path, resume_state.as_ref().map_or(0, |s| s.step))?;
    let setup = Setup {
        cfg,
        ds,
        device,
        ck,
        log_path,
        resume_state,
    };
    if cfg.devices <= 1 {
        return train_worker::<B, M>(model, &setup, device, None, on_step);
    }
    train_workers::<B, M>(model, &setup, on_step)
}

/// Runs `setup.cfg.devices` workers on scoped threads (see [`train`]); returns worker 0's network
/// and summary, or the first worker's own error (rather than the others' "a worker stopped").
fn train_workers<B, M>(
    model: M,
    setup: &Setup<B>,
    on_step: &mut dyn FnMut(usize, usize, &StepLog),
) -> Result<(M, TrainSummary), TrainError>
where
    B: AutodiffBackend,
    M: AutodiffModule<B> + OccNetwork<B>,
{
    let n = setup.cfg.devices;
    let threads = (rayon::current_num_threads() / n).max(1);
    // burn initialises parameters lazily, and a clone of an uninitialised parameter draws its own
    // values: touch every parameter (the fingerprint reads them all) before making the replicas.
    fingerprint::<B, M>(&model);
    // A clean collective: a run that failed earlier in this process may have left workers in it.
    abort_collective::<B::InnerBackend>();
    let (tx, rx) = std::sync::mpsc::channel::<StepLog>();
    let results = std::thread::scope(|s| {
        let handles: Vec<_> = (0..n)
            .map(|rank| {
                let model = model.clone();
                let tx = tx.clone();
                let device = worker_device::<B>(setup.device, rank, n);
                std::thread::Builder::new()
                    .name(format!("train-worker-{rank}"))
                    .spawn_scoped(s, move || {
                        let run = || -> Result<Option<(M, TrainSummary)>, TrainError> {
                            let pool = rayon::ThreadPoolBuilder::new()
                                .num_threads(threads)
                                .thread_name(move |i| format!("train-{rank}-{i}"))
                                .build()
                                .map_err(|e| TrainError::Parallel(format!("worker {rank}: {e}")))?;
                            let device = device?;
                            let model = model.fork(&device);
                            pool.install(|| {
                                let peer = Peer::<B::InnerBackend>::register(rank, n, &device)?;
                                let mut report = |_: usize, _: usize, log: &StepLog| {
                                    let _ = tx.send(log.clone());
                                };
                                let r = train_worker::<B, M>(
                                    model,
                                    setup,
                                    &device,
                                    Some(&peer),
                                    &mut report,
                                );
                                if r.is_ok() {
                                    peer.finish();
                                }
                                r.map(|(m, summary)| (rank == 0).then_some((m, summary)))
                            })
                        };
                        let r = std::panic::catch_unwind(std::panic::AssertUnwindSafe(run))
                            .unwrap_or_else(|panic| {
                                let msg = panic
                                    .downcast_ref::<String>()
                                    .cloned()
                                    .or_else(|| panic.downcast_ref::<&str>().map(|s| s.to_string()))
                                    .unwrap_or_default();
                                Err(TrainError::Parallel(format!(
                                    "worker {rank} panicked: {msg}"
                                )))
                            });
                        if r.is_err() {
                            // Release the workers waiting for this one.
                            abort_collective::<B::InnerBackend>();
                        }
                        r
                    })
            })
            .collect();
        drop(tx);
        for log in rx {
            on_step(log.step, setup.cfg.steps, &log);
        }
        handles
            .into_iter()
            .map(|h| match h {
                Ok(h) => h.join().unwrap_or_else(|_| {
                    Err(TrainError::Parallel("a worker thread panicked".into()))
                }),
                Err(e) => Err(TrainError::Parallel(format!(
                    "starting a worker thread: {e}"
                ))),
            })
            .collect::<Vec<_>>()
    });
    let mut first_err = None;
    let mut out = None;
    for r in results {
        match r {
            Ok(Some(x)) => out = Some(x),
            Ok(None) => {}
            // A worker's own error wins over the "a worker stopped" of the others.
            Err(e) => {
                let replace = match &first_err {
                    None => true,
                    Some(TrainError::Parallel(_)) => !matches!(e, TrainError::Parallel(_)),
                    Some(_) => false,
                };
                if replace {
                    first_err = Some(e);
                }
            }
        }
    }
    match (first_err, out) {
        (Some(e), _) => Err(e),
        (None, Some(x)) => Ok(x),
        (None, None) => Err(TrainError::Parallel("worker 0 returned nothing".into())),
    }
}

/// The forward pass and loss of one step on `idx` (frames `first..` of the step's batch). Everything
/// that can fail on one worker alone (a file, the loss) fails here, before the workers exchange
/// anything.
fn forward_loss<B, M>(
    model: &M,
    ds: &Dataset,
    idx: &[usize],
    first: usize,
    aug_seed: Option<u64>,
    device: &B::Device,
    step: usize,
) -> Result<StepLoss<B>, TrainError>
where
    B: AutodiffBackend,
    M: AutodiffModule<B> + OccNetwork<B>,
{
    let samples = load_samples(ds, idx, first, aug_seed)?;
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
        terms.push((name.to_string(), v));
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
    Ok((loss, loss_v, terms))
}

/// The training loop of one worker (`peer` = `None`: the only one). Worker 0 (or the only worker)
/// logs, reports and writes the checkpoints.
fn train_worker<B, M>(
    mut model: M,
    setup: &Setup<B>,
    device: &B::Device,
    peer: Option<&Peer<B::InnerBackend>>,
    on_step: &mut dyn FnMut(usize, usize, &StepLog),
) -> Result<(M, TrainSummary), TrainError>
where
    B: AutodiffBackend,
    M: AutodiffModule<B> + OccNetwork<B>,
{
    let Setup {
        cfg,
        ds,
        ck,
        log_path,
        resume_state,
        ..
    } = setup;
    let leader = peer.is_none_or(|p| p.rank() == 0);
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
    if let Some(state) = resume_state {
        model = load_weights(model, &ck.model(), device)?;
        for (which, opt) in [("decay", &mut opt_decay), ("plain", &mut opt_plain)] {
            let p = ck.optim(which);
            let rec = recorder.load(p.clone(), device).map_err(|e| {
                TrainError::Checkpoint(format!(
                    "{} (the optimizer state)",
                    record_error_text(&p.with_extension("bin"), &e.to_string())
                ))
            })?;
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
    let mut log = if leader {
        Some(
            std::fs::OpenOptions::new()
                .append(true)
                .open(log_path)
                .map_err(io_err(log_path))?,
        )
    } else {
        None
    };
    if let Some(p) = peer {
        if !p.same_everywhere(fingerprint::<B, M>(&model), "comparing the replicas")? {
            return Err(TrainError::Parallel(
                "the workers' networks differ before the first step".into(),
            ));
        }
    }
    let t_run = Instant::now();
    let mut losses = Vec::new();
    for step in start..cfg.steps {
        let t0 = Instant::now();
        let idx = batch_indices(ds.len(), cfg.batch_size, cfg.seed, step);
        let shard = peer.map_or(0..idx.len(), |p| p.shard(idx.len()));
        let aug_seed = cfg
            .augment
            .then(|| cfg.seed ^ (step as u64).wrapping_mul(0x2545_F491_4F6C_DD1D));
        let local = forward_loss::<B, M>(
            &model,
            ds,
            &idx[shard.clone()],
            shard.start,
            aug_seed,
            device,
            step,
        );
        let (loss, mut loss_v, mut terms) = match peer {
            None => local?,
            Some(p) => {
                let all_ok = p.all_ok(local.is_ok(), "agreeing on the step")?;
                match local {
                    Err(e) => return Err(e),
                    Ok(_) if !all_ok => {
                        return Err(TrainError::Parallel(format!(
                            "step {}: another worker failed (its error is reported)",
                            step + 1
                        )))
                    }
                    Ok(l) => l,
                }
            }
        };
        let mut grads = GradientsParams::from_grads(loss.backward(), &model);
        if let Some(p) = peer {
            grads = all_reduce_grads::<B, M>(p, &model, grads)?;
            let mut values = vec![loss_v];
            values.extend(terms.iter().map(|t| t.1));
            let mean = p.mean(&values, "averaging the losses")?;
            loss_v = mean[0];
            for (t, v) in terms.iter_mut().zip(&mean[1..]) {
                t.1 = *v;
            }
        }
        let grad_norm = clip_global_norm::<B, M>(&model, &mut grads, cfg.clip_norm);
        let plain = split_no_decay::<B, M>(&model, &mut grads);
        let lr = schedule.lr_at(step);
        model = opt_decay.step(lr, model, grads);
        model = opt_plain.step(lr, model, plain);
        if let Some(p) = peer {
            if !p.same_everywhere(fingerprint::<B, M>(&model), "comparing the replicas")? {
                return Err(TrainError::Parallel(format!(
                    "the workers' networks differ after step {}: the data-parallel run is broken",
                    step + 1
                )));
            }
        }
        let entry = StepLog {
            step: step + 1,
            lr,
            loss: loss_v,
            terms,
            grad_norm,
            seconds: t0.elapsed().as_secs_f64(),
            frames: cfg.batch_size,
        };
        losses.push(loss_v);
        if !leader {
            continue;
        }
        if let Some(log) = &mut log {
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
                .map_err(io_err(log_path))?;
            }
        }
        on_step(step + 1, cfg.steps, &entry);
        if (step + 1) % cfg.checkpoint_every.max(1) == 0 || step + 1 == cfg.steps {
            save_checkpoint(
                &model,
                &opt_decay,
                &opt_plain,
                ck,
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
    // Write into a fresh temporary folder, then swap it in: an interrupted save never leaves a torn
    // checkpoint. A kill between the two renames leaves only `checkpoint.old`, the previous complete
    // checkpoint, which [`recover_checkpoint`] puts back.
    let tmp = occ_data::formats::io::temp_sibling(&ck.dir);
    std::fs::create_dir_all(&tmp).map_err(io_err(&tmp))?;
    let t = CheckpointPaths { dir: tmp.clone() };
    let result = (|| -> Result<(), TrainError> {
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
        // The state is written last: a folder with state.json is complete.
        let text = serde_json::to_string_pretty(&state)
            .map_err(|e| TrainError::Checkpoint(e.to_string()))?;
        occ_data::formats::io::write_atomic(&t.state(), text.as_bytes())?;
        Ok(())
    })();
    if let Err(e) = result {
        let _ = std::fs::remove_dir_all(&tmp);
        return Err(e);
    }
    let old = ck.old_dir();
    if ck.dir.exists() {
        let _ = std::fs::remove_dir_all(&old);
        std::fs::rename(&ck.dir, &old).map_err(io_err(&ck.dir))?;
    }
    std::fs::rename(&tmp, &ck.dir).map_err(io_err(&ck.dir))?;
    let _ = std::fs::remove_dir_all(&old);
    Ok(())
}

/// A burn record error as one plain sentence: burn's "Unable to load record" carries nested,
/// escaped debug text and a hint about format versions that does not apply to a damaged file.
pub fn record_error_text(path: &Path, err: &str) -> String {
    let size = std::fs::metadata(path)
        .map(|m| format!(", {} bytes", m.len()))
        .unwrap_or_default();
    if err.contains("UnexpectedEof") || err.contains("failed to fill whole buffer") {
        format!(
            "{}: truncated or damaged (ends before the record is complete{size})",
            path.display()
        )
    } else if err.contains("Unable to load record") || err.contains("Unknown(") {
        format!(
            "{}: not a readable burn record (damaged, or not written by sparseocc{size})",
            path.display()
        )
    } else {
        format!("{}: {}", path.display(), first_line(err))
    }
}

/// Loads weights saved by [`train`] into `model` (shapes checked against the config by
/// [`occ_model::load_checked`]); a damaged file is an error naming it in one line.
pub fn load_weights<B: burn::tensor::backend::Backend, M: burn::module::Module<B>>(
    model: M,
    path: &Path,
    device: &B::Device,
) -> Result<M, TrainError> {
    let bin = path.with_extension("bin");
    let file = if path.extension().is_some() {
        path
    } else {
        bin.as_path()
    };
    if !file.is_file() {
        return Err(TrainError::Checkpoint(format!(
            "{}: missing (no weights in the checkpoint)",
            file.display()
        )));
    }
    occ_model::load_checked(model, path, device).map_err(|e| {
        let text = e.to_string();
        if text.contains("Unable to load record") || text.contains("Unknown(") {
            TrainError::Checkpoint(record_error_text(file, &text))
        } else {
            TrainError::Checkpoint(text)
        }
    })
}

/// A trained run loaded from its folder (or its `checkpoint/` folder): the run configuration, the
/// label grid it was trained on (`grid.json`) and the model with the checkpoint's weights. Every
/// error names the file (a missing `config.toml`, an unreadable grid, weights that do not match
/// the configuration).
pub fn load_run<B: occ_model::ModelBackend>(
    path: &Path,
    device: &B::Device,
) -> Result<(RunConfig, VoxelGrid, occ_model::OccNet<B>), TrainError> {
    let run = if path.join("config.toml").exists() {
        path.to_path_buf()
    } else if path.file_name().is_some_and(|n| n == "checkpoint")
        && path
            .parent()
            .is_some_and(|p| p.join("config.toml").exists())
    {
        path.parent().map(Path::to_path_buf).unwrap_or_default()
    } else {
        return Err(TrainError::Checkpoint(format!(
            "{}: not a training run (no config.toml in it or its parent)",
            path.display()
        )));
    };
    let cfg_path = run.join("config.toml");
    let cfg = RunConfig::load(&cfg_path)?;
    let grid_p = run.join("grid.json");
    let text = std::fs::read(&grid_p).map_err(io_err(&grid_p))?;
    let grid: VoxelGrid = serde_json::from_slice(&text).map_err(|e| {
        TrainError::Checkpoint(format!("{}: not a voxel grid: {e}", grid_p.display()))
    })?;
    let model: occ_model::OccNet<B> = cfg.model.init(device)?;
    let weights = run.join("checkpoint").join("model.bin");
    let model = load_weights(model, &weights, device).map_err(|e| {
        let e = e.to_string();
        if e.contains("truncated or damaged")
            || e.contains("not a readable burn record")
            || e.contains("missing")
        {
            TrainError::Checkpoint(e)
        } else {
            TrainError::Checkpoint(format!(
                "{e} (config {}; the checkpoint does not match it)",
                cfg_path.display()
            ))
        }
    })?;
    Ok((cfg, grid, model))
}

fn first_line(s: &str) -> &str {
    s.lines().next().unwrap_or_default()
}

fn read_state(path: &Path) -> Result<TrainState, TrainError> {
    let text = std::fs::read_to_string(path).map_err(io_err(path))?;
    serde_json::from_str(&text).map_err(|e| {
        TrainError::Checkpoint(format!(
            "{}: not a training state ({e}); the checkpoint is damaged",
            path.display()
        ))
    })
}

/// The checkpoint of `run` to resume from, after repairing an interrupted save: with `checkpoint/`
/// complete (its `state.json` written), that one (a leftover `checkpoint.old` is removed); with only
/// `checkpoint.old` left (a kill between the two renames of a save), that previous checkpoint is
/// moved back to `checkpoint/`. `None` when the run has no checkpoint at all.
pub fn recover_checkpoint(run: &Path) -> Result<Option<TrainState>, TrainError> {
    let ck = CheckpointPaths::new(run);
    let old = ck.old_dir();
    if ck.state().is_file() {
        let state = read_state(&ck.state())?;
        if old.exists() {
            let _ = std::fs::remove_dir_all(&old);
        }
        return Ok(Some(state));
    }
    let old_ck = CheckpointPaths { dir: old.clone() };
    if old_ck.state().is_file() {
        let state = read_state(&old_ck.state())?;
        if ck.dir.exists() {
            // An incomplete checkpoint/ (no state.json) is never written by `save_checkpoint`;
            // keep it aside rather than deleting it.
            let aside = occ_data::formats::io::temp_sibling(&ck.dir.with_extension("incomplete"));
            std::fs::rename(&ck.dir, &aside).map_err(io_err(&ck.dir))?;
        }
        std::fs::rename(&old, &ck.dir).map_err(io_err(&old))?;
        return Ok(Some(state));
    }
    if ck.dir.exists() {
        return Err(TrainError::Checkpoint(format!(
            "{}: missing; the checkpoint in {} is incomplete",
            ck.state().display(),
            ck.dir.display()
        )));
    }
    Ok(None)
}

/// Removes the temporary checkpoint folders left by killed saves (`.checkpoint.tmp-<pid>-...` of
/// processes that are gone; on systems without `/proc`, none are removed).
fn remove_stale_temporaries(ck_dir: &Path) {
    let (Some(parent), Some(name)) = (ck_dir.parent(), ck_dir.file_name()) else {
        return;
    };
    let name = name.to_string_lossy();
    let Ok(entries) = std::fs::read_dir(parent) else {
        return;
    };
    let proc = Path::new("/proc/self");
    if !proc.exists() {
        return;
    }
    let prefix = format!(".{name}.tmp-");
    for e in entries.flatten() {
        let f = e.file_name();
        let Some(rest) = f.to_str().and_then(|f| f.strip_prefix(&prefix)) else {
            continue;
        };
        let Some(pid) = rest.split('-').next().and_then(|p| p.parse::<u32>().ok()) else {
            continue;
        };
        if pid != std::process::id() && !Path::new(&format!("/proc/{pid}")).exists() {
            let _ = std::fs::remove_dir_all(e.path());
        }
    }
}

/// Makes `train_log.csv` the log of steps `1..=step`: a fresh log (header only) for step 0, else
/// the header and the rows of steps up to `step` of the existing log (rewritten atomically).
fn truncate_log(path: &Path, step: usize) -> Result<(), TrainError> {
    const HEADER: &str = "step,lr,loss,grad_norm,seconds,terms";
    let mut text = format!("{HEADER}\n");
    if step > 0 {
        match std::fs::read_to_string(path) {
            Ok(old) => {
                for line in old.lines() {
                    let Some(s) = line.split(',').next().and_then(|s| s.parse::<usize>().ok())
                    else {
                        continue;
                    };
                    if s <= step {
                        text.push_str(line);
                        text.push('\n');
                    }
                }
            }
            Err(e) if e.kind() == std::io::ErrorKind::NotFound => {}
            Err(e) => return Err(io_err(path)(e)),
        }
    }
    occ_data::formats::io::write_atomic(path, text.as_bytes())?;
    Ok(())
}
