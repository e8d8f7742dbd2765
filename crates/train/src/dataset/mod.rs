//! Dataset frames (real or synthetic) to model batches, for the three layouts of [`DatasetFormat`].
//!
//! - SemanticKITTI ([`KittiDataset`]): a frame is `image_2/NNNNNN.png` + `calib.txt` (+
//!   `voxels/NNNNNN.label` and `.invalid` for targets, `velodyne/NNNNNN.bin` for depth supervision).
//! - nuScenes surround layouts ([`SurroundDataset`]): a frame is a key-frame sample of the nuScenes
//!   v1.0 tables with its six cameras (`samples/CAM_*/…`, JPEG or PNG) and `LIDAR_TOP` sweep; targets
//!   from Occ3D (`gts/<scene name>/<sample token>/labels.npz`, grid in the ego frame at the LiDAR
//!   time) or nuScenes-Occupancy (`nuScenes-Occupancy/scene_<scene token>/occupancy/<lidar token>.npy`,
//!   grid in the LiDAR frame).
//!
//! Images go through the docs/formats.md §2.8 pipeline (random resize/crop/flip/rotate when training, drawn
//! per camera; resize + bottom crop at test time, which for 1600x900 nuScenes images at 704x256 is
//! BEVDet's crop), and the augmentation is folded into each camera's `img_from_lidar`, where "lidar"
//! is always the frame of the label grid.
//!
//! Training class ids always have 0 = empty: SemanticKITTI's learning map; Occ3D free (17) -> 0 and
//! class `c` (0..=16) -> `c + 1`, voxels outside `mask_camera` -> 255 (ignored); nuScenes-Occupancy
//! as its reader gives them (noise -> 255).
//!
//! Files of this module:
//! - `mod.rs`: [`DatasetFormat`], [`FrameRef`], [`Sample`], and [`Dataset`], which dispatches over
//!   the layouts (opening, up-front frame checks, loading with the whole-sample augmentation).
//! - `kitti.rs`: [`KittiDataset`] and the checks of its files (image against calibration, file
//!   sizes).
//! - `surround.rs`: [`SurroundDataset`]: opening the nuScenes tables, camera choice, ground-truth
//!   paths and targets, loading frames.
//! - `surround_views.rs`: [`SurroundView`] and [`SurroundFrameViews`], a frame's full-resolution
//!   cameras and LiDAR sweep in the label grid's frame.
//! - `occ3d_labels.rs`: Occ3D classes to training ids and back.
//! - `predictions.rs`: [`Dataset::write_prediction`] in each layout, and [`Dataset::score`].
//! - `collate.rs`: [`camera_input`] and [`collate`], samples to model inputs.
//!
//! The augmentations themselves live elsewhere: the per-camera image augmentation in
//! `occ_data::image` (drawn by each layout's `load`), the lateral mirror in [`crate::mirror`] and
//! the translation in [`crate::shift`] (drawn by [`Dataset::load`]).

mod collate;
mod kitti;
mod occ3d_labels;
mod predictions;
mod surround;
mod surround_views;

pub use collate::{camera_input, collate};
pub use kitti::{check_image_fits_calibration, KittiDataset};
pub use occ3d_labels::{occ3d_from_training, occ3d_training_labels};
pub use surround::SurroundDataset;
pub use surround_views::{SurroundFrameViews, SurroundView};

use crate::error::TrainError;
use occ_eval::Protocol;
use occ_geometry::VoxelGrid;
use occ_model::CameraInput;
use rand::Rng;
use serde::{Deserialize, Serialize};
use std::path::Path;

/// Dataset layout (the config's `data.format`).
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum DatasetFormat {
    /// SemanticKITTI (`sequences/XX/`), one front camera.
    #[default]
    SemanticKitti,
    /// Occ3D-nuScenes: nuScenes tables, six cameras, `gts/<scene>/<token>/labels.npz`.
    Occ3d,
    /// nuScenes-Occupancy (OpenOccupancy): nuScenes tables, six cameras, sparse `.npy` GT.
    NuscenesOccupancy,
}

