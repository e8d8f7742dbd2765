//! Recall of the non-ground voxels split by what the frame's camera could see (a diagnostic beside
//! the official SemanticKITTI protocol, not part of it; docs/evaluation.md §"Recall by visibility").
//!
//! SemanticKITTI's completion labels are accumulated over the scans of the whole drive through the
//! volume, so a frame's valid voxels include surfaces that its own camera cannot see: the parts of
//! the 51.2 m × 51.2 m volume outside the camera's field of view (beside and behind a front camera),
//! and, inside it, the sides and backs of objects that only later view positions observed. A
//! camera-only model can find the latter only by completing shapes and the former only from the
//! layout. Splitting the recall shows which of the three a model finds:
//!
//! - [`VisibilityClass::OutOfView`]: the voxel centre does not project into the image (or lies
//!   behind the camera);
//! - [`VisibilityClass::InViewSeen`]: it projects into the image and the frame's own sensor saw it
//!   (`.occluded` is 0);
//! - [`VisibilityClass::InViewUnseen`]: it projects into the image but the frame's own sensor did not
//!   see it (`.occluded` is 1: hidden behind a nearer surface, or between the LiDAR's rays).
//!
//! Counted voxels: valid (`.invalid` = 0) ground-truth voxels of the object and structure classes,
//! i.e. occupied and not one of `ground_classes` (learning ids); found = predicted occupied (any
//! class), the same rule as [`crate::EvalReport::non_ground_recall`], whose value is the total here.

use crate::error::EvalError;
use occ_data::formats::semantic_kitti::{
    list_stems, read_calib, read_label_raw, read_packed_bits, KittiPaths, LearningMap,
};
use occ_geometry::{project_voxel_centers, VoxelGrid};
use occ_labels::is_occupied;
use serde::{Deserialize, Serialize};
use std::path::Path;

/// Where a valid ground-truth voxel lies for the frame's camera (module docs).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum VisibilityClass {
    /// Outside the camera's field of view.
    OutOfView,
    /// In the field of view and seen by the frame's own sensor.
    InViewSeen,
    /// In the field of view, not seen by the frame's own sensor.
    InViewUnseen,
}

/// Voxels of one visibility class and how many of them were predicted occupied.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Serialize, Deserialize)]
pub struct RecallCount {
    /// Valid non-ground ground-truth voxels of this class.
    pub voxels: u64,
    /// Of them, predicted occupied.
    pub found: u64,
}

impl RecallCount {
    /// `found / voxels` (NaN when there are none).
    pub fn recall(&self) -> f64 {
        if self.voxels == 0 {
            f64::NAN
        } else {
            self.found as f64 / self.voxels as f64
        }
    }
}

/// Non-ground recall split by visibility (module docs).
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Serialize, Deserialize)]
pub struct VisibilityRecall {
    /// Outside the camera's field of view.
    pub out_of_view: RecallCount,
    /// In view, seen by the frame's sensor.
    pub in_view_seen: RecallCount,
    /// In view, not seen by the frame's sensor.
    pub in_view_unseen: RecallCount,
}

impl VisibilityRecall {
    /// The counter of `class`.
    pub fn of_mut(&mut self, class: VisibilityClass) -> &mut RecallCount {
        match class {
            VisibilityClass::OutOfView => &mut self.out_of_view,
            VisibilityClass::InViewSeen => &mut self.in_view_seen,
            VisibilityClass::InViewUnseen => &mut self.in_view_unseen,
        }
    }

    /// All three together (the plain non-ground recall).
    pub fn total(&self) -> RecallCount {
        let parts = [self.out_of_view, self.in_view_seen, self.in_view_unseen];
        RecallCount {
            voxels: parts.iter().map(|p| p.voxels).sum(),
            found: parts.iter().map(|p| p.found).sum(),
        }
    }

