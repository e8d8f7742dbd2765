//! The three evaluation protocols and the frame accumulator.
//!
//! # Common rules
//! Predictions and ground truth are per-voxel class indices (`u8`) of the protocol's label space
//! (SemanticKITTI: learning classes after the lut remap, docs/formats.md §2.4). The confusion matrix is
//! `conf[pred][gt]`. A voxel is *evaluated* when its ground truth is a class of the protocol
//! (`gt < num_classes`, which excludes the ignore label 255) and the frame's [`EvalMask`] keeps it.
//!
//! **Invalid predictions.** A prediction that is not a class index (`pred >= num_classes`, e.g. 255
//! from remapping an unknown or ignored SemanticKITTI raw id) is scored as the protocol's *empty* class
//! (SemanticKITTI / nuScenes-Occupancy 0, Occ3D 17 free) and counted in
//! [`EvalReport::invalid_predictions`]. The official scripts have no defined behaviour here:
//! semantic-kitti-api's `np.add.at(conf, (pred, gt), 1)` raises an IndexError for a remapped 255,
//! and the `np.bincount(n*gt + pred)` of OpenOccupancy / Occ3D silently moves such a voxel into the
//! next ground-truth row (or drops it). Scoring it as empty means: it is a false negative for its
//! ground-truth class and a false positive only for the empty class, which is outside every mIoU, so
//! the mIoU equals the one of a separate "invalid" row; for the geometry metrics it is "not
//! predicted occupied".
//!
//! # Per protocol
//! | | classes | empty | per-class IoU | mIoU | mask |
//! |---|---|---|---|---|---|
//! | SemanticKITTI (docs/evaluation.md §2) | 20 | 0 | `TP/(TP+FP+FN+1e-15)` | mean over 1..=19 (absent classes count 0) | `.invalid == 1` excluded |
//! | nuScenes-Occupancy (docs/evaluation.md §3) | 17 | 0 | `tp/(p+g-tp)` (NaN if 0/0) | mean over 1..=16 (NaN if any NaN, as `np.mean`) | none (GT 255 ignored) |
//! | Occ3D (docs/evaluation.md §4) | 18 | 17 (free) | `diag/(row+col-diag)` (NaN if 0/0) | nanmean over 0..=16 (free excluded, but it counts in FP/FN) | `mask_camera != 0` kept |
//!
//! Geometry metrics (empty class `e`): completion IoU `= Σ_{p≠e,g≠e} conf / (Σconf − conf[e][e])`
//! (NaN if 0/0, as numpy), precision `= Σ_{p≠e,g≠e} conf / (Σ_{p≠e} conf + ε)`, recall
//! `= Σ_{p≠e,g≠e} conf / (Σ_{g≠e} conf + ε)` with `ε = f32::EPSILON` exactly as
//! `evaluate_completion.py`. For nuScenes-Occupancy the completion IoU is the official SC IoU (the
//! binary `non-empty` IoU of `cm_to_ious`); for Occ3D it is the occupied-vs-free IoU (mmdet3d
//! `compute_occ_iou`), not part of the challenge metric. Precision/recall use the SemanticKITTI
//! formula for all protocols.

use crate::confusion::ConfusionMatrix;
use crate::error::EvalError;
use crate::report::{EvalReport, PerClass};
use serde::{Deserialize, Serialize};

/// SemanticKITTI learning-class names, index 0..=19 (docs/formats.md §2.4), as defined by the reader.
pub const SEMANTIC_KITTI_CLASSES: [&str; 20] = occ_data::formats::semantic_kitti::CLASS_NAMES;

/// SemanticKITTI learning classes of the ground (road, parking, sidewalk, other-ground, terrain);
/// every other class but empty is an object or a structure standing on it.
pub const SEMANTIC_KITTI_GROUND_CLASSES: [usize; 5] = [9, 10, 11, 12, 17];

/// nuScenes-Occupancy class names, index 0..=16 (docs/formats.md §3; 0 = empty, noise is ignored as 255).
pub const NUSCENES_OCCUPANCY_CLASSES: [&str; 17] =
    occ_data::formats::nuscenes_occupancy::CLASS_NAMES;

