//! Scoring whole folders of predictions against ground truth in the datasets' own layouts,
//! frames in parallel (rayon; each worker holds one frame at a time, so memory stays bounded).
//!
//! # SemanticKITTI (`sparseocc eval --dataset semantickitti`)
//! Like semantic-kitti-api `evaluate_completion.py`:
//! - ground truth `GT/sequences/XX/voxels/NNNNNN.label` (uint16 raw ids) + `NNNNNN.invalid`
//!   (bit-packed); the frames are **every** `voxels/*.label` of the chosen sequences (the input-only
//!   `*.bin` frames without a `.label` are not scored);
//! - predictions `PRED/sequences/XX/predictions/NNNNNN.label` (uint16 raw ids, the submission
//!   format, 256×256×32);
//! - both are remapped with the learning-map lut ([`LearningMap::semantic_kitti`]); prediction ids
//!   that remap to 255 (unknown ids, outlier, other-structure, other-object) are invalid predictions
//!   (see [`crate::protocol`]); ground-truth ids the map does not list are ignored, but a frame with
//!   more than half of its voxels unlisted is an error (not SemanticKITTI labels);
//! - every prediction must exist: all are checked before scoring, and the error names the first
//!   missing file and the count.
//!
//! Sequences: `FolderOptions::sequences`, written `8` or `08` (numbers are zero-padded to two
//! digits as the official script does); by default every sequence under `GT/sequences` is used.
//!
//! # Occ3D (`sparseocc eval --dataset occ3d`)
//! - ground truth `GT/gts/<scene>/<token>/labels.npz` (`GT` may also be the `gts` folder itself, or
//!   any folder holding `<...>/<token>/labels.npz` up to 4 levels deep, like the public sample);
//! - prediction of a frame with relative folder `<scene>/<token>`: `PRED/<scene>/<token>/labels.npz`
//!   (the ground-truth layout) or, if that does not exist, the flat `PRED/<token>.npz`; in both the
//!   key `semantics` holds the `[200,200,16]` class grid (any integer dtype, or integer-valued
//!   floats; values outside 0..=17 are invalid predictions); other keys are ignored;
//! - voxels evaluated: `mask_camera != 0` by default (the challenge setting), or
//!   `mask_lidar` / all voxels via [`Occ3dMask`].
//!
//! # nuScenes-Occupancy / OpenOccupancy (`sparseocc eval --dataset nuscenes-occupancy`)
//! - ground truth `GT/scene_<scene_token>/occupancy/<lidar_token>.npy` (`GT` may also be the
//!   parent of a `nuScenes-Occupancy/` folder holding those): the sparse `N x 4` `[z, y, x, cls]`
//!   (or `N x 7` `[z, y, x, vx, vy, vz, cls]`) array of the occupied voxels of the 512×512×40 grid,
//!   read into the dense training grid ([`read_sparse_occupancy`]: unlisted voxels 0 = empty, raw
//!   1..16 unchanged, raw 0 noise -> 255); the frames are **every** such `.npy`;
//! - prediction of a frame: `PRED/scene_<scene_token>/occupancy/<lidar_token>.npy` in the same
//!   sparse format (e.g. written by `write_sparse_occupancy`); every prediction must exist;
//! - every voxel is evaluated except ground-truth noise (255, ignored as in OpenOccupancy);
//!   predicted noise (raw 0 -> 255) is an invalid prediction, scored as empty (see
//!   [`crate::protocol`]).

use crate::error::EvalError;
use crate::protocol::{EvalMask, Evaluator, Protocol};
use crate::report::EvalReport;
use occ_data::formats::npy::{parse_npy, NpyValues};
use occ_data::formats::nuscenes_occupancy::read_sparse_occupancy;
use occ_data::formats::occ3d::read_labels_npz;
use occ_data::formats::semantic_kitti::{
    list_sequences, list_stems, read_label_raw, read_packed_bits, KittiPaths, LearningMap,
    NUM_VOXELS,
};
use occ_labels::IGNORE;
use rayon::prelude::*;
use std::io::Read;
use std::path::{Path, PathBuf};

/// The Occ3D-nuScenes label grid.
const OCC3D_DIMS: [usize; 3] = [200, 200, 16];

/// Which Occ3D mask selects the evaluated voxels.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub enum Occ3dMask {
    /// `mask_camera` (the Occ3D challenge metric).
    #[default]
    Camera,
    /// `mask_lidar`.
    Lidar,
    /// Every voxel.
    None,
}