    /// Adds one frame: `gt` and `pred` are learning ids (0 empty, 255 ignored), `invalid`,
    /// `occluded` and `in_view` one flag per voxel (non-zero = set).
    pub fn add_frame(
        &mut self,
        gt: &[u8],
        pred: &[u8],
        invalid: &[u8],
        occluded: &[u8],
        in_view: &[bool],
        ground_classes: &[usize],
    ) -> Result<(), EvalError> {
        let n = gt.len();
        for (what, len) in [
            ("prediction", pred.len()),
            ("invalid mask", invalid.len()),
            ("occluded mask", occluded.len()),
            ("field-of-view mask", in_view.len()),
        ] {
            if len != n {
                return Err(EvalError::SizeMismatch {
                    frame: "visibility split".into(),
                    what,
                    expected: n,
                    got: len,
                });
            }
        }
        for i in 0..n {
            let g = gt[i];
            if invalid[i] != 0 || !is_occupied(g) || ground_classes.contains(&(g as usize)) {
                continue;
            }
            let class = match (in_view[i], occluded[i] != 0) {
                (false, _) => VisibilityClass::OutOfView,
                (true, false) => VisibilityClass::InViewSeen,
                (true, true) => VisibilityClass::InViewUnseen,
            };
            let c = self.of_mut(class);
            c.voxels += 1;
            c.found += u64::from(is_occupied(pred[i]));
        }
        Ok(())
    }
}

/// [`VisibilityRecall`] of a SemanticKITTI-layout prediction folder against `gt_root` over
/// `sequences`: every frame with a `voxels/NNNNNN.label` needs its `.invalid`, `.occluded`, the
/// sequence's `calib.txt` and the prediction `pred_root/sequences/XX/predictions/NNNNNN.label`.
/// `grid` is the label grid, `image_wh` the size of the camera image (`image_2`) in pixels; the
/// field of view is that of `calib.camera_view` (P2 with `Tr`).
pub fn semantic_kitti_recall_by_visibility(
    gt_root: &Path,
    pred_root: &Path,
    sequences: &[String],
    grid: &VoxelGrid,
    image_wh: (usize, usize),
    ground_classes: &[usize],
) -> Result<VisibilityRecall, EvalError> {
    let gt_paths = KittiPaths::new(gt_root);
    let pred_paths = KittiPaths::new(pred_root);
    let map = LearningMap::semantic_kitti();
    let n = grid.num_voxels();
    let mut out = VisibilityRecall::default();
    for seq in sequences {
        let calib = read_calib(&gt_paths.calib(seq))?;
        let view = calib.camera_view(image_wh.0, image_wh.1);
        let in_view = project_voxel_centers(grid, &view).in_view;
        for frame in list_stems(&gt_paths.sequence_dir(seq).join("voxels"), "label")? {
            let gt = map.remap(&read_label_raw(&gt_paths.voxels(seq, &frame, "label"), n)?);
            let pred = map.remap(&read_label_raw(&pred_paths.prediction(seq, &frame), n)?);
            let invalid = read_packed_bits(&gt_paths.voxels(seq, &frame, "invalid"), n)?;
            let occluded = read_packed_bits(&gt_paths.voxels(seq, &frame, "occluded"), n)?;
            out.add_frame(&gt, &pred, &invalid, &occluded, &in_view, ground_classes)?;
        }
    }
    Ok(out)
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Hand-counted: six voxels, one of each case.
    #[test]
    fn counts_each_visibility_class_by_hand() {
        // voxel:      0  1  2   3  4   5
        let gt = [1u8, 13, 15, 9, 1, 255];
        let pred = [1u8, 0, 2, 1, 1, 1];
        let invalid = [0u8, 0, 0, 0, 1, 0];
        let occluded = [0u8, 1, 0, 0, 0, 0];
        let in_view = [true, true, false, true, true, true];
        let mut r = VisibilityRecall::default();
        r.add_frame(
            &gt,
            &pred,
            &invalid,
            &occluded,
            &in_view,
            &[9, 10, 11, 12, 17],
        )
        .unwrap();
        // 0: car, in view, seen, found. 1: building, in view, unseen, missed. 2: vegetation, out of
        // view, found (as another class). 3: road (ground) not counted. 4: invalid. 5: ignored.
        assert_eq!(
            r.in_view_seen,
            RecallCount {
                voxels: 1,
                found: 1
            }
        );
        assert_eq!(
            r.in_view_unseen,
            RecallCount {
                voxels: 1,
                found: 0
            }
        );
        assert_eq!(
            r.out_of_view,
            RecallCount {
                voxels: 1,
                found: 1
            }
        );
        assert_eq!(
            r.total(),
            RecallCount {
                voxels: 3,
                found: 2
            }
        );
        assert!((r.total().recall() - 2.0 / 3.0).abs() < 1e-12);
        assert!(RecallCount::default().recall().is_nan());
        assert!(r
            .add_frame(&gt, &pred[..5], &invalid, &occluded, &in_view, &[])
            .is_err());
    }
}