/// Occ3D-nuScenes class names, index 0..=17 (docs/formats.md §4; 17 = free).
pub const OCC3D_CLASSES: [&str; 18] = occ_data::formats::occ3d::CLASS_NAMES;

/// Evaluation protocol (dataset).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, Serialize, Deserialize)]
pub enum Protocol {
    /// SemanticKITTI semantic scene completion (docs/evaluation.md §2).
    #[serde(rename = "semantickitti")]
    SemanticKitti,
    /// nuScenes-Occupancy / OpenOccupancy (docs/evaluation.md §3).
    #[serde(rename = "nuscenes-occupancy")]
    NuScenesOccupancy,
    /// Occ3D-nuScenes (docs/evaluation.md §4).
    #[serde(rename = "occ3d")]
    Occ3d,
}

impl Protocol {
    /// Class names, indexed by class id.
    pub fn class_names(self) -> &'static [&'static str] {
        match self {
            Protocol::SemanticKitti => &SEMANTIC_KITTI_CLASSES,
            Protocol::NuScenesOccupancy => &NUSCENES_OCCUPANCY_CLASSES,
            Protocol::Occ3d => &OCC3D_CLASSES,
        }
    }

    /// Number of classes (size of the confusion matrix).
    pub fn num_classes(self) -> usize {
        self.class_names().len()
    }

    /// The empty / free class (geometry metrics; invalid predictions are scored as this).
    pub fn empty_class(self) -> u8 {
        match self {
            Protocol::SemanticKitti | Protocol::NuScenesOccupancy => 0,
            Protocol::Occ3d => 17,
        }
    }

    /// Classes averaged in the mIoU (and listed in the report's `per_class`).
    pub fn miou_classes(self) -> std::ops::Range<usize> {
        match self {
            Protocol::SemanticKitti => 1..20,
            Protocol::NuScenesOccupancy => 1..17,
            Protocol::Occ3d => 0..17,
        }
    }

    /// The name used on the command line and in reports.
    pub fn name(self) -> &'static str {
        match self {
            Protocol::SemanticKitti => "semantickitti",
            Protocol::NuScenesOccupancy => "nuscenes-occupancy",
            Protocol::Occ3d => "occ3d",
        }
    }

    /// Per-class IoU of class `c` with this protocol's formula (NaN where it is 0/0).
    pub fn class_iou(self, conf: &ConfusionMatrix, c: usize) -> f64 {
        let tp = conf.get(c, c) as f64;
        let pred = conf.row_sum(c) as f64;
        let gt = conf.col_sum(c) as f64;
        match self {
            // TP / (TP + FP + FN + 1e-15) with FP = row - TP, FN = col - TP.
            Protocol::SemanticKitti => tp / (tp + (pred - tp) + (gt - tp) + 1e-15),
            Protocol::NuScenesOccupancy | Protocol::Occ3d => tp / (pred + gt - tp),
        }
    }

    /// mIoU from per-class IoUs of all classes.
    fn miou(self, ious: &[f64]) -> f64 {
        let sel = &ious[self.miou_classes()];
        match self {
            // np.mean: NaN propagates (cannot occur for SemanticKITTI thanks to the 1e-15).
            Protocol::SemanticKitti | Protocol::NuScenesOccupancy => {
                sel.iter().sum::<f64>() / sel.len() as f64
            }
            // np.nanmean: NaN entries skipped; all NaN gives NaN.
            Protocol::Occ3d => {
                let valid: Vec<f64> = sel.iter().copied().filter(|v| !v.is_nan()).collect();
                if valid.is_empty() {
                    f64::NAN
                } else {
                    valid.iter().sum::<f64>() / valid.len() as f64
                }
            }
        }
    }
}

