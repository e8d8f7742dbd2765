//! Inference: a trained [`OccNet`] over dataset frames or a single camera image, to full-resolution
//! class grids written in the dataset's own layout (SemanticKITTI submission `.label`, Occ3D
//! `labels.npz`, nuScenes-Occupancy sparse `.npy`).

use crate::dataset::{
    camera_input, check_image_fits_calibration, collate, Dataset, FrameRef, Sample,
};
use crate::mirror::mirror_sample_y;
use crate::TrainError;
use occ_data::formats::semantic_kitti as sk;
use occ_data::image::{process_image, read_image, read_image_size, ImagePipelineConfig, RgbImage};
use occ_geometry::VoxelGrid;
use occ_model::ModelBackend;
use occ_model::OccNet;
use std::path::{Path, PathBuf};
use std::time::Instant;

/// One frame's prediction.
#[derive(Clone, Debug)]
pub struct Prediction {
    /// Full-resolution classes (learning ids, 0 = empty), flat `[X][Y][Z]`.
    pub classes: Vec<u8>,
    /// Seconds for the forward pass (image tensor to class grid; image loading excluded).
    pub seconds: f64,
    /// Active voxels per stage.
    pub stats: Vec<(String, usize)>,
}

/// Runs the model on one sample (its targets, if any, are not used).
///
/// With `test_mirror`, test-time mirror augmentation: the model also sees the sample mirrored across
/// the grid's x-z centre plane ([`mirror_sample_y`]: image flipped, cameras re-folded), its class
/// probabilities are mirrored back, and the class of each voxel is the argmax of the mean of the
/// two (the test-time counterpart of the `data.mirror_prob` training augmentation; twice the forward
/// time).
pub fn predict_sample<B: ModelBackend>(
    model: &OccNet<B>,
    sample: &Sample,
    grid: VoxelGrid,
    device: &B::Device,
    test_mirror: bool,
) -> Result<Prediction, TrainError> {
    let t0 = Instant::now();
    let forward = |s: &Sample| -> Result<occ_model::ModelOutput<B>, TrainError> {
        let mut batch = collate::<B>(std::slice::from_ref(s), grid, device)?;
        batch.target = None;
        Ok(model.forward(&batch)?)
    };
    let out = forward(sample)?;
    if !test_mirror {
        let classes = out
            .dense_prediction(1, grid.dims)
            .into_iter()
            .next()
            .unwrap_or_default();
        return Ok(Prediction {
            classes,
            seconds: t0.elapsed().as_secs_f64(),
            stats: out.stats,
        });
    }
    let mut mirrored = Sample {
        target: None,
        ..sample.clone()
    };
    mirror_sample_y(&mut mirrored, &grid)?;
    let out_m = forward(&mirrored)?;
    let probs = out
        .dense_probabilities(1, grid.dims)
        .pop()
        .unwrap_or_default();
    let probs_m = out_m
        .dense_probabilities(1, grid.dims)
        .pop()
        .unwrap_or_default();
    let classes = mean_of_mirrored_argmax(&probs, &probs_m, grid.dims).ok_or_else(|| {
        TrainError::Data(format!(
            "frame {}/{}: test-time mirror: {} and {} class probabilities for the grid {:?}",
            sample.frame.sequence,
            sample.frame.frame,
            probs.len(),
            probs_m.len(),
            grid.dims
        ))
    })?;
    let mut stats = out.stats;
    stats.extend(
        out_m
            .stats
            .into_iter()
            .map(|(k, v)| (format!("{k} (mirrored)"), v)),
    );
    Ok(Prediction {
        classes,
        seconds: t0.elapsed().as_secs_f64(),
        stats,
    })
}