/// Options of the folder scoring.
#[derive(Clone, Copy, Default)]
pub struct FolderOptions<'a> {
    /// Sequences to score: SemanticKITTI sequence ids, or Occ3D scene names (the `<scene>` folders
    /// of the ground truth); `None` = every one. Each may be listed once.
    pub sequences: Option<&'a [String]>,
    /// Occ3D mask.
    pub occ3d_mask: Occ3dMask,
    /// Called once per scored frame (from worker threads), e.g. to advance a progress bar.
    pub on_frame: Option<&'a (dyn Fn() + Sync)>,
}

/// Zero-pad numeric sequence ids to two digits (`8` -> `08`), as `evaluate_completion.py` does.
fn normalise_sequence(s: &str) -> String {
    match s.trim().parse::<u32>() {
        Ok(n) => format!("{n:02}"),
        Err(_) => s.trim().to_string(),
    }
}

/// The sequences of `list` after `normalise`, each once: one listed twice (`8` and `08`) is an
/// error, not scored twice.
fn unique_sequences(
    list: &[String],
    normalise: impl Fn(&str) -> String,
) -> Result<Vec<String>, EvalError> {
    let mut out: Vec<String> = Vec::new();
    for (i, s) in list.iter().enumerate() {
        let n = normalise(s);
        if n.is_empty() {
            return Err(EvalError::InvalidOptions(format!(
                "--sequences: entry {} is empty",
                i + 1
            )));
        }
        if let Some(j) = out.iter().position(|o| *o == n) {
            return Err(EvalError::InvalidOptions(format!(
                "--sequences: sequence {n} is listed twice (`{}` and `{s}`)",
                list[j]
            )));
        }
        out.push(n);
    }
    Ok(out)
}

/// A ground-truth entry `dir/*.ext` that is not a regular file (a folder, a broken link) is an
/// error naming it, rather than a frame silently left out of the score.
fn refuse_non_files(dir: &Path, ext: &str) -> Result<(), EvalError> {
    let rd = match std::fs::read_dir(dir) {
        Ok(rd) => rd,
        Err(e) if e.kind() == std::io::ErrorKind::NotFound => return Ok(()),
        Err(source) => {
            return Err(EvalError::Io {
                path: dir.to_path_buf(),
                source,
            })
        }
    };
    for entry in rd.flatten() {
        let p = entry.path();
        if p.extension().and_then(|e| e.to_str()) == Some(ext) && !p.is_file() {
            return Err(EvalError::BadGroundTruth {
                path: p,
                detail: "not a file (a ground-truth frame must be a regular file)".into(),
            });
        }
    }
    Ok(())
}

/// One frame to score: ground truth and prediction paths.
struct Job {
    name: String,
    gt: PathBuf,
    extra: Option<PathBuf>,
    pred: PathBuf,
}

fn check_predictions(jobs: &[Job]) -> Result<(), EvalError> {
    let missing: Vec<&Job> = jobs.iter().filter(|j| !j.pred.is_file()).collect();
    match missing.first() {
        None => Ok(()),
        Some(first) => Err(EvalError::MissingPrediction {
            path: first.pred.clone(),
            gt: first.gt.clone(),
            count: missing.len(),
        }),
    }
}

fn run_jobs(
    protocol: Protocol,
    jobs: &[Job],
    opts: &FolderOptions<'_>,
    score: impl Fn(&Job, &mut Evaluator) -> Result<(), EvalError> + Sync,
) -> Result<EvalReport, EvalError> {
    let ev = jobs
        .par_iter()
        .try_fold(
            || Evaluator::new(protocol),
            |mut acc, job| {
                score(job, &mut acc)?;
                if let Some(cb) = opts.on_frame {
                    cb();
                }
                Ok::<_, EvalError>(acc)
            },
        )
        .try_reduce(
            || Evaluator::new(protocol),
            |mut a, b| {
                a.merge(&b)?;
                Ok(a)
            },
        )?;
    Ok(ev.report())
}

