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

use crate::error::TrainError;
use burn::prelude::*;
use burn::tensor::TensorData;
use occ_data::formats::nuscenes_occupancy::{self as nocc, NuscenesTables, SampleCameras};
use occ_data::formats::occ3d::{self, Occ3dLabels};
use occ_data::formats::semantic_kitti::{self as sk, KittiPaths};
use occ_data::image::{process_image, read_image, read_image_size, ImagePipelineConfig};
use occ_data::labels::LearningMap;
use occ_eval::{EvalMask, EvalReport, Evaluator, FolderOptions, Protocol};
use occ_geometry::{transform_point, CameraView, Mat4, VoxelGrid};
use occ_labels::{EMPTY, IGNORE};
use occ_model::{Batch, CameraInput};
use rand::Rng;
use serde::{Deserialize, Serialize};
use std::path::{Path, PathBuf};

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

/// An image of `width` x `height` pixels must belong to the KITTI calibration `calib` (read from
/// `calib_path`): its principal point inside the central half of the image. Otherwise an error
/// naming both files (the image was resized or cropped without adjusting P2, or belongs to another
/// camera).
pub fn check_image_fits_calibration(
    image: &Path,
    width: usize,
    height: usize,
    calib_path: &Path,
    calib: &sk::Calib,
) -> Result<(), TrainError> {
    let (cx, cy) = (calib.p2[0][2], calib.p2[1][2]);
    let (w, h) = (width as f64, height as f64);
    if !(cx > 0.25 * w && cx < 0.75 * w && cy > 0.25 * h && cy < 0.75 * h) {
        return Err(TrainError::Data(format!(
            "{}: image is {width}x{height} but the calibration {} puts the principal point at ({cx:.1}, {cy:.1}); \
             the image does not belong to this calibration (or was resized without adjusting P2)",
            image.display(),
            calib_path.display()
        )));
    }
    Ok(())
}

/// Length of `path` in bytes (an error naming it when it cannot be read).
fn file_len(path: &Path) -> Result<u64, TrainError> {
    std::fs::metadata(path)
        .map(|m| m.len())
        .map_err(|e| TrainError::Data(format!("{}: {e}", path.display())))
}

/// `path` must be `expected` bytes long (`what` it holds, for the message).
fn check_file_len(path: &Path, expected: u64, what: &str) -> Result<(), TrainError> {
    let len = file_len(path)?;
    if len != expected {
        return Err(TrainError::Data(format!(
            "{}: {len} bytes, but {what} of this grid take {expected}",
            path.display()
        )));
    }
    Ok(())
}

/// A SemanticKITTI-layout dataset.
#[derive(Clone, Debug)]
pub struct KittiDataset {
    root: PathBuf,
    paths: KittiPaths,
    frames: Vec<FrameRef>,
    grid: VoxelGrid,
    pipeline: ImagePipelineConfig,
    map: LearningMap,
    /// Load LiDAR points (depth supervision).
    pub load_points: bool,
    /// Training: probability of the lateral mirror ([`crate::mirror`]).
    pub mirror_prob: f64,
    /// Training: largest translation in voxels along x and y ([`crate::shift`]).
    pub shift_voxels: [usize; 2],
}