/// Class of every voxel of `dims` from the mean of `probs` (`[X][Y][Z][C]`) and `probs_mirrored`,
/// the probabilities of the mirrored scene (voxel column `y` of it is column `Y - 1 - y` of the
/// scene), as [`occ_model::ModelOutput::dense_probabilities`] gives them: a voxel that one pass did
/// not predict has an all-zero row there, so it takes the other pass's classes (the mean over the
/// passes that predicted it), and one that neither predicted is empty. `None` if the two are not
/// `X·Y·Z·C` values for the same `C`.
pub fn mean_of_mirrored_argmax(
    probs: &[f32],
    probs_mirrored: &[f32],
    dims: [usize; 3],
) -> Option<Vec<u8>> {
    let [nx, ny, nz] = dims;
    let n = nx * ny * nz;
    if n == 0 || probs.len() != probs_mirrored.len() || !probs.len().is_multiple_of(n) {
        return None;
    }
    let c = probs.len() / n;
    if c == 0 || c > 256 {
        return None;
    }
    let mut classes = vec![0u8; n];
    for x in 0..nx {
        for y in 0..ny {
            for z in 0..nz {
                let v = (x * ny + y) * nz + z;
                let vm = (x * ny + (ny - 1 - y)) * nz + z;
                let (a, b) = (
                    &probs[v * c..(v + 1) * c],
                    &probs_mirrored[vm * c..(vm + 1) * c],
                );
                let mut best = 0;
                let mut best_p = f32::NEG_INFINITY;
                for k in 0..c {
                    let p = a[k] + b[k];
                    if p > best_p {
                        best_p = p;
                        best = k;
                    }
                }
                classes[v] = best as u8;
            }
        }
    }
    Some(classes)
}

/// Predicts every frame of `ds` and writes each below `out_root` in the dataset's layout
/// ([`Dataset::write_prediction`]: SemanticKITTI `sequences/XX/predictions/NNNNNN.label`, Occ3D
/// `<scene>/<token>/labels.npz`, nuScenes-Occupancy `scene_<token>/occupancy/<lidar token>.npy`;
/// atomically), with test-time mirror averaging when `test_mirror` ([`predict_sample`]).
/// `on_frame(done, total, &frame, &prediction)` reports progress. Returns the files
/// written with their forward times.
pub fn predict_dataset<B: ModelBackend>(
    model: &OccNet<B>,
    ds: &Dataset,
    out_root: &Path,
    device: &B::Device,
    test_mirror: bool,
    on_frame: &mut dyn FnMut(usize, usize, &FrameRef, &Prediction),
) -> Result<Vec<(PathBuf, f64)>, TrainError> {
    let mut written = Vec::with_capacity(ds.len());
    for i in 0..ds.len() {
        let sample = ds.load::<rand_chacha::ChaCha8Rng>(i, None)?;
        let pred = predict_sample(model, &sample, ds.grid(), device, test_mirror)?;
        let path = ds.write_prediction(out_root, i, &pred.classes)?;
        on_frame(i + 1, ds.len(), &sample.frame, &pred);
        written.push((path, pred.seconds));
    }
    Ok(written)
}

/// Loads one camera image (PNG or JPEG) with its KITTI-format calibration (`P2`, `Tr`) as a
/// test-time sample ([`sample_from_image`]).
///
/// The image may have any size; it goes through the test-time pipeline (resize to the network
/// width, bottom crop), and the calibration is adjusted accordingly. An image whose size does not
/// fit the calibration (principal point outside the central half of the image) is an error.
pub fn load_single_image(
    image: &Path,
    calib: &Path,
    pipeline: &ImagePipelineConfig,
) -> Result<Sample, TrainError> {
    let cal = sk::read_calib(calib)?;
    // The header against the calibration (and the size limit) before decoding.
    let (w, h) = read_image_size(image)?;
    check_image_fits_calibration(image, w, h, calib, &cal)?;
    let img = read_image(image)?;
    let stem = image
        .file_stem()
        .map(|s| s.to_string_lossy().into_owned())
        .unwrap_or_else(|| "image".into());
    sample_from_image(&img, &cal, pipeline, &stem)
}

