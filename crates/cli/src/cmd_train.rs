//! `sparseocc train --config C --data DIR --out RUN [--resume]`: trains a model on a dataset in the
//! config's layout (`data.format`: SemanticKITTI, Occ3D or nuScenes-Occupancy; real or synthetic),
//! checkpointing under `RUN/checkpoint`, logging to
//! `RUN/train_log.csv`, and (with validation sequences) scoring the held-out frames at the end.

use crate::backend::{self, Infer, Train};
use crate::progress;
use crate::util::ModelArg;
use anyhow::{bail, Context, Result};
use burn::module::{AutodiffModule, Module};
use occ_eval::{format_table, EvalReport as Report};
use occ_model::OccNet;
use occ_train::dataset::Dataset;
use occ_train::infer::predict_dataset;
use occ_train::trainer::{train, TrainSummary};
use occ_train::RunConfig;
use std::path::{Path, PathBuf};

/// Arguments of `sparseocc train`.
#[derive(clap::Args, Debug)]
pub struct TrainArgs {
    /// Run configuration (TOML; see configs/). Optional with --resume (RUN/config.toml is used).
    #[arg(long)]
    pub config: Option<PathBuf>,
    /// Dataset root (SemanticKITTI: the folder with sequences/; nuScenes layouts: the folder with
    /// samples/, the v1.0-* tables and the ground truth).
    #[arg(long)]
    pub data: PathBuf,
    /// Run folder (config.toml, checkpoint/, train_log.csv, summary.json).
    #[arg(long)]
    pub out: PathBuf,
    /// Continue from RUN/checkpoint.
    #[arg(long)]
    pub resume: bool,
    /// Override the model.
    #[arg(long, value_enum)]
    pub model: Option<ModelArg>,
    /// Override the training sequences (comma-separated).
    #[arg(long, value_delimiter = ',')]
    pub sequences: Option<Vec<String>>,
    /// Override the validation sequences (comma-separated; empty string for none).
    #[arg(long, value_delimiter = ',')]
    pub val_sequences: Option<Vec<String>>,
    /// Override the number of optimizer steps.
    #[arg(long)]
    pub steps: Option<usize>,
}

/// What `train` did (also written to `RUN/summary.json`).
pub struct TrainOutcome {
    /// The trained model (inference backend).
    pub model: OccNet<Infer>,
    /// Loop summary.
    pub summary: TrainSummary,
}

/// Resolves the run configuration from the arguments.
pub fn resolve_config(args: &TrainArgs) -> Result<RunConfig> {
    let saved = args.out.join("config.toml");
    let mut cfg = match (&args.config, args.resume && saved.exists()) {
        (_, true) => {
            let c = RunConfig::load(&saved)?;
            if let Some(p) = &args.config {
                let given = RunConfig::load(p)?;
                if given.to_toml()? != c.to_toml()? && args.model.is_none() {
                    bail!(
                        "--resume: {} differs from the run's {}; resume without --config or start a new run",
                        p.display(),
                        saved.display()
                    );
                }
            }
            c
        }
        (Some(p), false) => RunConfig::load(p)?,
        (None, false) => bail!(
            "--config is required (or --resume with an existing {})",
            saved.display()
        ),
    };
    if let Some(m) = args.model {
        cfg.model.kind = m.into();
    }
    if let Some(s) = &args.sequences {
        cfg.data.train_sequences = s.iter().filter(|s| !s.is_empty()).cloned().collect();
    }
    if let Some(s) = &args.val_sequences {
        cfg.data.val_sequences = s.iter().filter(|s| !s.is_empty()).cloned().collect();
    }
    if let Some(n) = args.steps {
        cfg.train.steps = n;
    }
    cfg.validate().map_err(anyhow::Error::msg)?;
    if cfg.data.train_sequences.is_empty() {
        bail!("no training sequences (set data.train_sequences or --sequences)");
    }
    Ok(cfg)
}

pub fn run(args: &TrainArgs) -> Result<()> {
    let cfg = resolve_config(args)?;
    run_with(&cfg, &args.data, &args.out, args.resume, true).map(|_| ())
}

