//! `sparseocc infer`: a trained model (or random weights) on a dataset's sequences (SemanticKITTI:
//! the submission layout `sequences/XX/predictions/*.label`; Occ3D: `<scene>/<token>/labels.npz`;
//! nuScenes-Occupancy: `scene_<token>/occupancy/<lidar token>.npy`), or on any single camera image
//! with its calibration.
//!
//! - `--checkpoint RUN` (a training run folder, or its `checkpoint/`): config from `RUN/config.toml`.
//! - `--config C --random-weights`: an untrained network (timing, smoke tests on real frames).

use crate::backend::{self, Infer};
use crate::labels_io::{read_kitti_label, read_surround_labels, LabelGrid};
use crate::panels::render_panel_set;
use crate::progress;
use anyhow::{bail, Context, Result};
use occ_data::formats::semantic_kitti::{self as sk, KittiPaths};
use occ_data::labels::LearningMap;
use occ_eval::format_table;
use occ_geometry::VoxelGrid;
use occ_model::OccNet;
use occ_train::dataset::{Dataset, DatasetFormat};
use occ_train::infer::{load_single_image, predict_dataset, predict_sample};
use occ_train::RunConfig;
use occ_viz::Palette;
use std::path::{Path, PathBuf};

/// Arguments of `sparseocc infer`.
#[derive(clap::Args, Debug)]
pub struct InferArgs {
    /// Training run folder (with config.toml and checkpoint/) or its checkpoint/ folder.
    #[arg(long)]
    pub checkpoint: Option<PathBuf>,
    /// Run configuration, for --random-weights.
    #[arg(long)]
    pub config: Option<PathBuf>,
    /// Use an untrained network built from --config (timing and smoke tests).
    #[arg(long)]
    pub random_weights: bool,
    /// Dataset root (SemanticKITTI: the folder with sequences/; nuScenes layouts: the folder with
    /// samples/ and the v1.0-* tables), with --sequences.
    #[arg(long)]
    pub data: Option<PathBuf>,
    /// Sequences (nuScenes layouts: scene names) to predict (comma-separated); default the
    /// config's val_sequences.
    #[arg(long, value_delimiter = ',')]
    pub sequences: Option<Vec<String>>,
    /// A single camera image (PNG or JPEG), with --calib.
    #[arg(long)]
    pub image: Option<PathBuf>,
    /// KITTI-format calibration (P2 and Tr lines) of --image.
    #[arg(long)]
    pub calib: Option<PathBuf>,
    /// Output folder: the predictions in the dataset's layout (or NAME.label for --image), renders/,
    /// summary.json.
    #[arg(long)]
    pub out: PathBuf,
    /// Render this many frames (camera overlay | prediction | ground truth when labelled).
    #[arg(long, default_value_t = 2)]
    pub render: usize,
    /// Test-time mirror augmentation: average each frame's class probabilities with those of its
    /// mirror image (twice the forward time). `--test-mirror` or `--test-mirror true` turns it on,
    /// `--test-mirror false` off; default: the run config's `data.test_mirror`.
    #[arg(long, num_args = 0..=1, default_missing_value = "true")]
    pub test_mirror: Option<bool>,
}

/// Loads a model and its configuration from a run folder (or its checkpoint/ folder).
pub fn load_checkpoint(path: &Path) -> Result<(RunConfig, VoxelGrid, OccNet<Infer>)> {
    Ok(occ_train::trainer::load_run::<Infer>(
        path,
        &backend::device(),
    )?)
}

fn grid_for(format: DatasetFormat, dims: [usize; 3]) -> Result<VoxelGrid> {
    if format != DatasetFormat::SemanticKitti {
        let g = format.default_grid();
        if g.dims == dims {
            return Ok(g);
        }
        bail!(
            "model.full_dims {dims:?} is not the {} grid {:?}; use a trained run (it stores its grid)",
            format.name(),
            g.dims
        );
    }
    for f in [1, 2, 4] {
        let g = VoxelGrid::semantic_kitti().downsampled(f);
        if g.dims == dims {
            return Ok(g);
        }
    }
    let small = occ_data::synthetic::Preset::KittiSmall.grid();
    if small.dims == dims {
        return Ok(small);
    }
    bail!("model.full_dims {dims:?} is not a SemanticKITTI grid; use a trained run (it stores its grid)")
}

