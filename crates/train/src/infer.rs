//! Inference: a trained [`OccNet`] over dataset frames or a single camera image, to full-resolution
//! class grids written in the dataset's own layout (SemanticKITTI submission `.label`, Occ3D
//! `labels.npz`, nuScenes-Occupancy sparse `.npy`).

use crate::dataset::{camera_input, collate, Dataset, FrameRef, Sample};
use crate::TrainError;
use occ_data::formats::semantic_kitti as sk;
use occ_data::image::{process_image, read_image, ImagePipelineConfig};
use occ_geometry::VoxelGrid;
use occ_model::OccNet;
use occ_sparse::SparseConvBackend;
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
pub fn predict_sample<B: SparseConvBackend>(
    model: &OccNet<B>,
    sample: &Sample,
    grid: VoxelGrid,
    device: &B::Device,
) -> Result<Prediction, TrainError> {
    let t0 = Instant::now();
    let mut batch = collate::<B>(std::slice::from_ref(sample), grid, device)?;
    batch.target = None;
    batch.points = None;
    let out = model.forward(&batch)?;
    let classes = out
        .dense_prediction(1, grid.dims)
        .into_iter()
        .next()
        .unwrap_or_default();
    Ok(Prediction {
        classes,
        seconds: t0.elapsed().as_secs_f64(),
        stats: out.stats,
    })
}

/// Predicts every frame of `ds` and writes each below `out_root` in the dataset's layout
/// ([`Dataset::write_prediction`]: SemanticKITTI `sequences/XX/predictions/NNNNNN.label`, Occ3D
/// `<scene>/<token>/labels.npz`, nuScenes-Occupancy `scene_<token>/occupancy/<lidar token>.npy`;
/// atomically). `on_frame(done, total, &frame, &prediction)` reports progress. Returns the files
/// written with their forward times.
pub fn predict_dataset<B: SparseConvBackend>(
    model: &OccNet<B>,
    ds: &Dataset,
    out_root: &Path,
    device: &B::Device,
    on_frame: &mut dyn FnMut(usize, usize, &FrameRef, &Prediction),
) -> Result<Vec<(PathBuf, f64)>, TrainError> {
    let mut written = Vec::with_capacity(ds.len());
    for i in 0..ds.len() {
        let sample = ds.load::<rand_chacha::ChaCha8Rng>(i, None)?;
        let pred = predict_sample(model, &sample, ds.grid(), device)?;
        let path = ds.write_prediction(out_root, i, &pred.classes)?;
        on_frame(i + 1, ds.len(), &sample.frame, &pred);
        written.push((path, pred.seconds));
    }
    Ok(written)
}

/// Loads one camera image (PNG or JPEG) with its KITTI-format calibration (`P2`, `Tr`) as a
/// test-time sample.
///
/// The image may have any size; it goes through the test-time pipeline (resize to the network
/// width, bottom crop), and the calibration is adjusted accordingly. An image whose size does not
/// fit the calibration (principal point outside the central half of the image) is an error.
pub fn load_single_image(
    image: &Path,
    calib: &Path,
    pipeline: &ImagePipelineConfig,
) -> Result<Sample, TrainError> {
    let img = read_image(image)?;
    let cal = sk::read_calib(calib)?;
    let (cx, cy) = (cal.p2[0][2], cal.p2[1][2]);
    let (w, h) = (img.width as f64, img.height as f64);
    if !(cx > 0.25 * w && cx < 0.75 * w && cy > 0.25 * h && cy < 0.75 * h) {
        return Err(TrainError::Data(format!(
            "{}: image is {}x{} but the calibration {} puts the principal point at ({cx:.1}, {cy:.1}); \
             the image does not belong to this calibration (or was resized without adjusting P2)",
            image.display(),
            img.width,
            img.height,
            calib.display()
        )));
    }
    let aug = pipeline.test_aug(img.width, img.height);
    let processed = process_image(&img, &aug)?;
    let view = cal.camera_view(img.width, img.height).augmented(&aug);
    let stem = image
        .file_stem()
        .map(|s| s.to_string_lossy().into_owned())
        .unwrap_or_else(|| "image".into());
    Ok(Sample {
        frame: FrameRef {
            sequence: String::new(),
            frame: stem,
        },
        chw: processed.chw,
        size: (processed.width, processed.height),
        cameras: vec![camera_input(&view)],
        target: None,
        points: None,
    })
}
