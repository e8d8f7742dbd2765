//! `sparseocc prepare semantickitti`: layout check and label preprocessing.

use crate::progress;
use anyhow::{Context, Result};
use occ_data::prepare::{prepare_semantic_kitti, PrepareOptions};
use std::path::PathBuf;

/// Arguments of `sparseocc prepare`.
#[derive(clap::Args, Debug)]
pub struct PrepareArgs {
    /// Dataset kind (only `semantickitti` has preprocessing).
    pub dataset: String,
    /// Dataset folder (the one containing `sequences/`).
    #[arg(long)]
    pub root: PathBuf,
    /// Only report what is present and missing; write nothing.
    #[arg(long)]
    pub check: bool,
    /// Restrict to these sequences (comma-separated).
    #[arg(long)]
    pub sequences: Option<String>,
    /// Rewrite existing label files.
    #[arg(long)]
    pub overwrite: bool,
    /// Write the report as JSON here.
    #[arg(long)]
    pub json: Option<PathBuf>,
}

pub fn run(args: &PrepareArgs) -> Result<()> {
    anyhow::ensure!(
        args.dataset == "semantickitti",
        "prepare: unknown dataset '{}' (supported: semantickitti)",
        args.dataset
    );
    let opts = PrepareOptions {
        check_only: args.check,
        sequences: args
            .sequences
            .as_ref()
            .map(|s| s.split(',').map(|x| x.trim().to_string()).collect()),
        out_root: None,
        overwrite: args.overwrite,
    };
    let pb = progress::bar(1, "prepare");
    let report = prepare_semantic_kitti(&args.root, &opts, &mut progress::callback(&pb))
        .with_context(|| format!("preparing {}", args.root.display()))?;
    pb.finish_and_clear();
    for s in &report.sequences {
        println!("{}", serde_json::to_string(s)?);
    }
    eprintln!(
        "{} sequences; {} frames with labels; written {}, skipped {}, failures {}",
        report.sequences.len(),
        report.preprocessable,
        report.written,
        report.skipped_existing,
        report.failures.len()
    );
    for f in &report.failures {
        eprintln!("  failed {}/{}: {}", f.sequence, f.frame, f.error);
    }
    if let Some(j) = &args.json {
        crate::util::write_json(j, &report)?;
    }
    anyhow::ensure!(report.ok(), "{} frames failed", report.failures.len());
    Ok(())
}
