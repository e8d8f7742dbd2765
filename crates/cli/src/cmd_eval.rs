//! `sparseocc eval`: score a folder of predictions with the official protocol.

use crate::progress;
use anyhow::{Context, Result};
use occ_eval::{format_table, score_folder, FolderOptions, Protocol};
use std::path::PathBuf;

/// Arguments of `sparseocc eval`.
#[derive(clap::Args, Debug)]
pub struct EvalArgs {
    /// semantickitti (also kitti), occ3d, or nuscenes-occupancy (also nuscenes; OpenOccupancy
    /// layout scene_<scene_token>/occupancy/<lidar_token>.npy in both --gt and --pred).
    #[arg(long, default_value = "semantickitti")]
    pub dataset: String,
    /// Ground-truth dataset root (SemanticKITTI: the folder containing sequences/).
    #[arg(long)]
    pub gt: PathBuf,
    /// Prediction root (SemanticKITTI: sequences/XX/predictions/NNNNNN.label).
    #[arg(long)]
    pub pred: PathBuf,
    /// Sequences to score (comma-separated; SemanticKITTI ids, `8` = `08`, Occ3D scene names, or
    /// nuScenes-Occupancy scene tokens, `<token>` or `scene_<token>`), each once; default all with
    /// labels.
    #[arg(long)]
    pub sequences: Option<String>,
    /// Write the report as JSON here.
    #[arg(long)]
    pub json: Option<PathBuf>,
}

pub fn run(args: &EvalArgs) -> Result<occ_eval::EvalReport> {
    let seqs: Option<Vec<String>> = args
        .sequences
        .as_ref()
        .map(|s| s.split(',').map(|x| x.trim().to_string()).collect());
    let pb = progress::bar(0, "eval");
    let tick = || pb.inc(1);
    let opts = FolderOptions {
        sequences: seqs.as_deref(),
        on_frame: Some(&tick),
        ..Default::default()
    };
    let protocol: Protocol = args
        .dataset
        .parse()
        .map_err(|e| anyhow::anyhow!("eval: {e}"))?;
    let report = score_folder(protocol, &args.gt, &args.pred, &opts).with_context(|| {
        format!(
            "scoring {} against {}",
            args.pred.display(),
            args.gt.display()
        )
    })?;
    pb.finish_and_clear();
    println!("{}", format_table(&report));
    if let Some(j) = &args.json {
        crate::util::write_json(j, &report)?;
    }
    Ok(report)
}
