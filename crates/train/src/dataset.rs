//! SemanticKITTI-layout frames (real or synthetic) to model batches.
//!
//! A frame is `image_2/NNNNNN.png` + `calib.txt` (+ `voxels/NNNNNN.label` and `.invalid` for targets,
//! `velodyne/NNNNNN.bin` for depth supervision). Images go through the FACTS.md §1 pipeline (random
//! resize/crop/flip/rotate when training, resize + bottom crop at test time), and the augmentation is
//! folded into each camera's `img_from_lidar`.

use crate::error::TrainError;
use burn::prelude::*;
use burn::tensor::TensorData;
use occ_data::formats::semantic_kitti::{self as sk, KittiPaths};
use occ_data::image::{process_image, read_png, ImagePipelineConfig};
use occ_data::labels::LearningMap;
use occ_geometry::VoxelGrid;
use occ_model::{Batch, CameraInput};
use rand::Rng;
use std::path::{Path, PathBuf};

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
    /// Normalised CHW image.
    pub chw: Vec<f32>,
    /// Network input size (width, height).
    pub size: (usize, usize),
    /// Camera geometry with the augmentation folded in.
    pub camera: CameraInput,
    /// Full-resolution class targets (0..19, 255 ignore; `.invalid` voxels are 255), if labelled.
    pub target: Option<Vec<u8>>,
    /// LiDAR points in the LiDAR frame (metres), if available.
    pub points: Option<Vec<[f32; 3]>>,
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
            for frame in sk::list_stems(&dir, "png")? {
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
        let img = read_png(&img_path)?;
        let calib = sk::read_calib(&self.paths.calib(&f.sequence))?;
        let aug = match rng {
            Some(r) => self.pipeline.sample_train_aug(img.width, img.height, r),
            None => self.pipeline.test_aug(img.width, img.height),
        };
        let processed = process_image(&img, &aug)?;
        let view = calib.camera_view(img.width, img.height).augmented(&aug);
        let camera = CameraInput {
            img_from_lidar: view.img_from_lidar(),
            cam_from_lidar: view.cam_from_lidar,
        };
        let n = self.grid.num_voxels();
        let label_p = self.paths.voxels(&f.sequence, &f.frame, "label");
        let target = if label_p.exists() {
            let mut t = self.map.remap(&sk::read_label_raw(&label_p, n)?);
            let inv_p = self.paths.voxels(&f.sequence, &f.frame, "invalid");
            if inv_p.exists() {
                let inv = sk::read_packed_bits(&inv_p, n)?;
                for (t, &v) in t.iter_mut().zip(&inv) {
                    if v == 1 {
                        *t = 255;
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
            camera,
            target,
            points,
        })
    }
}

/// Stacks samples (one camera each) into a [`Batch`] on `device`.
pub fn collate<B: Backend>(
    samples: &[Sample],
    grid: VoxelGrid,
    device: &B::Device,
) -> Result<Batch<B>, TrainError> {
    let first = samples
        .first()
        .ok_or_else(|| TrainError::Data("empty batch".into()))?;
    let (w, h) = first.size;
    let mut data = Vec::with_capacity(samples.len() * 3 * w * h);
    for s in samples {
        if s.size != (w, h) {
            return Err(TrainError::Data(format!(
                "frame {}/{}: image size {:?} differs from {:?} in the same batch",
                s.frame.sequence, s.frame.frame, s.size, first.size
            )));
        }
        data.extend_from_slice(&s.chw);
    }
    let images =
        Tensor::<B, 5>::from_data(TensorData::new(data, [samples.len(), 1, 3, h, w]), device);
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
        cameras: samples.iter().map(|s| vec![s.camera.clone()]).collect(),
        grid,
        target,
        points,
    })
}
