//! `sparseocc demo`: the whole pipeline on built-in synthetic data.
//!
//! Synthetic dataset (train + held-out val sequence, SemanticKITTI layout, `kitti-small` grid) →
//! SparseOcc++ trained with `configs/synthetic_tiny.toml` (built into the binary; `--config` to use
//! another, `--model` to train SparseOcc or the dense baseline instead) → predictions on the held-out
//! sequence in the submission layout → official SemanticKITTI scoring → renders → `summary.json`.
//! The per-voxel prior (most frequent training label of each voxel) is scored beside it as the
//! baseline a learned model must beat.

use crate::labels_io::read_label_grid;
use crate::panels::render_panels;
use crate::progress;
use crate::runs::{run_with, validate_with_bars};
use crate::util::ModelArg;
use anyhow::{Context, Result};
use occ_data::formats::semantic_kitti::{self as sk, KittiPaths};
use occ_data::labels::LearningMap;
use occ_data::synthetic::{self, Preset, SynthConfig};
use occ_eval::{
    score_semantic_kitti_folder, semantic_kitti_recall_by_visibility, EvalReport, FolderOptions,
    VisibilityRecall, SEMANTIC_KITTI_GROUND_CLASSES,
};
use occ_train::config::SYNTHETIC_TINY;
use occ_train::RunConfig;
use std::path::{Path, PathBuf};
use std::time::Instant;

/// Arguments of `sparseocc demo`.
#[derive(clap::Args, Debug)]
pub struct DemoArgs {
    /// Output folder (data/, run/, predictions/, prior_predictions/, renders/, summary.json).
    #[arg(long, default_value = "runs/demo")]
    pub out: PathBuf,
    /// Training sequences and frame counts (each sequence is its own procedurally generated street;
    /// `A-B:N` is the range `A..=B` of `N` frames each): 40 streets of four frames by default, 00-07 and
    /// 10-41 (the held-out street is 08).
    #[arg(long, default_value = "00-07:4,10-41:4")]
    pub train: String,
    /// Held-out validation sequence and frame count.
    #[arg(long, default_value = "08:6")]
    pub val: String,
    /// Random seed (data and training).
    #[arg(long, default_value_t = 0)]
    pub seed: u64,
    /// Run configuration (default: the built-in configs/synthetic_tiny.toml).
    #[arg(long)]
    pub config: Option<PathBuf>,
    /// Train this model instead.
    #[arg(long, value_enum)]
    pub model: Option<ModelArg>,
    /// Override the number of training steps.
    #[arg(long)]
    pub steps: Option<usize>,
}

