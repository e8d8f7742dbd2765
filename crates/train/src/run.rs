//! A whole training run as `sparseocc train` and `sparseocc demo` do it: check the settings, the
//! checkpoint to resume from and every frame of the dataset before anything is written, train with a
//! seeded network, optionally predict and score the validation sequences, and leave the run folder
//! (`config.toml`, `grid.json`, `checkpoint/`, `train_log.csv`, `summary.json`).
//!
//! Front ends (the CLI's progress bars, a notebook) follow the run through [`RunProgress`] events;
//! nothing here prints.

use crate::dataset::Dataset;
use crate::error::TrainError;
use crate::infer::predict_dataset;
use crate::trainer::{recover_checkpoint, train, StepLog, TrainSummary};
use crate::RunConfig;
use burn::module::{AutodiffModule, Module};
use burn::tensor::backend::{AutodiffBackend, Backend};
use occ_eval::EvalReport;
use occ_model::ModelBackend;
use occ_model::OccNet;
use std::path::Path;

/// What a run reports while it goes.
pub enum RunProgress<'a> {
    /// `done` of `total` frames checked (training and validation frames together).
    CheckData {
        /// Frames checked.
        done: usize,
        /// Frames to check.
        total: usize,
    },
    /// Training starts.
    Started {
        /// Training frames.
        frames: usize,
        /// Parameters of the network.
        parameters: usize,
    },
    /// One optimizer step done.
    Step {
        /// Step (1-based).
        step: usize,
        /// Steps of the run.
        total: usize,
        /// The step's losses and timing.
        log: &'a StepLog,
    },
    /// Training ended (before validation).
    Trained(&'a TrainSummary),
    /// `done` of `total` validation frames predicted.
    Predict {
        /// Frames predicted.
        done: usize,
        /// Frames to predict.
        total: usize,
    },
}

/// Scores of the validation sequences.
#[derive(Clone, Debug)]
pub struct Validation {
    /// The official scoring of the predictions.
    pub report: EvalReport,
    /// Mean forward time per frame, seconds.
    pub seconds_per_frame: f64,
}

/// What [`train_run`] did.
pub struct RunOutcome<B: Backend> {
    /// The trained network, on the inference backend.
    pub model: OccNet<B>,
    /// The training loop's summary.
    pub summary: TrainSummary,
    /// Validation scores (when validation ran).
    pub validation: Option<Validation>,
}

fn write_atomic(path: &Path, bytes: &[u8]) -> Result<(), TrainError> {
    Ok(occ_data::formats::io::write_atomic(path, bytes)?)
}

fn write_json(path: &Path, value: &serde_json::Value) -> Result<(), TrainError> {
    let text = serde_json::to_string_pretty(value)
        .map_err(|e| TrainError::Data(format!("{}: {e}", path.display())))?;
    write_atomic(path, text.as_bytes())
}

/// What to run: a configuration, the dataset and the run folder.
#[derive(Clone, Copy, Debug)]
pub struct RunSpec<'a> {
    /// The run configuration.
    pub cfg: &'a RunConfig,
    /// Dataset root.
    pub data: &'a Path,
    /// Run folder.
    pub out: &'a Path,
    /// Continue from `out/checkpoint`.
    pub resume: bool,
    /// Predict and score `cfg.data.val_sequences` after training (when there are any).
    pub validate: bool,
}

