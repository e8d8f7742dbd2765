//! nuScenes surround layouts ([`SurroundDataset`]: Occ3D and nuScenes-Occupancy): frames from the
//! nuScenes tables, the camera rig, ground-truth paths and targets, and loading a frame.

use super::{camera_input, occ3d_training_labels, DatasetFormat, FrameRef, Sample};
use crate::error::TrainError;
use occ_data::formats::nuscenes_occupancy::{self as nocc, NuscenesTables, SampleCameras};
use occ_data::formats::occ3d;
use occ_data::image::{process_image, read_image, read_image_size, ImagePipelineConfig};
use occ_geometry::VoxelGrid;
use rand::Rng;
use std::path::{Path, PathBuf};

/// One key-frame sample of a nuScenes-layout dataset.
#[derive(Clone, Debug)]
pub(super) struct SurroundFrame {
    /// `sequence` = scene name, `frame` = sample token.
    pub(super) frame: FrameRef,
}

/// A nuScenes-layout dataset (six cameras) with Occ3D or nuScenes-Occupancy ground truth.
#[derive(Clone, Debug)]
pub struct SurroundDataset {
    pub(super) root: PathBuf,
    pub(super) format: DatasetFormat,
    pub(super) tables: std::sync::Arc<NuscenesTables>,
    pub(super) frames: Vec<SurroundFrame>,
    pub(super) refs: Vec<FrameRef>,
    pub(super) grid: VoxelGrid,
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
    pub(super) fn cameras_of(
        &self,
        i: usize,
    ) -> Result<(&SurroundFrame, SampleCameras), TrainError> {
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