pub fn run(args: &InferArgs) -> Result<()> {
    let (cfg, grid, model) = match (&args.checkpoint, &args.config, args.random_weights) {
        (Some(ck), None, false) => load_checkpoint(ck)?,
        (None, Some(c), true) => {
            let cfg = RunConfig::load(c)?;
            let grid = grid_for(cfg.data.format, cfg.model.full_dims)?;
            let device = backend::device();
            // The same random network in every run (the config's `train.seed`), as in `bench`.
            <Infer as burn::tensor::backend::Backend>::seed(&device, cfg.train.seed);
            let model: OccNet<Infer> = cfg.model.init(&device)?;
            (cfg, grid, model)
        }
        _ => bail!("give either --checkpoint RUN, or --config C --random-weights"),
    };
    std::fs::create_dir_all(&args.out)
        .with_context(|| format!("creating {}", args.out.display()))?;
    let device = backend::device();
    let map = LearningMap::semantic_kitti();
    let test_mirror = args.test_mirror.unwrap_or(cfg.data.test_mirror);
    let mut summary = serde_json::json!({
        "model": cfg.model.kind.name(),
        "device": backend::describe(),
        "weights": if args.random_weights { "random" } else { "checkpoint" },
        "test_mirror": test_mirror,
    });
    match (&args.data, &args.image) {
        (Some(data), None) => {
            let seqs = args
                .sequences
                .clone()
                .unwrap_or_else(|| cfg.data.val_sequences.clone());
            if seqs.is_empty() {
                bail!("--sequences is required (the config has no val_sequences)");
            }
            let mut ds = Dataset::open(data, &cfg.data, &seqs, &[])?;
            ds.set_load_points(cfg.model.needs_points_at_test());
            let pb = progress::bar(ds.len() as u64, "check data");
            ds.check_all(&mut progress::callback(&pb))?;
            pb.finish_and_clear();
            if ds.grid().dims != grid.dims {
                bail!(
                    "{}: dataset grid {:?} but the model predicts {:?}",
                    data.display(),
                    ds.grid().dims,
                    grid.dims
                );
            }
            let pb = progress::bar(ds.len() as u64, "infer");
            let mut times = Vec::new();
            let written = predict_dataset(
                &model,
                &ds,
                &args.out,
                &device,
                test_mirror,
                &mut |d, t, f, p| {
                    pb.set_length(t as u64);
                    pb.set_position(d as u64);
                    times.push(p.seconds);
                    if std::env::var_os("CI").is_some() || !console_is_tty() {
                        eprintln!(
                            "  {}/{}: {:.3} s, voxels {:?}",
                            f.sequence, f.frame, p.seconds, p.stats
                        );
                    }
                },
            )?;
            pb.finish_and_clear();
            for (i, (path, _)) in written.iter().enumerate().take(args.render) {
                let out = render_frame(&ds, data, i, path, grid, &args.out)?;
                eprintln!("wrote {}", out.display());
            }
            if ds.is_labelled()? {
                let r = ds.score(&args.out)?;
                println!("{}", format_table(&r));
                summary["iou"] = serde_json::json!(r.iou);
                summary["miou"] = serde_json::json!(r.miou);
                summary["per_class"] = serde_json::json!(r.per_class);
            }
            summary["dataset_format"] = serde_json::json!(ds.format().name());
            let mean = times.iter().sum::<f64>() / times.len().max(1) as f64;
            eprintln!(
                "{} frames, {:.3} s per frame (forward pass, image decoding excluded), {}",
                times.len(),
                mean,
                backend::describe()
            );
            summary["frames"] = serde_json::json!(times.len());
            summary["seconds_per_frame"] = serde_json::json!(mean);
            summary["seconds"] = serde_json::json!(times);
        }
        (None, Some(image)) => {
            let Some(calib) = &args.calib else {
                bail!("--image needs --calib (KITTI calib.txt with P2 and Tr)");
            };
            let sample = load_single_image(image, calib, &cfg.data.pipeline())?;
            let pred = predict_sample(&model, &sample, grid, &device, test_mirror)?;
            let name = sample.frame.frame.clone();
            let label_p = args.out.join(format!("{name}.label"));
            sk::write_label_raw(&label_p, &map.inverse_remap(&pred.classes))?;
            let pred_grid = LabelGrid {
                classes: pred.classes.clone(),
                grid,
                palette: Palette::SemanticKitti,
                occupancy_only: false,
                title: "prediction",
            };
            let out = args.out.join(format!("{name}.png"));
            render_panel_set(None, Some(&pred_grid), Some((image, calib)), &out, 360)?;
            eprintln!(
                "wrote {} and {} ({:.3} s forward, {})",
                label_p.display(),
                out.display(),
                pred.seconds,
                backend::describe()
            );
            summary["frames"] = serde_json::json!(1);
            summary["seconds_per_frame"] = serde_json::json!(pred.seconds);
            summary["stats"] = serde_json::json!(pred.stats);
        }
        _ => bail!("give either --data DIR --sequences S, or --image IMG --calib CALIB"),
    }
    crate::util::write_json(&args.out.join("summary.json"), &summary)?;
    Ok(())
}

/// Renders frame `i` (prediction at `pred_path` | ground truth when labelled; with the camera
/// overlay for SemanticKITTI) to `OUT/renders/<sequence>_<frame>.png`.
fn render_frame(
    ds: &Dataset,
    data: &Path,
    i: usize,
    pred_path: &Path,
    grid: VoxelGrid,
    out_root: &Path,
) -> Result<PathBuf> {
    let f = &ds.frames()[i];
    let out = out_root
        .join("renders")
        .join(format!("{}_{}.png", f.sequence, f.frame));
    match ds {
        Dataset::Kitti(_) => {
            let paths = KittiPaths::new(data);
            let pred = read_kitti_label(pred_path, grid)?;
            let gt_p = paths.voxels(&f.sequence, &f.frame, "label");
            let gt = gt_p
                .exists()
                .then(|| read_kitti_label(&gt_p, grid))
                .transpose()?;
            render_panel_set(
                gt.as_ref(),
                Some(&pred),
                Some((
                    &paths.image_2(&f.sequence, &f.frame),
                    &paths.calib(&f.sequence),
                )),
                &out,
                360,
            )?;
        }
        Dataset::Surround(s) => {
            let format: DatasetFormat = ds.format();
            let pred = read_surround_labels(pred_path, format, grid)?;
            let gt_p = s.gt_path(i)?;
            let gt = gt_p
                .exists()
                .then(|| read_surround_labels(&gt_p, format, grid))
                .transpose()?;
            render_panel_set(gt.as_ref(), Some(&pred), None, &out, 360)?;
        }
    }
    Ok(out)
}

fn console_is_tty() -> bool {
    use std::io::IsTerminal;
    std::io::stderr().is_terminal()
}