/// Score a prediction folder against a ground-truth folder with `protocol`'s layout and rules (what
/// `sparseocc eval` and the Python package's `evaluate` run).
pub fn score_folder(
    protocol: Protocol,
    gt_root: &Path,
    pred_root: &Path,
    opts: &FolderOptions<'_>,
) -> Result<EvalReport, EvalError> {
    match protocol {
        Protocol::SemanticKitti => score_semantic_kitti_folder(gt_root, pred_root, opts),
        Protocol::Occ3d => score_occ3d_folder(gt_root, pred_root, opts),
        Protocol::NuScenesOccupancy => score_nuscenes_occupancy_folder(gt_root, pred_root, opts),
    }
}

/// Score SemanticKITTI submission folders (see the module docs for layout and rules).
pub fn score_semantic_kitti_folder(
    gt_root: &Path,
    pred_root: &Path,
    opts: &FolderOptions<'_>,
) -> Result<EvalReport, EvalError> {
    let gt_paths = KittiPaths::new(gt_root);
    let pred_paths = KittiPaths::new(pred_root);
    let sequences: Vec<String> = match opts.sequences {
        Some(s) => unique_sequences(s, normalise_sequence)?,
        None => list_sequences(gt_root)?,
    };
    let mut jobs = Vec::new();
    for seq in &sequences {
        let seq_dir = gt_paths.sequence_dir(seq);
        if !seq_dir.is_dir() {
            return Err(EvalError::NoFrames {
                root: seq_dir,
                what: format!("sequence {seq} does not exist"),
            });
        }
        refuse_non_files(&seq_dir.join("voxels"), "label")?;
        for frame in list_stems(&seq_dir.join("voxels"), "label")? {
            jobs.push(Job {
                name: format!("{seq}/{frame}"),
                gt: gt_paths.voxels(seq, &frame, "label"),
                extra: Some(gt_paths.voxels(seq, &frame, "invalid")),
                pred: pred_paths.prediction(seq, &frame),
            });
        }
    }
    if jobs.is_empty() {
        return Err(EvalError::NoFrames {
            root: gt_root.to_path_buf(),
            what: format!(
                "no sequences/XX/voxels/*.label in sequence(s) [{}]",
                sequences.join(", ")
            ),
        });
    }
    check_predictions(&jobs)?;
    // A synthetic dataset may use a coarser grid over the same volume (its synthetic.json says so).
    let n_voxels = occ_data::synthetic::read_synthetic_meta(gt_root)?
        .map(|m| m.grid.num_voxels())
        .unwrap_or(NUM_VOXELS);
    let map = LearningMap::semantic_kitti();
    run_jobs(Protocol::SemanticKitti, &jobs, opts, |job, ev| {
        let raw = read_label_raw(&job.gt, n_voxels)?;
        // Unlisted ids are ignored, as by the official script; a frame made mostly of them is not
        // SemanticKITTI ground truth (it would score 0 without a word).
        let unlisted = raw.iter().filter(|&&r| !map.is_listed(r)).count();
        if unlisted * 2 > raw.len() {
            let first = raw
                .iter()
                .find(|&&r| !map.is_listed(r))
                .copied()
                .unwrap_or_default();
            return Err(EvalError::BadGroundTruth {
                path: job.gt.clone(),
                detail: format!(
                    "{unlisted} of {} voxels have ids the SemanticKITTI learning map does not list \
                     (e.g. {first}); not SemanticKITTI voxel labels",
                    raw.len()
                ),
            });
        }
        let gt = map.remap(&raw);
        let invalid_path = job.extra.as_deref().unwrap_or(&job.gt);
        let invalid = read_packed_bits(invalid_path, n_voxels)?;
        let pred = map.remap(&read_label_raw(&job.pred, n_voxels)?);
        ev.add_frame(&pred, &gt, EvalMask::Invalid(&invalid), &job.name)
    })
}

/// All `labels.npz` below `base` (at most `depth` folders deep), as folders relative to `base`.
fn find_npz(
    base: &Path,
    rel: &Path,
    depth: usize,
    out: &mut Vec<PathBuf>,
) -> Result<(), EvalError> {
    let dir = base.join(rel);
    let rd = std::fs::read_dir(&dir).map_err(|source| EvalError::Io {
        path: dir.clone(),
        source,
    })?;
    for entry in rd {
        let entry = entry.map_err(|source| EvalError::Io {
            path: dir.clone(),
            source,
        })?;
        let path = entry.path();
        let name = entry.file_name();
        if path.is_dir() && depth > 0 {
            find_npz(base, &rel.join(&name), depth - 1, out)?;
        } else if name == "labels.npz" && path.is_file() && !rel.as_os_str().is_empty() {
            out.push(rel.to_path_buf());
        }
    }
    Ok(())
}