impl KittiDataset {
    /// Opens `root` (the folder with `sequences/`), listing the frames of `sequences` that have an image.
    /// The label grid comes from `synthetic.json` when present, else SemanticKITTI's 256x256x32.
    pub fn open(
        root: &Path,
        sequences: &[String],
        pipeline: ImagePipelineConfig,
    ) -> Result<Self, TrainError> {
        let paths = KittiPaths::new(root);
        let grid = match occ_data::synthetic::read_synthetic_meta(root)? {
            Some(m) => m.grid,
            None => VoxelGrid::semantic_kitti(),
        };
        let mut frames = Vec::new();
        for seq in sequences {
            let dir = root.join("sequences").join(seq).join("image_2");
            if !dir.is_dir() {
                return Err(TrainError::Data(format!(
                    "{}: missing (sequence {seq} has no image_2 folder)",
                    dir.display()
                )));
            }
            let images = sk::list_stems(&dir, "png")?;
            // A labelled frame without its image would be left out of the predictions (and then
            // reported as a missing prediction when scoring): name every such frame now.
            let labelled = sk::list_stems(&paths.sequence_dir(seq).join("voxels"), "label")?;
            let orphans: Vec<&String> = labelled
                .iter()
                .filter(|f| images.binary_search(f).is_err())
                .collect();
            if let Some(first) = orphans.first() {
                return Err(TrainError::Data(format!(
                    "{}: missing; {} labelled frame(s) of sequence {seq} have no image ({})",
                    paths.image_2(seq, first).display(),
                    orphans.len(),
                    orphans
                        .iter()
                        .take(10)
                        .map(|s| s.as_str())
                        .collect::<Vec<_>>()
                        .join(", ")
                )));
            }
            for frame in images {
                frames.push(FrameRef {
                    sequence: seq.clone(),
                    frame,
                });
            }
        }
        if frames.is_empty() {
            return Err(TrainError::Data(format!(
                "{}: no frames in sequences {sequences:?}",
                root.display()
            )));
        }
        Ok(Self {
            root: root.to_path_buf(),
            paths,
            frames,
            grid,
            pipeline,
            map: LearningMap::semantic_kitti(),
            load_points: false,
            mirror_prob: 0.0,
            shift_voxels: [0, 0],
        })
    }

    /// The dataset root.
    pub fn root(&self) -> &Path {
        &self.root
    }
    /// Frames in order.
    pub fn frames(&self) -> &[FrameRef] {
        &self.frames
    }
    /// Number of frames.
    pub fn len(&self) -> usize {
        self.frames.len()
    }
    /// True without frames.
    pub fn is_empty(&self) -> bool {
        self.frames.is_empty()
    }
    /// The full-resolution label grid.
    pub fn grid(&self) -> VoxelGrid {
        self.grid
    }

    /// What [`Self::load`] would refuse in frame `i`, found without decoding it: the sequence's
    /// calibration, the image header (size limit, against the calibration), and the sizes of the
    /// label, `.invalid` and (with `load_points`) velodyne files. `Err` names the file and the problem.
    pub fn check_frame(&self, i: usize) -> Result<(), TrainError> {
        let f = self
            .frames
            .get(i)
            .ok_or_else(|| TrainError::Data(format!("frame index {i} out of range")))?;
        let img_path = self.paths.image_2(&f.sequence, &f.frame);
        let calib_path = self.paths.calib(&f.sequence);
        let calib = sk::read_calib(&calib_path)?;
        let (w, h) = read_image_size(&img_path)?;
        check_image_fits_calibration(&img_path, w, h, &calib_path, &calib)?;
        let n = self.grid.num_voxels() as u64;
        let label_p = self.paths.voxels(&f.sequence, &f.frame, "label");
        if label_p.exists() {
            check_file_len(&label_p, 2 * n, "uint16 voxel labels")?;
            let inv_p = self.paths.voxels(&f.sequence, &f.frame, "invalid");
            if inv_p.exists() {
                check_file_len(&inv_p, n.div_ceil(8), "bit-packed voxel mask")?;
            }
        }
        if self.load_points {
            let p = self.paths.velodyne(&f.sequence, &f.frame);
            if p.exists() {
                let len = file_len(&p)?;
                if len % 16 != 0 {
                    return Err(TrainError::Data(format!(
                        "{}: {len} bytes is not a whole number of float32 (x, y, z, intensity) points",
                        p.display()
                    )));
                }
            }
        }
        Ok(())
    }

