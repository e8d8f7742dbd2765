//! `sparseocc prepare semantickitti --root DIR [--check]`: check a SemanticKITTI layout and
//! write the preprocessed labels `labels/XX/NNNNNN_1_1.npy` and `_1_2.npy` (docs/formats.md
//! §2.5: `lut[label]`, 255 where invalid, float32, 256x256x32 and 128x128x16).

use crate::error::DataError;
use crate::formats::io::create_dir_all;
use crate::formats::semantic_kitti::{
    list_sequences, list_stems, preprocess_labels, read_label_raw, read_packed_bits, split_of,
    write_label_npy, KittiPaths, LearningMap, DIMS,
};
use crate::labels::downsample_labels;
use rayon::prelude::*;
use serde::Serialize;
use std::collections::BTreeSet;
use std::path::{Path, PathBuf};

/// Options of [`prepare_semantic_kitti`].
#[derive(Clone, Debug, Default, PartialEq, Eq)]
pub struct PrepareOptions {
    /// Only check the layout; write nothing.
    pub check_only: bool,
    /// Restrict to these sequences (default: every folder under `sequences/`).
    pub sequences: Option<Vec<String>>,
    /// Where `labels/XX/...` is written (default: the dataset root).
    pub out_root: Option<PathBuf>,
    /// Rewrite label files that already exist.
    pub overwrite: bool,
}

/// Layout of one sequence.
#[derive(Clone, Debug, Default, PartialEq, Eq, Serialize)]
pub struct SequenceReport {
    pub sequence: String,
    /// "train", "val", "test" or "unknown".
    pub split: String,
    pub has_calib: bool,
    pub has_poses: bool,
    /// SSC frames: stems of `voxels/*.bin`.
    pub ssc_frames: usize,
    pub images: usize,
    pub velodyne: usize,
    pub point_labels: usize,
    pub voxel_bin: usize,
    pub voxel_invalid: usize,
    pub voxel_occluded: usize,
    pub voxel_label: usize,
    /// SSC frames lacking each file (frame ids).
    pub missing_image: Vec<String>,
    pub missing_invalid: Vec<String>,
    pub missing_occluded: Vec<String>,
    pub missing_label: Vec<String>,
    pub missing_velodyne: Vec<String>,
    /// Frames whose `_1_1.npy` / `_1_2.npy` exist after this run.
    pub preprocessed: usize,
    /// Frames written by this run.
    pub written: usize,
}

/// A frame that could not be preprocessed.
#[derive(Clone, Debug, PartialEq, Eq, Serialize)]
pub struct FrameFailure {
    pub sequence: String,
    pub frame: String,
    pub error: String,
}

/// Result of [`prepare_semantic_kitti`] (serialised by the CLI as its JSON summary).
#[derive(Clone, Debug, Default, PartialEq, Eq, Serialize)]
pub struct PrepareReport {
    pub root: PathBuf,
    pub labels_root: PathBuf,
    pub check_only: bool,
    pub sequences: Vec<SequenceReport>,
    /// Official sequences (00-21) not present under `sequences/`.
    pub absent_sequences: Vec<String>,
    /// Frames with `.label` + `.invalid` that can be preprocessed.
    pub preprocessable: usize,
    pub written: usize,
    pub skipped_existing: usize,
    pub failures: Vec<FrameFailure>,
}

impl PrepareReport {
    /// True when nothing failed.
    pub fn ok(&self) -> bool {
        self.failures.is_empty()
    }
}

/// Preprocess one frame: read `voxels/NNNNNN.label` + `.invalid`, write `_1_1.npy` and `_1_2.npy`.
/// `dims` is the dataset's label grid (SemanticKITTI's 256x256x32, or a synthetic dataset's own,
/// from its `synthetic.json`).
pub fn preprocess_frame(
    paths: &KittiPaths,
    labels_root: &Path,
    seq: &str,
    frame: &str,
    map: &LearningMap,
    dims: [usize; 3],
) -> Result<(), DataError> {
    let n = dims.iter().product();
    let raw = read_label_raw(&paths.voxels(seq, frame, "label"), n)?;
    let invalid = read_packed_bits(&paths.voxels(seq, frame, "invalid"), n)?;
    let full = preprocess_labels(&raw, &invalid, map)?;
    let half = downsample_labels(&full, dims, 2)?;
    let out = KittiPaths::new(labels_root);
    write_label_npy(&out.preprocessed_label(seq, frame, 1), &full, dims)?;
    write_label_npy(
        &out.preprocessed_label(seq, frame, 2),
        &half,
        [dims[0] / 2, dims[1] / 2, dims[2] / 2],
    )?;
    Ok(())
}