/// Fits the per-voxel prior on the training sequences and writes its predictions for `val`.
fn prior_baseline(
    data: &Path,
    train: &[(String, usize)],
    val: &[(String, usize)],
    pred_root: &Path,
    n: usize,
) -> Result<EvalReport> {
    let paths = KittiPaths::new(data);
    let map = LearningMap::semantic_kitti();
    let mut counts = vec![0u32; n * 20];
    for (seq, _) in train {
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
    let pred_paths = KittiPaths::new(pred_root);
    let raw = map.inverse_remap(&prior);
    for (seq, _) in val {
        for frame in sk::list_stems(&data.join("sequences").join(seq).join("voxels"), "label")? {
            let p = pred_paths.prediction(seq, &frame);
            if let Some(dir) = p.parent() {
                std::fs::create_dir_all(dir)
                    .with_context(|| format!("creating {}", dir.display()))?;
            }
            sk::write_label_raw(&p, &raw)?;
        }
    }
    let names: Vec<String> = val.iter().map(|s| s.0.clone()).collect();
    Ok(score_semantic_kitti_folder(
        data,
        pred_root,
        &FolderOptions {
            sequences: Some(&names),
            ..Default::default()
        },
    )?)
}

/// `non_ground_recall_by_visibility` of summary.json: the recall of each part (null when empty) and
/// the share of the valid non-ground voxels in it.
fn visibility_json(v: &VisibilityRecall) -> serde_json::Value {
    let total = v.total().voxels.max(1) as f64;
    let part = |c: occ_eval::RecallCount| {
        serde_json::json!({
            "recall": nan_null(c.recall()),
            "share_of_voxels": c.voxels as f64 / total,
        })
    };
    serde_json::json!({
        "out_of_view": part(v.out_of_view),
        "in_view_seen": part(v.in_view_seen),
        "in_view_unseen": part(v.in_view_unseen),
    })
}

/// A metric for JSON: `null` when it is undefined (NaN), as the evaluation reports write them.
fn nan_null(v: f64) -> serde_json::Value {
    if v.is_finite() {
        serde_json::json!(v)
    } else {
        serde_json::Value::Null
    }
}

pub fn run(args: &DemoArgs) -> Result<()> {
    let t0 = Instant::now();
    let data = args.out.join("data");
    let train = synthetic::parse_sequences(&args.train)?;
    let val = synthetic::parse_sequences(&args.val)?;
    if let Some((name, _)) = val.iter().find(|v| train.iter().any(|t| t.0 == v.0)) {
        anyhow::bail!(
            "sequence {name} is in both --train ({}) and --val ({}): the held-out street must not be trained on",
            args.train,
            args.val
        );
    }
    let mut cfg = match &args.config {
        Some(p) => RunConfig::load(p)?,
        None => RunConfig::from_toml(SYNTHETIC_TINY, "built-in configs/synthetic_tiny.toml")?,
    };
    if let Some(m) = args.model {
        cfg.model.kind = m.into();
    }
    if let Some(s) = args.steps {
        cfg.train.steps = s;
    }
    cfg.train.seed = args.seed;
    cfg.data.train_sequences = train.iter().map(|s| s.0.clone()).collect();
    cfg.data.val_sequences = val.iter().map(|s| s.0.clone()).collect();
    cfg.validate().map_err(anyhow::Error::msg)?;
    let mut seqs = train.clone();
    seqs.extend(val.iter().cloned());

    eprintln!("[1/5] generating synthetic scenes into {}", data.display());
    let synth = SynthConfig::new(Preset::KittiSmall, args.seed, seqs);
    let pb = progress::bar(1, "synth");
    let summary = synthetic::generate(&data, &synth, &mut progress::callback(&pb))?;
    pb.finish_and_clear();
    let grid = Preset::KittiSmall.grid();

    eprintln!("[2/5] per-voxel prior baseline (most frequent training label of each voxel)");
    let prior = prior_baseline(
        &data,
        &train,
        &val,
        &args.out.join("prior_predictions"),
        grid.num_voxels(),
    )?;
    eprintln!(
        "      prior on the held-out sequence: IoU {:.3}, mIoU {:.3}",
        prior.iou, prior.miou
    );

    eprintln!(
        "[3/5] training {} ({} steps)",
        cfg.model.kind.name(),
        cfg.train.steps
    );
    let run_dir = args.out.join("run");
    let outcome = run_with(&cfg, &data, &run_dir, false, false)?;
    let train_seconds = outcome.summary.train_seconds;

    eprintln!("[4/5] predicting and scoring the held-out sequence");
    let pred_root = args.out.join("predictions");
    let v = validate_with_bars(&outcome.model, &cfg, &data, &pred_root)?;
    let (report, spf) = (v.report, v.seconds_per_frame);
    crate::curves::write_curves(&run_dir, Some((report.iou, report.miou)))?;

    eprintln!("[5/5] rendering");
    let paths = KittiPaths::new(&data);
    let pred_paths = KittiPaths::new(&pred_root);
    let mut renders = Vec::new();
    for (seq, _) in &val {
        let frames = sk::list_stems(&data.join("sequences").join(seq).join("voxels"), "label")?;
        for frame in frames.iter().take(2) {
            let gt = read_label_grid(&paths.voxels(seq, frame, "label"))?;
            let pred = read_label_grid(&pred_paths.prediction(seq, frame))?;
            let out = args.out.join("renders").join(format!("{seq}_{frame}.png"));
            render_panels(
                &gt,
                Some(&pred),
                Some((&paths.image_2(seq, frame), &paths.calib(seq))),
                &out,
                360,
            )?;
            eprintln!("      wrote {}", out.display());
            renders.push(out);
        }
    }
    let val_names: Vec<String> = val.iter().map(|s| s.0.clone()).collect();
    let by_view = |root: &Path| {
        semantic_kitti_recall_by_visibility(
            &data,
            root,
            &val_names,
            &grid,
            synth.image_size(),
            &SEMANTIC_KITTI_GROUND_CLASSES,
        )
    };
    let vis_model = by_view(&pred_root)?;
    let vis_prior = by_view(&args.out.join("prior_predictions"))?;
    let summary_json = serde_json::json!({
        "model": cfg.model.kind.name(),
        "iou": report.iou,
        "miou": report.miou,
        "precision": report.precision,
        "recall": report.recall,
        "per_class": report.per_class,
        "non_ground_recall": nan_null(report.non_ground_recall(&SEMANTIC_KITTI_GROUND_CLASSES)),
        "non_ground_recall_by_visibility": visibility_json(&vis_model),
        "frames": report.frames,
        "train_seconds": train_seconds,
        "train_steps": outcome.summary.steps,
        "first_loss": outcome.summary.first_loss,
        "last_loss": outcome.summary.last_loss,
        "seconds_per_val_frame": spf,
        "val_sequences": val_names,
        "prior": {
            "description": "most frequent training label of each voxel",
            "iou": prior.iou,
            "miou": prior.miou,
            "per_class": prior.per_class,
            "non_ground_recall": nan_null(prior.non_ground_recall(&SEMANTIC_KITTI_GROUND_CLASSES)),
            "non_ground_recall_by_visibility": visibility_json(&vis_prior),
        },
        "synth_frames": summary.frames,
        "renders": renders,
        "device": crate::backend::describe(),
        "total_seconds": t0.elapsed().as_secs_f64(),
    });
    crate::util::write_json(&args.out.join("summary.json"), &summary_json)?;
    eprintln!(
        "{}: IoU {:.3}, mIoU {:.3}, non-ground recall {:.3} | per-voxel prior: IoU {:.3}, mIoU {:.3}, non-ground recall {:.3}",
        cfg.model.kind.name(),
        report.iou,
        report.miou,
        report.non_ground_recall(&SEMANTIC_KITTI_GROUND_CLASSES),
        prior.iou,
        prior.miou,
        prior.non_ground_recall(&SEMANTIC_KITTI_GROUND_CLASSES),
    );
    let r = |c: occ_eval::RecallCount| c.recall();
    eprintln!(
        "      non-ground recall by visibility (share of the voxels): in view and seen {:.3} ({:.2}), in view unseen {:.3} ({:.2}), out of view {:.3} ({:.2})",
        r(vis_model.in_view_seen),
        vis_model.in_view_seen.voxels as f64 / vis_model.total().voxels.max(1) as f64,
        r(vis_model.in_view_unseen),
        vis_model.in_view_unseen.voxels as f64 / vis_model.total().voxels.max(1) as f64,
        r(vis_model.out_of_view),
        vis_model.out_of_view.voxels as f64 / vis_model.total().voxels.max(1) as f64,
    );
    eprintln!(
        "done in {:.1} s; summary in {}",
        t0.elapsed().as_secs_f64(),
        args.out.join("summary.json").display()
    );
    Ok(())
}