impl std::str::FromStr for Protocol {
    type Err = String;
    fn from_str(s: &str) -> Result<Self, Self::Err> {
        match s.to_ascii_lowercase().replace('_', "-").as_str() {
            "semantickitti" | "semantic-kitti" | "kitti" => Ok(Protocol::SemanticKitti),
            "nuscenes-occupancy" | "nuscenes" | "openoccupancy" => Ok(Protocol::NuScenesOccupancy),
            "occ3d" | "occ3d-nuscenes" => Ok(Protocol::Occ3d),
            other => Err(format!(
                "unknown dataset '{other}' (expected semantickitti, nuscenes-occupancy or occ3d)"
            )),
        }
    }
}

/// Which voxels of a frame are evaluated (in addition to `gt < num_classes`).
#[derive(Debug, Clone, Copy)]
pub enum EvalMask<'a> {
    /// Every voxel.
    All,
    /// SemanticKITTI `.invalid` grid (unpacked, one byte per voxel): voxels equal to 1 are excluded
    /// (`evaluate_completion.py` `masks[invalid_voxels == 1] = False`).
    Invalid(&'a [u8]),
    /// Visibility grid (Occ3D `mask_camera`, OpenOccupancy `visible_mask`): voxels that are nonzero
    /// are kept (numpy boolean indexing of the mask cast to bool).
    Visible(&'a [u8]),
}

/// Errors unless the counts of `conf` sum to a `u64` (every row, column and total the metrics
/// take then fits too); `what` names the matrix.
fn check_total(conf: &ConfusionMatrix, what: &str) -> Result<(), EvalError> {
    if conf.checked_total().is_none() {
        return Err(EvalError::Incompatible(format!(
            "{what}: its counts sum to more than 2^64 - 1 voxels"
        )));
    }
    Ok(())
}

/// Confusion-matrix accumulator of one protocol over any number of frames.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct Evaluator {
    protocol: Protocol,
    conf: ConfusionMatrix,
    frames: u64,
    invalid_predictions: u64,
}

impl Evaluator {
    /// Empty accumulator.
    pub fn new(protocol: Protocol) -> Self {
        Self {
            protocol,
            conf: ConfusionMatrix::new(protocol.num_classes()),
            frames: 0,
            invalid_predictions: 0,
        }
    }

    /// Rebuild an accumulator from a report (e.g. to merge the reports of several shards).
    pub fn from_report(report: &EvalReport) -> Result<Self, EvalError> {
        let conf = ConfusionMatrix::from_rows(&report.confusion).ok_or_else(|| {
            EvalError::Incompatible("report confusion matrix is not square".into())
        })?;
        if conf.num_classes() != report.dataset.num_classes() {
            return Err(EvalError::Incompatible(format!(
                "report confusion matrix is {}x{} but {} has {} classes",
                conf.num_classes(),
                conf.num_classes(),
                report.dataset.name(),
                report.dataset.num_classes()
            )));
        }
        check_total(&conf, "report confusion matrix")?;
        Ok(Self {
            protocol: report.dataset,
            conf,
            frames: report.frames,
            invalid_predictions: report.invalid_predictions,
        })
    }

    /// An accumulator holding `conf` (`conf[pred][gt]`, e.g. the sum of several frames' matrices)
    /// over `frames` frames. Predictions that were not class indices are already in `conf` as the
    /// empty class, so the count of invalid predictions is 0.
    pub fn from_confusion(
        protocol: Protocol,
        conf: ConfusionMatrix,
        frames: u64,
    ) -> Result<Self, EvalError> {
        if conf.num_classes() != protocol.num_classes() {
            return Err(EvalError::Incompatible(format!(
                "confusion matrix is {n}x{n} but {} has {} classes",
                protocol.name(),
                protocol.num_classes(),
                n = conf.num_classes()
            )));
        }
        check_total(&conf, "confusion matrix")?;
        Ok(Self {
            protocol,
            conf,
            frames,
            invalid_predictions: 0,
        })
    }

    /// The protocol.
    pub fn protocol(&self) -> Protocol {
        self.protocol
    }

    /// The accumulated `conf[pred][gt]`.
    pub fn confusion(&self) -> &ConfusionMatrix {
        &self.conf
    }

    /// Frames added so far.
    pub fn frames(&self) -> u64 {
        self.frames
    }