/// A decoded camera image with its calibration as a test-time sample named `name`: the image goes
/// through the test-time pipeline (resize to the network width, bottom crop), and the calibration
/// is adjusted accordingly. An image whose size does not fit the calibration (principal point
/// outside the central half of the image) is an error naming `name`.
pub fn sample_from_image(
    img: &RgbImage,
    cal: &sk::Calib,
    pipeline: &ImagePipelineConfig,
    name: &str,
) -> Result<Sample, TrainError> {
    check_image_fits_calibration(
        Path::new(name),
        img.width,
        img.height,
        Path::new("(the calibration given)"),
        cal,
    )?;
    let aug = pipeline.test_aug(img.width, img.height);
    let processed = process_image(img, &aug)?;
    let view = cal.camera_view(img.width, img.height).augmented(&aug);
    Ok(Sample {
        frame: FrameRef {
            sequence: String::new(),
            frame: name.to_string(),
        },
        chw: processed.chw,
        size: (processed.width, processed.height),
        cameras: vec![camera_input(&view)],
        target: None,
        points: None,
    })
}

/// Predicts one frame of a dataset: `sequence` (a nuScenes-layout scene name) and `frame` (its
/// frame stem, or sample token) below `root`, in the layout `data.format`, with the LiDAR points
/// loaded when the model needs them at test time. The dataset's grid must be the model's.
#[allow(clippy::too_many_arguments)]
pub fn predict_dataset_frame<B: ModelBackend>(
    model: &OccNet<B>,
    data: &crate::config::DataConfig,
    needs_points: bool,
    root: &Path,
    sequence: &str,
    frame: &str,
    grid: VoxelGrid,
    device: &B::Device,
    test_mirror: bool,
) -> Result<Prediction, TrainError> {
    let mut ds = Dataset::open(root, data, &[sequence.to_string()], &[])?;
    ds.set_load_points(needs_points);
    if ds.grid().dims != grid.dims {
        return Err(TrainError::Data(format!(
            "{}: dataset grid {:?} but the model predicts {:?}",
            root.display(),
            ds.grid().dims,
            grid.dims
        )));
    }
    let Some(i) = ds.frames().iter().position(|f| f.frame == frame) else {
        let first: Vec<&str> = ds
            .frames()
            .iter()
            .take(3)
            .map(|f| f.frame.as_str())
            .collect();
        return Err(TrainError::Data(format!(
            "{}: sequence {sequence} has no frame {frame} ({} frames, e.g. {first:?})",
            root.display(),
            ds.len()
        )));
    };
    let sample = ds.load::<rand_chacha::ChaCha8Rng>(i, None)?;
    predict_sample(model, &sample, grid, device, test_mirror)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn mirrored_probabilities_are_mirrored_back_before_the_mean() {
        // Grid 1 x 3 x 1, two classes. Column y of the mirrored scene is column 2 - y of the scene.
        let probs = [0.9, 0.1, 0.4, 0.6, 0.5, 0.5];
        let probs_m = [0.2, 0.8, 0.9, 0.1, 0.0, 1.0];
        let c = mean_of_mirrored_argmax(&probs, &probs_m, [1, 3, 1]).unwrap();
        // y = 0 pairs with mirrored y = 2: (0.9 + 0.0, 0.1 + 1.0) -> class 1;
        // y = 1 with mirrored y = 1: (0.4 + 0.9, 0.6 + 0.1) -> class 0;
        // y = 2 with mirrored y = 0: (0.5 + 0.2, 0.5 + 0.8) -> class 1.
        assert_eq!(c, vec![1, 0, 1]);
        // A voxel predicted by one pass only (an all-zero row in the other) keeps that pass's
        // class even when it is not sure of it; one predicted by neither is empty.
        let probs = [0.4, 0.6, 0.0, 0.0, 0.0, 0.0];
        let probs_m = [0.3, 0.7, 0.0, 0.0, 0.0, 0.0];
        // y = 0: (0.4, 0.6) + mirrored y = 2 (0, 0) -> 1; y = 1: nothing -> 0; y = 2: (0, 0) +
        // mirrored y = 0 (0.3, 0.7) -> 1.
        let c = mean_of_mirrored_argmax(&probs, &probs_m, [1, 3, 1]).unwrap();
        assert_eq!(c, vec![1, 0, 1]);
        assert!(mean_of_mirrored_argmax(&probs, &probs_m[..4], [1, 3, 1]).is_none());
        assert!(mean_of_mirrored_argmax(&probs, &probs_m, [1, 4, 1]).is_none());
    }
}
