//! `sparseocc demo`: the whole pipeline on built-in synthetic data.
//!
//! Today it runs: synthetic dataset generation (train + held-out val sequence, SemanticKITTI layout,
//! `kitti-small` grid) → the per-voxel prior baseline (most frequent training label of each voxel) →
//! predictions in the submission layout → official SemanticKITTI scoring → renders → `summary.json`.
//! The learned models (SparseOcc++, SparseOcc, dense) plug in at the prediction step once integrated;
//! until then the demo says so in its output and summary.

use crate::cmd_viz::render_panels;
use crate::labels_io::read_label_grid;
use crate::progress;
use anyhow::{Context, Result};
use occ_data::formats::semantic_kitti::{self as sk, KittiPaths};
use occ_data::labels::LearningMap;
use occ_data::synthetic::{self, Preset, SynthConfig};
use occ_eval::{format_table, score_semantic_kitti_folder, FolderOptions};
use std::path::PathBuf;
use std::time::Instant;

/// Arguments of `sparseocc demo`.
#[derive(clap::Args, Debug)]
pub struct DemoArgs {
    /// Output folder (data/, predictions/, renders/, summary.json).
    #[arg(long, default_value = "runs/demo")]
    pub out: PathBuf,
    /// Training sequence and frame count.
    #[arg(long, default_value = "00:24")]
    pub train: String,
    /// Held-out validation sequence and frame count.
    #[arg(long, default_value = "08:6")]
    pub val: String,
    /// Random seed.
    #[arg(long, default_value_t = 0)]
    pub seed: u64,
}

pub fn run(args: &DemoArgs) -> Result<()> {
    let t0 = Instant::now();
    let data = args.out.join("data");
    let pred_root = args.out.join("predictions");
    let train = synthetic::parse_sequences(&args.train)?;
    let val = synthetic::parse_sequences(&args.val)?;
    let mut seqs = train.clone();
    seqs.extend(val.iter().cloned());
    eprintln!("[1/4] generating synthetic scenes into {}", data.display());
    let cfg = SynthConfig::new(Preset::KittiSmall, args.seed, seqs);
    let pb = progress::bar(1, "synth");
    let summary = synthetic::generate(&data, &cfg, &mut progress::callback(&pb))?;
    pb.finish_and_clear();
    let grid = Preset::KittiSmall.grid();
    let n = grid.num_voxels();
    let paths = KittiPaths::new(&data);
    let map = LearningMap::semantic_kitti();

    eprintln!(
        "[2/4] fitting the per-voxel prior on {} training frames",
        train.iter().map(|s| s.1).sum::<usize>()
    );
    eprintln!("      (learned models are not integrated into the demo yet: this is the baseline they must beat)");
    let t_fit = Instant::now();
    let mut counts = vec![0u32; n * 20];
    for (seq, _) in &train {
        for frame in sk::list_stems(&data.join("sequences").join(seq).join("voxels"), "label")? {
            let labels = map.remap(&sk::read_label_raw(&paths.voxels(seq, &frame, "label"), n)?);
            for (i, &c) in labels.iter().enumerate() {
                if (c as usize) < 20 {
                    counts[i * 20 + c as usize] += 1;
                }
            }
        }
    }
    let prior: Vec<u8> = counts
        .chunks(20)
        .map(|c| {
            let mut best = 0;
            for k in 1..20 {
                if c[k] > c[best] {
                    best = k;
                }
            }
            best as u8
        })
        .collect();
    let train_seconds = t_fit.elapsed().as_secs_f64();

    eprintln!("[3/4] writing predictions and scoring the held-out sequence");
    let pred_paths = KittiPaths::new(&pred_root);
    let raw = map.inverse_remap(&prior);
    let mut first = None;
    for (seq, _) in &val {
        for frame in sk::list_stems(&data.join("sequences").join(seq).join("voxels"), "label")? {
            let p = pred_paths.prediction(seq, &frame);
            if let Some(dir) = p.parent() {
                std::fs::create_dir_all(dir)
                    .with_context(|| format!("creating {}", dir.display()))?;
            }
            sk::write_label_raw(&p, &raw)?;
            first.get_or_insert((seq.clone(), frame.clone(), p));
        }
    }
    let val_names: Vec<String> = val.iter().map(|s| s.0.clone()).collect();
    let report = score_semantic_kitti_folder(
        &data,
        &pred_root,
        &FolderOptions {
            sequences: Some(&val_names),
            ..Default::default()
        },
    )?;
    println!("{}", format_table(&report));

    eprintln!("[4/4] rendering");
    if let Some((seq, frame, pred_p)) = &first {
        let gt = read_label_grid(&paths.voxels(seq, frame, "label"))?;
        let pred = read_label_grid(pred_p)?;
        let out = args.out.join("renders").join(format!("{seq}_{frame}.png"));
        render_panels(
            &gt,
            Some(&pred),
            Some((&paths.image_2(seq, frame), &paths.calib(seq))),
            &out,
            360,
        )?;
        eprintln!("      wrote {}", out.display());
    }
    let summary_json = serde_json::json!({
        "model": "per-voxel prior (most frequent training label of each voxel); learned models not yet integrated",
        "iou": report.iou,
        "miou": report.miou,
        "precision": report.precision,
        "recall": report.recall,
        "per_class": report.per_class,
        "frames": report.frames,
        "train_seconds": train_seconds,
        "val_sequences": val_names,
        "synth_frames": summary.frames,
        "total_seconds": t0.elapsed().as_secs_f64(),
    });
    crate::util::write_json(&args.out.join("summary.json"), &summary_json)?;
    eprintln!(
        "done in {:.1} s; summary in {}",
        t0.elapsed().as_secs_f64(),
        args.out.join("summary.json").display()
    );
    Ok(())
}