    /// Loads frame `i`; with `rng`, applies the training augmentation.
    pub fn load<R: Rng + ?Sized>(
        &self,
        i: usize,
        rng: Option<&mut R>,
    ) -> Result<Sample, TrainError> {
        let f = self
            .frames
            .get(i)
            .ok_or_else(|| TrainError::Data(format!("frame index {i} out of range")))?
            .clone();
        let img_path = self.paths.image_2(&f.sequence, &f.frame);
        let calib_path = self.paths.calib(&f.sequence);
        let calib = sk::read_calib(&calib_path)?;
        // The image's header against its calibration before decoding it.
        let (w, h) = read_image_size(&img_path)?;
        check_image_fits_calibration(&img_path, w, h, &calib_path, &calib)?;
        let img = read_image(&img_path)?;
        let aug = match rng {
            Some(r) => self.pipeline.sample_train_aug(img.width, img.height, r),
            None => self.pipeline.test_aug(img.width, img.height),
        };
        let processed = process_image(&img, &aug)?;
        let view = calib.camera_view(img.width, img.height).augmented(&aug);
        let camera = camera_input(&view);
        let n = self.grid.num_voxels();
        let label_p = self.paths.voxels(&f.sequence, &f.frame, "label");
        let target = if label_p.exists() {
            let raw = sk::read_label_raw(&label_p, n)?;
            // Unlisted ids are ignored (255), as in scoring; a frame made mostly of them is not
            // SemanticKITTI ground truth.
            let count = raw.iter().filter(|&&r| !self.map.is_listed(r)).count();
            if count * 2 > raw.len() {
                let bad = raw
                    .iter()
                    .find(|&&r| !self.map.is_listed(r))
                    .copied()
                    .unwrap_or_default();
                return Err(TrainError::Data(format!(
                    "{}: {count} of {n} voxels have ids the SemanticKITTI learning map does not list \
                     (e.g. {bad}); not SemanticKITTI voxel labels",
                    label_p.display()
                )));
            }
            let mut t = self.map.remap(&raw);
            let inv_p = self.paths.voxels(&f.sequence, &f.frame, "invalid");
            if inv_p.exists() {
                let inv = sk::read_packed_bits(&inv_p, n)?;
                for (t, &v) in t.iter_mut().zip(&inv) {
                    if v == 1 {
                        *t = IGNORE;
                    }
                }
            }
            Some(t)
        } else {
            None
        };
        let points = if self.load_points {
            let p = self.paths.velodyne(&f.sequence, &f.frame);
            if p.exists() {
                Some(
                    sk::read_velodyne(&p)?
                        .iter()
                        .map(|q| [q[0], q[1], q[2]])
                        .collect(),
                )
            } else {
                None
            }
        } else {
            None
        };
        Ok(Sample {
            frame: f,
            chw: processed.chw,
            size: (processed.width, processed.height),
            cameras: vec![camera],
            target,
            points,
        })
    }
}

/// One key-frame sample of a nuScenes-layout dataset.
#[derive(Clone, Debug)]
struct SurroundFrame {
    /// `sequence` = scene name, `frame` = sample token.
    frame: FrameRef,
}

/// A nuScenes-layout dataset (six cameras) with Occ3D or nuScenes-Occupancy ground truth.
#[derive(Clone, Debug)]
pub struct SurroundDataset {
    root: PathBuf,
    format: DatasetFormat,
    tables: std::sync::Arc<NuscenesTables>,
    frames: Vec<SurroundFrame>,
    refs: Vec<FrameRef>,
    grid: VoxelGrid,
    gt_root: PathBuf,
    pipeline: ImagePipelineConfig,
    /// Camera channels of every frame, in order (the six nuScenes cameras unless
    /// [`SurroundDataset::set_cameras`] chose others).
    channels: Vec<String>,
    /// Load LiDAR points (depth supervision).
    pub load_points: bool,
    /// Training: probability of the lateral mirror ([`crate::mirror`]).
    pub mirror_prob: f64,
    /// Training: largest translation in voxels along x and y ([`crate::shift`]).
    pub shift_voxels: [usize; 2],
}

/// One camera of a frame at full resolution, mapping the label grid's frame to its pixels.
#[derive(Clone, Debug, PartialEq)]
pub struct SurroundView {
    /// Channel (`CAM_FRONT`, or a custom rig's name).
    pub channel: String,
    /// The camera's `sample_data` token.
    pub sample_data_token: String,
    /// The image file.
    pub image: PathBuf,
    /// Intrinsics and image size of the tables; `cam_from_lidar` maps the label grid's frame to
    /// the camera at its own timestamp (ego motion between the LiDAR and camera timestamps
    /// applied); no augmentation.
    pub view: CameraView,
}