    /// Add one frame. `pred` and `gt` are class indices of equal length; `mask` selects voxels
    /// (see [`EvalMask`]); `frame` names the frame in errors.
    pub fn add_frame(
        &mut self,
        pred: &[u8],
        gt: &[u8],
        mask: EvalMask<'_>,
        frame: &str,
    ) -> Result<(), EvalError> {
        let size_err = |what, got| EvalError::SizeMismatch {
            frame: frame.to_string(),
            what,
            expected: gt.len(),
            got,
        };
        if pred.len() != gt.len() {
            return Err(size_err("prediction", pred.len()));
        }
        let n = self.protocol.num_classes();
        let empty = usize::from(self.protocol.empty_class());
        // Dense local histogram over all (pred, gt) byte pairs: no branches in the hot loop.
        let mut hist = vec![0u64; 256 * 256];
        match mask {
            EvalMask::All => {
                for (&p, &g) in pred.iter().zip(gt) {
                    hist[usize::from(p) * 256 + usize::from(g)] += 1;
                }
            }
            EvalMask::Invalid(m) | EvalMask::Visible(m) => {
                if m.len() != gt.len() {
                    return Err(size_err("mask", m.len()));
                }
                let keep_if_one = matches!(mask, EvalMask::Visible(_));
                for ((&p, &g), &mv) in pred.iter().zip(gt).zip(m) {
                    let keep = if keep_if_one { mv != 0 } else { mv != 1 };
                    hist[usize::from(p) * 256 + usize::from(g)] += u64::from(keep);
                }
            }
        }
        for p in 0..256 {
            for g in 0..n {
                let c = hist[p * 256 + g];
                if c == 0 {
                    continue;
                }
                if p < n {
                    self.conf.add(p, g, c);
                } else {
                    self.conf.add(empty, g, c);
                    self.invalid_predictions += c;
                }
            }
        }
        self.frames += 1;
        Ok(())
    }

    /// Add another accumulator of the same protocol.
    pub fn merge(&mut self, other: &Evaluator) -> Result<(), EvalError> {
        let sum = u128::from(self.conf.total()) + u128::from(other.conf.total());
        if sum > u128::from(u64::MAX) {
            return Err(EvalError::Incompatible(format!(
                "merging two evaluations of {sum} voxels in all: more than 2^64 - 1"
            )));
        }
        if other.protocol != self.protocol || !self.conf.merge(&other.conf) {
            return Err(EvalError::Incompatible(format!(
                "{} evaluator merged with {} evaluator",
                self.protocol.name(),
                other.protocol.name()
            )));
        }
        self.frames += other.frames;
        self.invalid_predictions += other.invalid_predictions;
        Ok(())
    }

    /// The metrics of everything added so far.
    pub fn report(&self) -> EvalReport {
        let p = self.protocol;
        let conf = &self.conf;
        let n = p.num_classes();
        let ious: Vec<f64> = (0..n).map(|c| p.class_iou(conf, c)).collect();
        let e = usize::from(p.empty_class());
        let total = conf.total();
        let ee = conf.get(e, e);
        let pred_empty = conf.row_sum(e);
        let gt_empty = conf.col_sum(e);
        // Σ over p≠e, g≠e = total − row(e) − (col(e) − conf[e][e]); in this order no step leaves
        // 0..=total.
        let occ_tp = (total - pred_empty - (gt_empty - ee)) as f64;
        let pred_occ = (total - pred_empty) as f64;
        let gt_occ = (total - gt_empty) as f64;
        let eps = f64::from(f32::EPSILON);
        let names = p.class_names();
        EvalReport {
            dataset: p,
            frames: self.frames,
            evaluated_voxels: total,
            invalid_predictions: self.invalid_predictions,
            iou: occ_tp / (total - ee) as f64,
            precision: occ_tp / (pred_occ + eps),
            recall: occ_tp / (gt_occ + eps),
            miou: p.miou(&ious),
            per_class: PerClass(
                p.miou_classes()
                    .map(|c| (names[c].to_string(), ious[c]))
                    .collect(),
            ),
            confusion: conf.to_rows(),
        }
    }
}