impl DatasetFormat {
    /// The official evaluation protocol of this layout.
    pub fn protocol(self) -> Protocol {
        match self {
            DatasetFormat::SemanticKitti => Protocol::SemanticKitti,
            DatasetFormat::Occ3d => Protocol::Occ3d,
            DatasetFormat::NuscenesOccupancy => Protocol::NuScenesOccupancy,
        }
    }
    /// Training classes including empty (class 0): 20, 18 or 17.
    pub fn num_classes(self) -> usize {
        self.protocol().num_classes()
    }
    /// The label grid of the real dataset.
    pub fn default_grid(self) -> VoxelGrid {
        match self {
            DatasetFormat::SemanticKitti => VoxelGrid::semantic_kitti(),
            DatasetFormat::Occ3d => VoxelGrid::occ3d_nuscenes(),
            DatasetFormat::NuscenesOccupancy => VoxelGrid::nuscenes_occupancy(),
        }
    }
    /// The config name.
    pub fn name(self) -> &'static str {
        match self {
            DatasetFormat::SemanticKitti => "semantic_kitti",
            DatasetFormat::Occ3d => "occ3d",
            DatasetFormat::NuscenesOccupancy => "nuscenes_occupancy",
        }
    }
}

/// One frame reference.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct FrameRef {
    /// Sequence name ("08").
    pub sequence: String,
    /// Frame stem ("000000").
    pub frame: String,
}

/// A loaded, preprocessed frame (host memory).
#[derive(Clone, Debug)]
pub struct Sample {
    /// Which frame.
    pub frame: FrameRef,
    /// Normalised images, one CHW block per camera (`[V, 3, H, W]` flat).
    pub chw: Vec<f32>,
    /// Network input size (width, height) of every camera.
    pub size: (usize, usize),
    /// Camera geometry per view, with the augmentation folded in (`img_from_lidar` maps the label
    /// grid's frame to pixels).
    pub cameras: Vec<CameraInput>,
    /// Full-resolution training class targets (0 = empty, 255 ignore), if labelled.
    pub target: Option<Vec<u8>>,
    /// LiDAR points in the label grid's frame (metres), if available.
    pub points: Option<Vec<[f32; 3]>>,
}

impl Sample {
    /// Replaces the target (if any) by `f(target)`, for the whole-sample transforms (`crate::mirror`,
    /// `crate::shift`); `f` returns `None` when the target does not match the grid `dims`, which is an
    /// error naming the frame and the transform `what`.
    pub fn map_target(
        &mut self,
        what: &str,
        dims: [usize; 3],
        f: impl FnOnce(&[u8]) -> Option<Vec<u8>>,
    ) -> Result<(), TrainError> {
        if let Some(t) = &mut self.target {
            *t = f(t).ok_or_else(|| {
                TrainError::Data(format!(
                    "frame {}/{}: {what}: {} labels for the grid {dims:?}",
                    self.frame.sequence,
                    self.frame.frame,
                    t.len(),
                ))
            })?;
        }
        Ok(())
    }
}
/// Any of the supported datasets.
// One value per run: the size difference of the variants does not matter.
#[allow(clippy::large_enum_variant)]
#[derive(Clone, Debug)]
pub enum Dataset {
    /// SemanticKITTI layout.
    Kitti(KittiDataset),
    /// nuScenes layouts.
    Surround(SurroundDataset),
}

impl Dataset {
    /// Opens the frames of `sequences` (scene names for the nuScenes layouts, where `"*"` means
    /// every scene not in `exclude`) in the layout `cfg.format`.
    pub fn open(
        root: &Path,
        cfg: &crate::config::DataConfig,
        sequences: &[String],
        exclude: &[String],
    ) -> Result<Self, TrainError> {
        if !(0.0..=1.0).contains(&cfg.mirror_prob) {
            return Err(TrainError::Config(format!(
                "data.mirror_prob must be in [0, 1], got {}",
                cfg.mirror_prob
            )));
        }
        Ok(match cfg.format {
            DatasetFormat::SemanticKitti => {
                let mut d = KittiDataset::open(root, sequences, cfg.pipeline())?;
                d.mirror_prob = cfg.mirror_prob;
                d.shift_voxels = [cfg.shift_voxels.0, cfg.shift_voxels.1];
                Dataset::Kitti(d)
            }
            f => {
                let mut d = SurroundDataset::open(
                    root,
                    f,
                    sequences,
                    exclude,
                    cfg.pipeline(),
                    cfg.gt_dir.as_deref(),
                    cfg.nuscenes_version.as_deref(),
                )?;
                d.mirror_prob = cfg.mirror_prob;
                d.shift_voxels = [cfg.shift_voxels.0, cfg.shift_voxels.1];
                Dataset::Surround(d)
            }
        })
    }