/// The cameras and LiDAR sweep of one frame, in the label grid's frame (what
/// [`SurroundDataset::load`] builds a [`Sample`] from, before any image augmentation).
#[derive(Clone, Debug, PartialEq)]
pub struct SurroundFrameViews {
    /// Scene name and sample token.
    pub frame: FrameRef,
    /// The cameras in the dataset's order.
    pub cameras: Vec<SurroundView>,
    /// The key-frame `LIDAR_TOP` file.
    pub lidar: PathBuf,
    /// `grid_from_lidar`: the LiDAR calibration for Occ3D (grid in the ego frame at the LiDAR
    /// time), the identity for nuScenes-Occupancy (grid in the LiDAR frame).
    pub grid_from_lidar: Mat4,
}

impl SurroundFrameViews {
    /// The LiDAR sweep's points in the label grid's frame (metres).
    pub fn read_points(&self) -> Result<Vec<[f32; 3]>, TrainError> {
        let pts = nocc::read_lidar_pcd_bin(&self.lidar)?;
        Ok(pts
            .iter()
            .map(|q| transform_point(&self.grid_from_lidar, q.map(f64::from)).map(|v| v as f32))
            .collect())
    }
}

impl SurroundDataset {
    /// Opens `root` (the nuScenes root: `samples/`, the table folder, the ground-truth folder).
    /// `scenes` are scene names (`scene-0103`); `"*"` adds every scene not in `exclude`, in table
    /// order. Frames are the key-frame samples of those scenes, by timestamp.
    pub fn open(
        root: &Path,
        format: DatasetFormat,
        scenes: &[String],
        exclude: &[String],
        pipeline: ImagePipelineConfig,
        gt_dir: Option<&str>,
        version: Option<&str>,
    ) -> Result<Self, TrainError> {
        if format == DatasetFormat::SemanticKitti {
            return Err(TrainError::Config(
                "SurroundDataset: the semantic_kitti layout has no surround cameras".into(),
            ));
        }
        let meta = occ_data::synthetic::read_synthetic_meta(root)?;
        let version = match version {
            Some(v) => v.to_string(),
            None => match meta.as_ref().and_then(|m| m.nuscenes_version.clone()) {
                Some(v) => v,
                None => ["v1.0-trainval", "v1.0-mini", "v1.0-test"]
                    .into_iter()
                    .find(|v| root.join(v).join("sample.json").is_file())
                    .ok_or_else(|| {
                        TrainError::Data(format!(
                            "{}: no nuScenes tables (v1.0-trainval/, v1.0-mini/ or v1.0-test/ with sample.json); \
                             set data.nuscenes_version",
                            root.display()
                        ))
                    })?
                    .to_string(),
            },
        };
        let table_dir = root.join(&version);
        let tables = NuscenesTables::load(&table_dir)?;
        let scene_rows = nocc::read_scenes(&table_dir)?;
        let mut chosen: Vec<&nocc::SceneRow> = Vec::new();
        for name in scenes {
            if name == "*" {
                for r in &scene_rows {
                    if !exclude.contains(&r.name) && !chosen.iter().any(|c| c.token == r.token) {
                        chosen.push(r);
                    }
                }
            } else {
                let r = scene_rows.iter().find(|r| &r.name == name).ok_or_else(|| {
                    TrainError::Data(format!(
                        "{}: no scene named `{name}` (the tables have {} scenes)",
                        table_dir.join("scene.json").display(),
                        scene_rows.len()
                    ))
                })?;
                if !chosen.iter().any(|c| c.token == r.token) {
                    chosen.push(r);
                }
            }
        }
        let mut frames = Vec::new();
        for scene in &chosen {
            let mut samples: Vec<_> = tables
                .sample
                .iter()
                .filter(|s| s.scene_token == scene.token)
                .collect();
            samples.sort_by_key(|s| s.timestamp);
            frames.extend(samples.into_iter().map(|s| SurroundFrame {
                frame: FrameRef {
                    sequence: scene.name.clone(),
                    frame: s.token.clone(),
                },
            }));
        }
        if frames.is_empty() {
            return Err(TrainError::Data(format!(
                "{}: no key-frame samples in scenes {scenes:?}",
                table_dir.display()
            )));
        }
        let grid = match (&meta, format) {
            (Some(m), DatasetFormat::Occ3d) => m.grid,
            _ => format.default_grid(),
        };
        let gt_root = root.join(gt_dir.unwrap_or(match format {
            DatasetFormat::NuscenesOccupancy => "nuScenes-Occupancy",
            _ => "gts",
        }));
        let refs = frames.iter().map(|f| f.frame.clone()).collect();
        Ok(Self {
            root: root.to_path_buf(),
            format,
            tables: std::sync::Arc::new(tables),
            frames,
            refs,
            grid,
            gt_root,
            pipeline,
            channels: nocc::CAMERA_CHANNELS
                .iter()
                .map(|c| c.to_string())
                .collect(),
            load_points: false,
            mirror_prob: 0.0,
            shift_voxels: [0, 0],
        })
    }