/// Trains with `cfg` on `data` into `out`; validates on `cfg.data.val_sequences` when `validate`.
pub fn run_with(
    cfg: &RunConfig,
    data: &Path,
    out: &Path,
    resume: bool,
    validate: bool,
) -> Result<TrainOutcome> {
    // Nothing is written into the run folder before the settings, the checkpoint to resume from
    // and the dataset have been checked.
    cfg.validate().map_err(anyhow::Error::msg)?;
    if resume && occ_train::trainer::recover_checkpoint(out)?.is_none() {
        bail!(
            "{}: --resume, but the run has no checkpoint ({} is missing); drop --resume to start a new run",
            out.display(),
            out.join("checkpoint").join("state.json").display()
        );
    }
    let mut ds = Dataset::open(
        data,
        &cfg.data,
        &cfg.data.train_sequences,
        &cfg.data.val_sequences,
    )?;
    ds.set_load_points(cfg.model.needs_points_for_training());
    if ds.grid().dims != cfg.model.full_dims {
        bail!(
            "{}: the dataset grid is {:?} but the config's model.full_dims is {:?}",
            data.display(),
            ds.grid().dims,
            cfg.model.full_dims
        );
    }
    // Every frame's headers and file sizes, of the training and the validation frames, before the
    // first step (a bad file otherwise stops the run when that frame comes up).
    let pb = progress::bar(ds.len() as u64, "check data");
    ds.check_all(&mut progress::callback(&pb))?;
    if validate && !cfg.data.val_sequences.is_empty() {
        let mut val = Dataset::open(data, &cfg.data, &cfg.data.val_sequences, &[])?;
        val.set_load_points(cfg.model.needs_points_at_test());
        val.check_all(&mut progress::callback(&pb))?;
    }
    pb.finish_and_clear();
    std::fs::create_dir_all(out).with_context(|| format!("creating {}", out.display()))?;
    let toml_path = out.join("config.toml");
    crate::util::write_file(&toml_path, cfg.to_toml()?.as_bytes())?;
    crate::util::write_json(&out.join("grid.json"), &ds.grid())?;

    let device = backend::device();
    // Seeded initial weights (`train.seed`): burn draws parameter initialisations from the backend's
    // generator, which is seeded from the OS unless set, so without this two runs of the same config
    // start from different networks.
    <Train as burn::tensor::backend::Backend>::seed(&device, cfg.train.seed);
    let model: OccNet<Train> = cfg.model.init(&device)?;
    eprintln!(
        "training {} on {} frames ({}), {} steps, {} parameters, {}",
        cfg.model.kind.name(),
        ds.len(),
        cfg.data.train_sequences.join(","),
        cfg.train.steps,
        model.num_params(),
        backend::describe()
    );
    let pb = progress::bar(cfg.train.steps as u64, "train");
    let (model, summary) = train(
        model,
        &cfg.train,
        &ds,
        out,
        resume,
        &device,
        &mut |step, total, log| {
            pb.set_length(total as u64);
            pb.set_position(step as u64);
            pb.set_message(format!("loss {:.3}", log.loss));
            if std::env::var_os("CI").is_some() && (step % 25 == 0 || step == total) {
                eprintln!(
                    "  step {step}/{total} loss {:.4} ({:.2} s/step)",
                    log.loss, log.seconds
                );
            }
        },
    )?;
    pb.finish_and_clear();
    eprintln!(
        "trained {} steps in {:.1} s (loss {:.3} -> {:.3}){}",
        summary.steps,
        summary.train_seconds,
        summary.first_loss,
        summary.last_loss,
        summary
            .resumed_from
            .map(|s| format!(", resumed from step {s}"))
            .unwrap_or_default()
    );
    let model = model.valid();
    let (val, spf) = if validate && !cfg.data.val_sequences.is_empty() {
        let (r, spf) = validate_on(&model, cfg, data, &out.join("val_predictions"))?;
        (Some(r), Some(spf))
    } else {
        (None, None)
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
        "device": backend::describe(),
    });
    if let Some(r) = &val {
        json["iou"] = serde_json::json!(r.iou);
        json["miou"] = serde_json::json!(r.miou);
        json["per_class"] = serde_json::json!(r.per_class);
        json["val_seconds_per_frame"] = serde_json::json!(spf);
    }
    crate::util::write_json(&out.join("summary.json"), &json)?;
    crate::curves::write_curves(out, val.as_ref().map(|r| (r.iou, r.miou)))?;
    Ok(TrainOutcome { model, summary })
}

/// Predicts the validation sequences into `pred_root` and scores them; returns the report and the
/// mean forward time per frame.
pub fn validate_on(
    model: &OccNet<Infer>,
    cfg: &RunConfig,
    data: &Path,
    pred_root: &Path,
) -> Result<(Report, f64)> {
    let mut ds = Dataset::open(data, &cfg.data, &cfg.data.val_sequences, &[])?;
    ds.set_load_points(cfg.model.needs_points_at_test());
    let pb = progress::bar(ds.len() as u64, "predict");
    let written = predict_dataset(
        model,
        &ds,
        pred_root,
        &backend::device(),
        cfg.data.test_mirror,
        &mut |d, t, _, _| {
            pb.set_length(t as u64);
            pb.set_position(d as u64);
        },
    )?;
    pb.finish_and_clear();
    let spf = written.iter().map(|w| w.1).sum::<f64>() / written.len().max(1) as f64;
    let report = ds.score(pred_root)?;
    println!("{}", format_table(&report));
    eprintln!(
        "validation ({}): IoU {:.3}, mIoU {:.3}, {:.3} s per frame",
        cfg.data.val_sequences.join(","),
        report.iou,
        report.miou,
        spf
    );
    Ok((report, spf))
}