/// Trains with `spec.cfg` on the dataset at `spec.data` into the run folder `spec.out` (resuming
/// from `out/checkpoint` when `resume`), then predicts and scores `cfg.data.val_sequences` into
/// `out/val_predictions` when `validate` and there are any. `device_name` is recorded in
/// `summary.json`.
///
/// Nothing is written into `out` before the settings, the checkpoint to resume from and every frame
/// (training and validation) have been checked.
pub fn train_run<B>(
    spec: RunSpec,
    device: &B::Device,
    device_name: &str,
    progress: &mut dyn FnMut(RunProgress),
) -> Result<RunOutcome<B::InnerBackend>, TrainError>
where
    B: AutodiffBackend + ModelBackend,
    B::InnerBackend: ModelBackend,
{
    let RunSpec {
        cfg,
        data,
        out,
        resume,
        validate,
    } = spec;
    cfg.validate().map_err(TrainError::Config)?;
    if resume && recover_checkpoint(out)?.is_none() {
        return Err(TrainError::Checkpoint(format!(
            "{}: --resume, but the run has no checkpoint ({} is missing); drop --resume to start a new run",
            out.display(),
            out.join("checkpoint").join("state.json").display()
        )));
    }
    let mut ds = Dataset::open(
        data,
        &cfg.data,
        &cfg.data.train_sequences,
        &cfg.data.val_sequences,
    )?;
    ds.set_load_points(cfg.model.needs_points_for_training());
    if ds.grid().dims != cfg.model.full_dims {
        return Err(TrainError::Data(format!(
            "{}: the dataset grid is {:?} but the config's model.full_dims is {:?}",
            data.display(),
            ds.grid().dims,
            cfg.model.full_dims
        )));
    }
    // Every frame's headers and file sizes before the first step (a bad file otherwise stops the run
    // when that frame comes up).
    let val = if validate && !cfg.data.val_sequences.is_empty() {
        let mut v = Dataset::open(data, &cfg.data, &cfg.data.val_sequences, &[])?;
        v.set_load_points(cfg.model.needs_points_at_test());
        Some(v)
    } else {
        None
    };
    let total = ds.len() + val.as_ref().map_or(0, Dataset::len);
    ds.check_all(&mut |done, _| progress(RunProgress::CheckData { done, total }))?;
    if let Some(v) = &val {
        let base = ds.len();
        v.check_all(&mut |done, _| {
            progress(RunProgress::CheckData {
                done: base + done,
                total,
            })
        })?;
    }
    std::fs::create_dir_all(out).map_err(|source| TrainError::Io {
        path: out.to_path_buf(),
        source,
    })?;
    let toml = cfg.to_toml()?;
    write_atomic(&out.join("config.toml"), toml.as_bytes())?;
    let grid =
        serde_json::to_value(ds.grid()).map_err(|e| TrainError::Data(format!("grid.json: {e}")))?;
    write_json(&out.join("grid.json"), &grid)?;

    // Seeded initial weights (`train.seed`): burn draws parameter initialisations from the backend's
    // generator, which is seeded from the OS unless set, so without this two runs of the same config
    // start from different networks.
    B::seed(device, cfg.train.seed);
    let model: OccNet<B> = cfg.model.init(device)?;
    progress(RunProgress::Started {
        frames: ds.len(),
        parameters: model.num_params(),
    });
    let (model, summary) = train(
        model,
        &cfg.train,
        &ds,
        out,
        resume,
        device,
        &mut |step, total, log| progress(RunProgress::Step { step, total, log }),
    )?;
    progress(RunProgress::Trained(&summary));
    let model = model.valid();
    let validation = match val {
        Some(_) => Some(validate_on(
            &model,
            cfg,
            data,
            &out.join("val_predictions"),
            device,
            progress,
        )?),
        None => None,
    };
    let mut json = serde_json::json!({
        "model": cfg.model.kind.name(),
        "steps": summary.steps,
        "train_seconds": summary.train_seconds,
        "first_loss": summary.first_loss,
        "last_loss": summary.last_loss,
        "resumed_from": summary.resumed_from,
        "train_sequences": cfg.data.train_sequences,
        "val_sequences": cfg.data.val_sequences,
        "device": device_name,
    });
    if let Some(v) = &validation {
        json["iou"] = serde_json::json!(v.report.iou);
        json["miou"] = serde_json::json!(v.report.miou);
        json["per_class"] = serde_json::json!(v.report.per_class);
        json["val_seconds_per_frame"] = serde_json::json!(v.seconds_per_frame);
    }
    write_json(&out.join("summary.json"), &json)?;
    Ok(RunOutcome {
        model,
        summary,
        validation,
    })
}

/// Predicts `cfg.data.val_sequences` of the dataset at `data` into `pred_root` (the dataset's
/// submission layout) and scores them with the layout's official protocol.
pub fn validate_on<B: ModelBackend>(
    model: &OccNet<B>,
    cfg: &RunConfig,
    data: &Path,
    pred_root: &Path,
    device: &B::Device,
    progress: &mut dyn FnMut(RunProgress),
) -> Result<Validation, TrainError> {
    let mut ds = Dataset::open(data, &cfg.data, &cfg.data.val_sequences, &[])?;
    ds.set_load_points(cfg.model.needs_points_at_test());
    let written = predict_dataset(
        model,
        &ds,
        pred_root,
        device,
        cfg.data.test_mirror,
        &mut |done, total, _, _| progress(RunProgress::Predict { done, total }),
    )?;
    let seconds_per_frame = written.iter().map(|w| w.1).sum::<f64>() / written.len().max(1) as f64;
    let report = ds.score(pred_root)?;
    Ok(Validation {
        report,
        seconds_per_frame,
    })
}