    /// The layout.
    pub fn format(&self) -> DatasetFormat {
        self.format
    }
    /// Frames in order (`sequence` = scene name, `frame` = sample token).
    pub fn frames(&self) -> &[FrameRef] {
        &self.refs
    }
    /// The full-resolution label grid.
    pub fn grid(&self) -> VoxelGrid {
        self.grid
    }
    /// The nuScenes tables.
    pub fn tables(&self) -> &NuscenesTables {
        &self.tables
    }
    /// The camera channels of every frame, in order.
    pub fn cameras(&self) -> &[String] {
        &self.channels
    }

    /// Uses the cameras `channels` in this order instead of the six nuScenes ones (a custom rig;
    /// [`NuscenesTables::camera_channels`] lists the rig of `sensor.json`). Every channel must be
    /// a camera sensor of the tables, else an error naming `sensor.json` and the channel.
    pub fn set_cameras(&mut self, channels: Vec<String>) -> Result<(), TrainError> {
        let rig = self.tables.camera_channels();
        if channels.is_empty() {
            return Err(TrainError::Data(format!(
                "{}: no cameras chosen (the rig has {})",
                self.tables.dir.join("sensor.json").display(),
                rig.join(", ")
            )));
        }
        for c in &channels {
            if !rig.contains(c) {
                return Err(TrainError::Data(format!(
                    "{}: no camera sensor with channel `{c}` (the camera channels are: {})",
                    self.tables.dir.join("sensor.json").display(),
                    if rig.is_empty() {
                        "none".to_string()
                    } else {
                        rig.join(", ")
                    }
                )));
            }
        }
        self.channels = channels;
        Ok(())
    }

    /// The key-frame LiDAR and cameras of frame `i`.
    fn cameras_of(&self, i: usize) -> Result<(&SurroundFrame, SampleCameras), TrainError> {
        let f = self
            .frames
            .get(i)
            .ok_or_else(|| TrainError::Data(format!("frame index {i} out of range")))?;
        Ok((
            f,
            self.tables
                .sample_cameras_of(&f.frame.frame, &self.channels)?,
        ))
    }

    /// The cameras (full resolution, label grid's frame) and LiDAR file of frame `i`, exactly as
    /// [`SurroundDataset::load`] uses them before the image augmentation.
    pub fn frame_views(&self, i: usize) -> Result<SurroundFrameViews, TrainError> {
        let (f, cams) = self.cameras_of(i)?;
        Ok(self.views_of(f, &cams))
    }

    fn views_of(&self, f: &SurroundFrame, cams: &SampleCameras) -> SurroundFrameViews {
        let cameras = cams
            .cameras
            .iter()
            .map(|cam| {
                let cam_from_grid = match self.format {
                    DatasetFormat::Occ3d => cam.cam_from_ego_lidar,
                    _ => cam.view.cam_from_lidar,
                };
                SurroundView {
                    channel: cam.channel.clone(),
                    sample_data_token: cam.sample_data_token.clone(),
                    image: self.root.join(&cam.filename),
                    view: CameraView::new(cam.view.camera, cam_from_grid),
                }
            })
            .collect();
        SurroundFrameViews {
            frame: f.frame.clone(),
            cameras,
            lidar: self.root.join(&cams.lidar_filename),
            grid_from_lidar: self
                .grid_from_lidar(cams)
                .unwrap_or_else(occ_geometry::mat4_identity),
        }
    }

