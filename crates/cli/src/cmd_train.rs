//! `sparseocc train --config C --data DIR --out RUN [--resume]`: trains a model on a dataset in the
//! config's layout (`data.format`: SemanticKITTI, Occ3D or nuScenes-Occupancy; real or synthetic),
//! checkpointing under `RUN/checkpoint`, logging to
//! `RUN/train_log.csv`, and (with validation sequences) scoring the held-out frames at the end.

use crate::runs::run_with;
use crate::util::ModelArg;
use anyhow::{bail, Result};
use occ_train::RunConfig;
use std::path::PathBuf;

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
    /// Data-parallel workers (`train.devices`): each trains a replica on batch_size / N frames of
    /// every step, gradients all-reduced before the clipping and the optimizer step. On the CPU the
    /// workers share the machine's threads.
    #[arg(long)]
    pub devices: Option<usize>,
    /// Override how often a step is logged to train_log.csv (`train.log_every`; 1: every step,
    /// which step timings need).
    #[arg(long)]
    pub log_every: Option<usize>,
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
    if let Some(n) = args.devices {
        cfg.train.devices = n;
    }
    if let Some(n) = args.log_every {
        cfg.train.log_every = n;
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