    /// The layout.
    pub fn format(&self) -> DatasetFormat {
        match self {
            Dataset::Kitti(_) => DatasetFormat::SemanticKitti,
            Dataset::Surround(s) => s.format,
        }
    }
    /// Frames in order.
    pub fn frames(&self) -> &[FrameRef] {
        match self {
            Dataset::Kitti(d) => d.frames(),
            Dataset::Surround(d) => &d.refs,
        }
    }
    /// Number of frames.
    pub fn len(&self) -> usize {
        self.frames().len()
    }
    /// True without frames.
    pub fn is_empty(&self) -> bool {
        self.frames().is_empty()
    }
    /// The full-resolution label grid.
    pub fn grid(&self) -> VoxelGrid {
        match self {
            Dataset::Kitti(d) => d.grid(),
            Dataset::Surround(d) => d.grid,
        }
    }
    /// Whether frames carry LiDAR points (depth supervision).
    pub fn set_load_points(&mut self, on: bool) {
        match self {
            Dataset::Kitti(d) => d.load_points = on,
            Dataset::Surround(d) => d.load_points = on,
        }
    }
    /// Checks every frame up front ([`KittiDataset::check_frame`], [`SurroundDataset::check_frame`]:
    /// headers and file sizes, nothing decoded), so that a bad file fails a run before its first step
    /// rather than when the frame comes up. `on_frame(done, total)` reports progress. The error
    /// names the first bad file and the problem, and how many frames are bad in all.
    pub fn check_all(&self, on_frame: &mut dyn FnMut(usize, usize)) -> Result<(), TrainError> {
        let n = self.len();
        let mut first: Option<TrainError> = None;
        let mut bad = 0usize;
        for i in 0..n {
            let r = match self {
                Dataset::Kitti(d) => d.check_frame(i),
                Dataset::Surround(d) => d.check_frame(i),
            };
            if let Err(e) = r {
                bad += 1;
                first.get_or_insert(e);
            }
            on_frame(i + 1, n);
        }
        match first {
            None => Ok(()),
            Some(e) if bad == 1 => Err(e),
            Some(e) => Err(TrainError::Data(format!(
                "{e} (and {} more bad frame(s) of {n})",
                bad - 1
            ))),
        }
    }

    /// Loads frame `i`; with `rng`, applies the training augmentation: the image augmentation per
    /// camera, then the lateral mirror of the whole sample with probability `mirror_prob`, then a
    /// translation by a whole number of voxels drawn uniformly within `±shift_voxels`.
    pub fn load<R: Rng + ?Sized>(
        &self,
        i: usize,
        mut rng: Option<&mut R>,
    ) -> Result<Sample, TrainError> {
        let (mut s, p, shift) = match self {
            Dataset::Kitti(d) => (
                d.load(i, rng.as_deref_mut())?,
                d.mirror_prob,
                d.shift_voxels,
            ),
            Dataset::Surround(d) => (
                d.load(i, rng.as_deref_mut())?,
                d.mirror_prob,
                d.shift_voxels,
            ),
        };
        if let Some(r) = rng {
            if p > 0.0 && r.random::<f64>() < p {
                crate::mirror::mirror_sample_y(&mut s, &self.grid())?;
            }
            if shift != [0, 0] {
                let [mx, my] = shift.map(|m| m as i64);
                let d = [r.random_range(-mx..=mx), r.random_range(-my..=my)];
                crate::shift::shift_sample_xy(&mut s, &self.grid(), d)?;
            }
        }
        Ok(s)
    }
}