    /// Ground-truth file of frame `i` (it may not exist).
    pub fn gt_path(&self, i: usize) -> Result<PathBuf, TrainError> {
        let (f, cams) = self.cameras_of(i)?;
        Ok(self.gt_path_of(f, &cams))
    }

    fn gt_path_of(&self, f: &SurroundFrame, cams: &SampleCameras) -> PathBuf {
        match self.format {
            DatasetFormat::NuscenesOccupancy => self.tables.occupancy_path(&self.gt_root, cams),
            _ => self
                .gt_root
                .join(&f.frame.sequence)
                .join(&f.frame.frame)
                .join("labels.npz"),
        }
    }

    /// `grid_from_lidar`: Occ3D grids live in the ego frame at the LiDAR time, nuScenes-Occupancy
    /// grids in the LiDAR frame.
    fn grid_from_lidar(&self, cams: &SampleCameras) -> Option<Mat4> {
        (self.format == DatasetFormat::Occ3d).then_some(cams.ego_from_lidar)
    }

    /// What [`Self::load`] would refuse in frame `i`, found without decoding it: every camera
    /// image's header against its `sample_data` size. `Err` names the file and the problem.
    pub fn check_frame(&self, i: usize) -> Result<(), TrainError> {
        let (_, cams) = self.cameras_of(i)?;
        for cam in &cams.cameras {
            let path = self.root.join(&cam.filename);
            let (w, h) = (cam.view.camera.width, cam.view.camera.height);
            let (iw, ih) = read_image_size(&path)?;
            if (iw, ih) != (w, h) {
                return Err(TrainError::Data(format!(
                    "{}: image is {iw}x{ih} but its sample_data ({}) says {w}x{h}",
                    path.display(),
                    cam.sample_data_token
                )));
            }
        }
        Ok(())
    }

    /// Loads frame `i`; with `rng`, applies the training augmentation (drawn per camera).
    pub fn load<R: Rng + ?Sized>(
        &self,
        i: usize,
        mut rng: Option<&mut R>,
    ) -> Result<Sample, TrainError> {
        let (f, cams) = self.cameras_of(i)?;
        let views = self.views_of(f, &cams);
        let mut chw = Vec::new();
        let mut cameras = Vec::with_capacity(views.cameras.len());
        let mut size = (0, 0);
        for cam in &views.cameras {
            let path = &cam.image;
            let (w, h) = (cam.view.camera.width, cam.view.camera.height);
            // The header against the tables before decoding.
            let (iw, ih) = read_image_size(path)?;
            if (iw, ih) != (w, h) {
                return Err(TrainError::Data(format!(
                    "{}: image is {iw}x{ih} but its sample_data ({}) says {w}x{h}",
                    path.display(),
                    cam.sample_data_token
                )));
            }
            let img = read_image(path)?;
            if (img.width, img.height) != (w, h) {
                return Err(TrainError::Data(format!(
                    "{}: image is {}x{} but its sample_data ({}) says {w}x{h}",
                    path.display(),
                    img.width,
                    img.height,
                    cam.sample_data_token
                )));
            }
            let aug = match rng.as_deref_mut() {
                Some(r) => self.pipeline.sample_train_aug(img.width, img.height, r),
                None => self.pipeline.test_aug(img.width, img.height),
            };
            let processed = process_image(&img, &aug)?;
            let view = cam.view.augmented(&aug);
            cameras.push(camera_input(&view));
            size = (processed.width, processed.height);
            chw.extend_from_slice(&processed.chw);
        }
        let gt = self.gt_path_of(f, &cams);
        let target = if gt.exists() {
            Some(self.read_target(&gt)?)
        } else {
            None
        };
        let points = if self.load_points && views.lidar.exists() {
            Some(views.read_points()?)
        } else {
            None
        };
        Ok(Sample {
            frame: f.frame.clone(),
            chw,
            size,
            cameras,
            target,
            points,
        })
    }

