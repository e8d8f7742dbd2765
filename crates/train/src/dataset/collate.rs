//! Samples to model inputs: a camera's [`CameraInput`] and a batch of samples stacked into a
//! [`Batch`] of burn tensors.

use super::Sample;
use crate::error::TrainError;
use burn::prelude::*;
use burn::tensor::TensorData;
use occ_geometry::{CameraView, VoxelGrid};
use occ_model::{Batch, CameraInput};

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