/// The size problem of a voxel file of `n` voxels, if any (`.label`: 2 bytes per voxel; `.bin`,
/// `.invalid`, `.occluded`: one bit per voxel); a folder in place of the file is one too.
fn voxel_file_problem(path: &Path, ext: &str, n: usize) -> Option<String> {
    let expected = match ext {
        "label" => 2 * n,
        _ => n.div_ceil(8),
    } as u64;
    match std::fs::metadata(path) {
        Err(e) => Some(format!("{}: {e}", path.display())),
        Ok(m) if !m.is_file() => Some(format!("{}: not a file", path.display())),
        Ok(m) if m.len() < expected => Some(format!(
            "{}: truncated: expected {expected} bytes for {n} voxels, found {}",
            path.display(),
            m.len()
        )),
        Ok(m) if m.len() > expected => Some(format!(
            "{}: wrong size: expected {expected} bytes for {n} voxels, found {}",
            path.display(),
            m.len()
        )),
        Ok(_) => None,
    }
}

fn missing(frames: &[String], have: &BTreeSet<String>) -> Vec<String> {
    frames
        .iter()
        .filter(|f| !have.contains(*f))
        .cloned()
        .collect()
}

/// Check the layout under `root` (the folder containing `sequences/`) and, unless
/// `opts.check_only`, write the preprocessed labels of every frame that has `voxels/*.label`
/// and `.invalid`. `progress(done, total)` is called as frames complete (total = frames to write).
/// A frame that fails is recorded in `failures` and the others continue.
pub fn prepare_semantic_kitti(
    root: &Path,
    opts: &PrepareOptions,
    progress: &mut dyn FnMut(usize, usize),
) -> Result<PrepareReport, DataError> {
    let seq_dir = root.join("sequences");
    if !seq_dir.is_dir() {
        return Err(DataError::NotFound {
            path: seq_dir,
            what: "SemanticKITTI `sequences/` folder (is --root the dataset folder?)".into(),
        });
    }
    let paths = KittiPaths::new(root);
    // A synthetic dataset (e.g. `sparseocc synth --preset kitti-small`) has its own grid.
    let dims = match crate::synthetic::read_synthetic_meta(root)? {
        Some(m) => m.grid.dims,
        None => DIMS,
    };
    let n_voxels: usize = dims.iter().product();
    if dims.iter().any(|d| d % 2 != 0) {
        return Err(DataError::InvalidArgument(format!(
            "{}: the label grid {dims:?} cannot be halved for the 1/2-resolution labels",
            root.display()
        )));
    }
    let labels_root = opts.out_root.clone().unwrap_or_else(|| root.to_path_buf());
    let out_paths = KittiPaths::new(&labels_root);
    let present = list_sequences(root)?;
    let selected: Vec<String> = match &opts.sequences {
        Some(list) => {
            for s in list {
                if !present.contains(s) {
                    return Err(DataError::NotFound {
                        path: paths.sequence_dir(s),
                        what: format!("sequence {s}"),
                    });
                }
            }
            list.clone()
        }
        None => present.clone(),
    };
    let mut report = PrepareReport {
        root: root.to_path_buf(),
        labels_root: labels_root.clone(),
        check_only: opts.check_only,
        ..Default::default()
    };
    report.absent_sequences = (0..=21)
        .map(|i| format!("{i:02}"))
        .filter(|s| !present.contains(s))
        .collect();

    let mut jobs: Vec<(usize, String)> = Vec::new();
    for (si, seq) in selected.iter().enumerate() {
        let sdir = paths.sequence_dir(seq);
        let set = |dir: &str, ext: &str| -> Result<BTreeSet<String>, DataError> {
            Ok(list_stems(&sdir.join(dir), ext)?.into_iter().collect())
        };
        let bins = list_stems(&sdir.join("voxels"), "bin")?;
        let images = set("image_2", "png")?;
        let velo = set("velodyne", "bin")?;
        let plabels = set("labels", "label")?;
        let invalid = set("voxels", "invalid")?;
        let occluded = set("voxels", "occluded")?;
        let vlabel = set("voxels", "label")?;
        let mut r = SequenceReport {
            sequence: seq.clone(),
            split: split_of(seq).unwrap_or("unknown").to_string(),
            has_calib: paths.calib(seq).is_file(),
            has_poses: paths.poses(seq).is_file(),
            ssc_frames: bins.len(),
            images: images.len(),
            velodyne: velo.len(),
            point_labels: plabels.len(),
            voxel_bin: bins.len(),
            voxel_invalid: invalid.len(),
            voxel_occluded: occluded.len(),
            voxel_label: vlabel.len(),
            missing_image: missing(&bins, &images),
            missing_invalid: missing(&bins, &invalid),
            missing_occluded: missing(&bins, &occluded),
            missing_velodyne: missing(&bins, &velo),
            ..Default::default()
        };
        // the test split has no labels by design
        if r.split != "test" {
            r.missing_label = missing(&bins, &vlabel);
        }
        // Every voxel file must have the grid's size, also with --check. The `.label` and
        // `.invalid` of a frame that is preprocessed below are read (and their problems reported)
        // by that; the others are reported here.
        let mut problems: Vec<(String, &str, String)> = Vec::new();
        for (ext, stems) in [
            ("bin", bins.iter().cloned().collect::<BTreeSet<String>>()),
            ("label", vlabel.clone()),
            ("invalid", invalid.clone()),
            ("occluded", occluded.clone()),
        ] {
            for f in &stems {
                if let Some(problem) = voxel_file_problem(&paths.voxels(seq, f, ext), ext, n_voxels)
                {
                    problems.push((f.clone(), ext, problem));
                }
            }
        }
        let jobs_before = jobs.len();
        // frames with label + invalid (a .label without .bin still counts)
        for f in vlabel.iter().filter(|f| invalid.contains(*f)) {
            report.preprocessable += 1;
            let done = out_paths.preprocessed_label(seq, f, 1).is_file()
                && out_paths.preprocessed_label(seq, f, 2).is_file();
            if done && !opts.overwrite {
                report.skipped_existing += 1;
                r.preprocessed += 1;
            } else if !opts.check_only {
                jobs.push((si, f.clone()));
            }
        }
        let queued: BTreeSet<&String> = jobs[jobs_before..].iter().map(|(_, f)| f).collect();
        for (f, ext, problem) in problems {
            if !(queued.contains(&f) && (ext == "label" || ext == "invalid")) {
                report.failures.push(FrameFailure {
                    sequence: seq.clone(),
                    frame: f,
                    error: problem,
                });
            }
        }
        report.sequences.push(r);
    }

    if !opts.check_only && !jobs.is_empty() {
        let map = LearningMap::semantic_kitti();
        let seqs: BTreeSet<&String> = jobs.iter().map(|(si, _)| &selected[*si]).collect();
        for s in seqs {
            create_dir_all(&labels_root.join("labels").join(s))?;
        }
        let total = jobs.len();
        progress(0, total);
        let chunk = (rayon::current_num_threads() * 2).max(1);
        let mut done = 0;
        for batch in jobs.chunks(chunk) {
            let results: Vec<Result<(), DataError>> = batch
                .par_iter()
                .map(|(si, f)| {
                    preprocess_frame(&paths, &labels_root, &selected[*si], f, &map, dims)
                })
                .collect();
            for ((si, f), res) in batch.iter().zip(results) {
                match res {
                    Ok(()) => {
                        report.written += 1;
                        report.sequences[*si].written += 1;
                        report.sequences[*si].preprocessed += 1;
                    }
                    Err(e) => report.failures.push(FrameFailure {
                        sequence: selected[*si].clone(),
                        frame: f.clone(),
                        error: e.to_string(),
                    }),
                }
            }
            done += batch.len();
            progress(done, total);
        }
    }
    Ok(report)
}
