//! Predictions of a [`Dataset`]'s frames written in the dataset's own layout, and scored against
//! its ground truth with the layout's official protocol.

use super::{occ3d_from_training, Dataset, DatasetFormat};
use crate::error::TrainError;
use occ_data::formats::nuscenes_occupancy as nocc;
use occ_data::formats::occ3d::{self, Occ3dLabels};
use occ_data::formats::semantic_kitti::{self as sk, KittiPaths};
use occ_data::labels::LearningMap;
use occ_eval::{EvalMask, EvalReport, Evaluator, FolderOptions};
use std::path::{Path, PathBuf};

impl Dataset {
    /// Writes the prediction of frame `i` (training ids, flat `[X][Y][Z]`) below `out_root` in the
    /// dataset's own layout, atomically: SemanticKITTI `sequences/XX/predictions/NNNNNN.label`
    /// (raw ids), Occ3D `<scene>/<token>/labels.npz` (`semantics`, classes 0..=17), nuScenes-Occupancy
    /// `scene_<scene token>/occupancy/<lidar token>.npy` (sparse `[z, y, x, cls]`).
    pub fn write_prediction(
        &self,
        out_root: &Path,
        i: usize,
        classes: &[u8],
    ) -> Result<PathBuf, TrainError> {
        let path = self.prediction_path(out_root, i)?;
        if let Some(dir) = path.parent() {
            std::fs::create_dir_all(dir).map_err(|source| TrainError::Io {
                path: dir.to_path_buf(),
                source,
            })?;
        }
        match self {
            Dataset::Kitti(_) => {
                sk::write_label_raw(&path, &LearningMap::semantic_kitti().inverse_remap(classes))?
            }
            Dataset::Surround(d) if d.format == DatasetFormat::NuscenesOccupancy => {
                nocc::write_sparse_occupancy(&path, classes)?
            }
            Dataset::Surround(d) => {
                let n = d.grid.num_voxels();
                let labels = Occ3dLabels {
                    semantics: occ3d_from_training(classes),
                    mask_lidar: vec![1; n],
                    mask_camera: vec![1; n],
                    dims: d.grid.dims,
                };
                occ3d::write_labels_npz(&path, &labels)?
            }
        }
        Ok(path)
    }

    /// Where [`Dataset::write_prediction`] puts frame `i`.
    pub fn prediction_path(&self, out_root: &Path, i: usize) -> Result<PathBuf, TrainError> {
        let f = self
            .frames()
            .get(i)
            .ok_or_else(|| TrainError::Data(format!("frame index {i} out of range")))?;
        Ok(match self {
            Dataset::Kitti(_) => KittiPaths::new(out_root).prediction(&f.sequence, &f.frame),
            Dataset::Surround(d) if d.format == DatasetFormat::NuscenesOccupancy => {
                let (_, cams) = d.cameras_of(i)?;
                d.tables.occupancy_path(out_root, &cams)
            }
            Dataset::Surround(_) => out_root.join(&f.sequence).join(&f.frame).join("labels.npz"),
        })
    }

    /// True when every frame has ground truth.
    pub fn is_labelled(&self) -> Result<bool, TrainError> {
        match self {
            Dataset::Kitti(d) => Ok(d
                .frames()
                .iter()
                .all(|f| d.paths.voxels(&f.sequence, &f.frame, "label").exists())),
            Dataset::Surround(d) => {
                for i in 0..d.frames.len() {
                    if !d.gt_path(i)?.exists() {
                        return Ok(false);
                    }
                }
                Ok(true)
            }
        }
    }

    /// Scores the predictions written by [`Dataset::write_prediction`] below `pred_root` against
    /// this dataset's frames with the official protocol (the files are read back with the
    /// protocol's own readers; Occ3D evaluates `mask_camera` voxels, nuScenes-Occupancy ignores noise).
    pub fn score(&self, pred_root: &Path) -> Result<EvalReport, TrainError> {
        match self {
            Dataset::Kitti(d) => {
                let mut seqs: Vec<String> = d.frames().iter().map(|f| f.sequence.clone()).collect();
                seqs.dedup();
                Ok(occ_eval::score_semantic_kitti_folder(
                    &d.root,
                    pred_root,
                    &FolderOptions {
                        sequences: Some(&seqs),
                        ..Default::default()
                    },
                )?)
            }
            Dataset::Surround(d) => {
                let mut ev = Evaluator::new(d.format.protocol());
                for i in 0..d.frames.len() {
                    let name =
                        format!("{}/{}", d.frames[i].frame.sequence, d.frames[i].frame.frame);
                    let gt_p = d.gt_path(i)?;
                    let pred_p = self.prediction_path(pred_root, i)?;
                    if d.format == DatasetFormat::NuscenesOccupancy {
                        let gt = nocc::read_sparse_occupancy(&gt_p)?;
                        let pred = nocc::read_sparse_occupancy(&pred_p)?;
                        ev.add_frame(&pred, &gt, EvalMask::All, &name)?;
                    } else {
                        let gt = occ3d::read_labels_npz(&gt_p)?;
                        let pred = occ_eval::folder::read_occ3d_prediction(&pred_p, gt.dims)?;
                        ev.add_frame(
                            &pred,
                            &gt.semantics,
                            EvalMask::Visible(&gt.mask_camera),
                            &name,
                        )?;
                    }
                }
                Ok(ev.report())
            }
        }
    }
}