/// Read the `semantics` array of an Occ3D prediction `.npz` as class bytes (values outside
/// 0..=254 become 255, i.e. invalid); `dims` must match.
pub fn read_occ3d_prediction(path: &Path, dims: [usize; 3]) -> Result<Vec<u8>, EvalError> {
    let bad = |detail: String| EvalError::BadPrediction {
        path: path.to_path_buf(),
        detail,
    };
    let bytes = std::fs::read(path).map_err(|source| EvalError::Io {
        path: path.to_path_buf(),
        source,
    })?;
    let mut archive = zip::ZipArchive::new(std::io::Cursor::new(&bytes[..]))
        .map_err(|e| bad(format!("not a valid .npz (zip): {e}")))?;
    let mut entry = archive
        .by_name("semantics.npy")
        .map_err(|e| bad(format!("no `semantics` array: {e}")))?;
    let n: usize = dims.iter().product();
    // A uint8 grid plus a generous header; larger entries (e.g. int64) are allowed up to 8 bytes per voxel.
    let limit = (n as u64) * 8 + (1 << 16);
    let mut npy = Vec::new();
    (&mut entry)
        .take(limit + 1)
        .read_to_end(&mut npy)
        .map_err(|e| bad(format!("cannot decompress `semantics`: {e}")))?;
    if npy.len() as u64 > limit {
        return Err(bad(format!("`semantics` is larger than {limit} bytes")));
    }
    let arr = parse_npy(&npy, &path.join("semantics.npy"))?;
    if arr.shape != dims {
        return Err(bad(format!(
            "`semantics` has shape {:?}, the ground truth {dims:?}",
            arr.shape
        )));
    }
    let to_class = |v: f64| -> Result<u8, EvalError> {
        if v.fract() != 0.0 || v.is_nan() {
            return Err(bad(format!("`semantics` value {v} is not an integer")));
        }
        Ok(if (0.0..=254.0).contains(&v) {
            v as u8
        } else {
            IGNORE
        })
    };
    match arr.values {
        NpyValues::U8(v) => Ok(v),
        NpyValues::Bool(_) => Err(bad("`semantics` is boolean, expected class ids".into())),
        other => other.to_f64().into_iter().map(to_class).collect(),
    }
}

/// Score Occ3D prediction folders (see the module docs for layout and rules).
pub fn score_occ3d_folder(
    gt_root: &Path,
    pred_root: &Path,
    opts: &FolderOptions<'_>,
) -> Result<EvalReport, EvalError> {
    let base = if gt_root.join("gts").is_dir() {
        gt_root.join("gts")
    } else {
        gt_root.to_path_buf()
    };
    let mut rels = Vec::new();
    find_npz(&base, Path::new(""), 4, &mut rels)?;
    rels.sort();
    if rels.is_empty() {
        return Err(EvalError::NoFrames {
            root: base,
            what: "no <scene>/<token>/labels.npz".into(),
        });
    }
    // `sequences` are scene names: a frame `<...>/<scene>/<token>` is kept when its scene folder is
    // listed; every listed scene must have frames.
    if let Some(list) = opts.sequences {
        let scenes = unique_sequences(list, |s| s.trim().to_string())?;
        let scene_of = |rel: &Path| {
            rel.parent()
                .and_then(|p| p.file_name())
                .map(|n| n.to_string_lossy().into_owned())
        };
        for s in &scenes {
            if !rels
                .iter()
                .any(|r| scene_of(r).as_deref() == Some(s.as_str()))
            {
                return Err(EvalError::NoFrames {
                    root: base,
                    what: format!("scene {s} has no <scene>/<token>/labels.npz"),
                });
            }
        }
        rels.retain(|r| scene_of(r).is_some_and(|n| scenes.contains(&n)));
    }
    // The grid every ground truth must have: a synthetic dataset's own, else Occ3D's 200x200x16.
    let meta = match occ_data::synthetic::read_synthetic_meta(gt_root)? {
        Some(m) => Some(m),
        None => match gt_root.parent() {
            Some(p) if base == gt_root && !p.as_os_str().is_empty() => {
                occ_data::synthetic::read_synthetic_meta(p).unwrap_or(None)
            }
            _ => None,
        },
    };
    let expected_dims = meta.map(|m| m.grid.dims).unwrap_or(OCC3D_DIMS);
    let jobs: Vec<Job> = rels
        .iter()
        .map(|rel| {
            let nested = pred_root.join(rel).join("labels.npz");
            let flat = rel
                .file_name()
                .map(|t| pred_root.join(format!("{}.npz", t.to_string_lossy())));
            let pred = match flat {
                Some(f) if !nested.is_file() && f.is_file() => f,
                _ => nested,
            };
            Job {
                name: rel.display().to_string(),
                gt: base.join(rel).join("labels.npz"),
                extra: None,
                pred,
            }
        })
        .collect();
    check_predictions(&jobs)?;
    run_jobs(Protocol::Occ3d, &jobs, opts, |job, ev| {
        let gt = read_labels_npz(&job.gt)?;
        if gt.dims != expected_dims {
            return Err(EvalError::BadGroundTruth {
                path: job.gt.clone(),
                detail: format!(
                    "grid {:?}, but the dataset's ground truth is {expected_dims:?}",
                    gt.dims
                ),
            });
        }
        let pred = read_occ3d_prediction(&job.pred, gt.dims)?;
        let mask = match opts.occ3d_mask {
            Occ3dMask::Camera => EvalMask::Visible(&gt.mask_camera),
            Occ3dMask::Lidar => EvalMask::Visible(&gt.mask_lidar),
            Occ3dMask::None => EvalMask::All,
        };
        ev.add_frame(&pred, &gt.semantics, mask, &job.name)
    })
}

