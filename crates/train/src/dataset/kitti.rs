//! SemanticKITTI layout ([`KittiDataset`]): one front camera per frame, with the checks of its
//! files (image against the calibration, label and point file sizes).

use super::{camera_input, FrameRef, Sample};
use crate::error::TrainError;
use occ_data::formats::semantic_kitti::{self as sk, KittiPaths};
use occ_data::image::{process_image, read_image, read_image_size, ImagePipelineConfig};
use occ_data::labels::LearningMap;
use occ_geometry::VoxelGrid;
use occ_labels::IGNORE;
use rand::Rng;
use std::path::{Path, PathBuf};

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
    pub(super) root: PathBuf,
    pub(super) paths: KittiPaths,
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
    /// calibration, the image header (size limit, against the calibration) and the image file
    /// whole, a labelled frame's `.invalid` mask present, and the sizes of the label, `.invalid`
    /// and (with `load_points`) velodyne files. `Err` names the file and the problem.
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
            // The mask of the voxels no scan observed belongs to the labels: without it they would
            // train as empty. Scoring and `prepare` need it too.
            let inv_p = self.paths.voxels(&f.sequence, &f.frame, "invalid");
            if !inv_p.exists() {
                return Err(TrainError::Data(format!(
                    "{}: missing; a labelled frame needs its mask of unobserved voxels next to {}",
                    inv_p.display(),
                    label_p.display()
                )));
            }
            check_file_len(&inv_p, n.div_ceil(8), "bit-packed voxel mask")?;
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
            let inv = sk::read_packed_bits(&inv_p, n)?;
            for (t, &v) in t.iter_mut().zip(&inv) {
                if v == 1 {
                    *t = IGNORE;
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
