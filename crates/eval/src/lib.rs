//! occ-eval: the official occupancy evaluation protocols (docs/evaluation.md).
//!
//! - [`Protocol::SemanticKitti`]: SemanticKITTI SSC (`evaluate_completion.py` of semantic-kitti-api).
//! - [`Protocol::NuScenesOccupancy`]: nuScenes-Occupancy / OpenOccupancy (`occnet.py` + `cm_to_ious`).
//! - [`Protocol::Occ3d`]: Occ3D-nuScenes (`occ_metrics.py` of the CVPR2023 challenge, camera mask).
//!
//! An [`Evaluator`] accumulates a `u64` confusion matrix `conf[pred][gt]` over frames (frames can be
//! added in any order, in parallel evaluators that are merged afterwards); [`Evaluator::report`] turns
//! it into a serialisable [`EvalReport`] (fractions in `[0, 1]`), and [`format_table`] prints it.
//! [`folder`] scores whole prediction folders in the datasets' submission layouts; [`visibility`]
//! splits the non-ground recall by what the frame's camera could see (a diagnostic, not a protocol).

pub mod confusion;
pub mod error;
pub mod folder;
pub mod protocol;
pub mod report;
pub mod visibility;

pub use confusion::ConfusionMatrix;
pub use error::EvalError;
pub use folder::{
    score_folder, score_nuscenes_occupancy_folder, score_occ3d_folder, score_semantic_kitti_folder,
    FolderOptions, Occ3dMask,
};
pub use protocol::{EvalMask, Evaluator, Protocol, SEMANTIC_KITTI_GROUND_CLASSES};
pub use report::{format_table, EvalReport, PerClass};
pub use visibility::{semantic_kitti_recall_by_visibility, RecallCount, VisibilityRecall};
