//! `sparseocc synth`: procedural driving scenes in the real dataset layouts.

use crate::progress;
use anyhow::{Context, Result};
use occ_data::synthetic::{self, Preset, SynthConfig};
use std::path::PathBuf;

/// Arguments of `sparseocc synth`.
#[derive(clap::Args, Debug)]
pub struct SynthArgs {
    /// Output dataset folder.
    #[arg(long)]
    pub out: PathBuf,
    /// kitti (256x256x32, 1226x370), kitti-small (128x128x16, 613x185) or surround (Occ3D, 6 cameras).
    #[arg(long, default_value = "kitti-small")]
    pub preset: String,
    /// Sequences and frame counts, e.g. `00:40,08:10`; `A-B:N` is the range `A..=B` of `N` frames each
    /// (`10-49:4`).
    #[arg(long, default_value = "00:20,08:5")]
    pub sequences: String,
    /// Random seed (same seed, same files).
    #[arg(long, default_value_t = 0)]
    pub seed: u64,
    /// Image size WxH (default: the preset's).
    #[arg(long)]
    pub image_size: Option<String>,
}

pub fn parse_size(s: &str) -> Result<(usize, usize)> {
    let (w, h) = s
        .split_once(['x', 'X'])
        .with_context(|| format!("image size '{s}': expected WxH"))?;
    Ok((
        w.trim().parse().context("image width")?,
        h.trim().parse().context("image height")?,
    ))
}

pub fn run(args: &SynthArgs) -> Result<()> {
    let mut cfg = SynthConfig::new(
        args.preset.parse::<Preset>()?,
        args.seed,
        synthetic::parse_sequences(&args.sequences)?,
    );
    if let Some(s) = &args.image_size {
        cfg.image_size = Some(parse_size(s)?);
    }
    let pb = progress::bar(1, "synth");
    let summary = synthetic::generate(&args.out, &cfg, &mut progress::callback(&pb))
        .with_context(|| format!("generating into {}", args.out.display()))?;
    pb.finish_and_clear();
    eprintln!(
        "wrote {} frames ({} files, {:.1} MB) to {} in {:.1} s ({:.2} frames/s)",
        summary.frames,
        summary.files,
        summary.bytes as f64 / 1e6,
        args.out.display(),
        summary.seconds,
        summary.frames_per_second
    );
    synthetic::write_summary(&args.out, &summary)?;
    Ok(())
}