/// The sorted sub-folders of `dir` whose names start with `prefix`.
fn list_dirs_with_prefix(dir: &Path, prefix: &str) -> Result<Vec<String>, EvalError> {
    let rd = std::fs::read_dir(dir).map_err(|source| EvalError::Io {
        path: dir.to_path_buf(),
        source,
    })?;
    let mut out = Vec::new();
    for entry in rd {
        let entry = entry.map_err(|source| EvalError::Io {
            path: dir.to_path_buf(),
            source,
        })?;
        if let Some(name) = entry.file_name().to_str() {
            if name.starts_with(prefix) && entry.path().is_dir() {
                out.push(name.to_string());
            }
        }
    }
    out.sort();
    Ok(out)
}

/// Score nuScenes-Occupancy (OpenOccupancy) prediction folders (see the module docs for layout
/// and rules).
pub fn score_nuscenes_occupancy_folder(
    gt_root: &Path,
    pred_root: &Path,
    opts: &FolderOptions<'_>,
) -> Result<EvalReport, EvalError> {
    let nested = gt_root.join("nuScenes-Occupancy");
    let base = if nested.is_dir() {
        nested
    } else {
        gt_root.to_path_buf()
    };
    let mut scenes = list_dirs_with_prefix(&base, "scene_")?;
    // `sequences` are scene tokens (`<token>` or the folder name `scene_<token>`); every listed
    // scene must have a folder.
    if let Some(list) = opts.sequences {
        let wanted = unique_sequences(list, |s| {
            let s = s.trim();
            if s.starts_with("scene_") {
                s.to_string()
            } else {
                format!("scene_{s}")
            }
        })?;
        if let Some(missing) = wanted.iter().find(|w| !scenes.contains(w)) {
            return Err(EvalError::NoFrames {
                root: base,
                what: format!("scene {missing} has no {missing}/occupancy/ folder"),
            });
        }
        scenes.retain(|s| wanted.contains(s));
    }
    let mut jobs = Vec::new();
    for scene in scenes {
        let occ_dir = base.join(&scene).join("occupancy");
        for token in list_stems(&occ_dir, "npy")? {
            let file = format!("{token}.npy");
            jobs.push(Job {
                name: format!("{scene}/{token}"),
                gt: occ_dir.join(&file),
                extra: None,
                pred: pred_root.join(&scene).join("occupancy").join(&file),
            });
        }
    }
    if jobs.is_empty() {
        return Err(EvalError::NoFrames {
            root: base,
            what: "no scene_<scene_token>/occupancy/<lidar_token>.npy".into(),
        });
    }
    check_predictions(&jobs)?;
    run_jobs(Protocol::NuScenesOccupancy, &jobs, opts, |job, ev| {
        let gt = read_sparse_occupancy(&job.gt)?;
        let pred = read_sparse_occupancy(&job.pred)?;
        ev.add_frame(&pred, &gt, EvalMask::All, &job.name)
    })
}