    /// Training targets from a ground-truth file (see the module docs for the class ids).
    fn read_target(&self, path: &Path) -> Result<Vec<u8>, TrainError> {
        let t = match self.format {
            DatasetFormat::NuscenesOccupancy => nocc::read_sparse_occupancy(path)?,
            _ => {
                let l = occ3d::read_labels_npz(path)?;
                if l.dims != self.grid.dims {
                    return Err(TrainError::Data(format!(
                        "{}: grid {:?}, the dataset's is {:?}",
                        path.display(),
                        l.dims,
                        self.grid.dims
                    )));
                }
                occ3d_training_labels(&l)
            }
        };
        if t.len() != self.grid.num_voxels() {
            return Err(TrainError::Data(format!(
                "{}: {} voxels, the grid {:?} has {}",
                path.display(),
                t.len(),
                self.grid.dims,
                self.grid.num_voxels()
            )));
        }
        Ok(t)
    }
}

/// Occ3D labels to training ids: free (17) -> 0, class `c` -> `c + 1`, outside `mask_camera` -> 255.
pub fn occ3d_training_labels(l: &Occ3dLabels) -> Vec<u8> {
    l.semantics
        .iter()
        .zip(&l.mask_camera)
        .map(|(&s, &m)| match (m, s) {
            (0, _) => IGNORE,
            (_, occ3d::FREE) => EMPTY,
            (_, c) => c + 1,
        })
        .collect()
}

/// Training ids back to Occ3D classes: 0 -> free (17), `k` -> `k - 1` (255 stays invalid).
pub fn occ3d_from_training(classes: &[u8]) -> Vec<u8> {
    classes
        .iter()
        .map(|&k| match k {
            EMPTY => occ3d::FREE,
            IGNORE => IGNORE,
            k => k - 1,
        })
        .collect()
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

/// Camera input of a view (grid frame -> pixels, with the augmentation folded in).
pub fn camera_input(view: &CameraView) -> CameraInput {
    CameraInput {
        img_from_lidar: view.img_from_lidar(),
        cam_from_lidar: view.cam_from_lidar,
    }
}

/// Stacks samples (the same number of cameras each) into a [`Batch`] on `device`.
pub fn collate<B: Backend>(
    samples: &[Sample],
    grid: VoxelGrid,
    device: &B::Device,
) -> Result<Batch<B>, TrainError> {
    let first = samples
        .first()
        .ok_or_else(|| TrainError::Data("empty batch".into()))?;
    let (w, h) = first.size;
    let v = first.cameras.len();
    let mut data = Vec::with_capacity(samples.len() * v * 3 * w * h);
    for s in samples {
        if s.size != (w, h) || s.cameras.len() != v || s.chw.len() != v * 3 * w * h {
            return Err(TrainError::Data(format!(
                "frame {}/{}: {} images of {:?} ({} values) differ from {v} of {:?} in the same batch",
                s.frame.sequence,
                s.frame.frame,
                s.cameras.len(),
                s.size,
                s.chw.len(),
                first.size
            )));
        }
        data.extend_from_slice(&s.chw);
    }
    let images =
        Tensor::<B, 5>::from_data(TensorData::new(data, [samples.len(), v, 3, h, w]), device);
    let target = if samples.iter().all(|s| s.target.is_some()) {
        Some(
            samples
                .iter()
                .map(|s| s.target.clone().unwrap_or_default())
                .collect(),
        )
    } else {
        None
    };
    let points = if samples.iter().all(|s| s.points.is_some()) {
        Some(
            samples
                .iter()
                .map(|s| s.points.clone().unwrap_or_default())
                .collect(),
        )
    } else {
        None
    };
    Ok(Batch {
        images,
        cameras: samples.iter().map(|s| s.cameras.clone()).collect(),
        grid,
        target,
        points,
    })
}
