//! The model input: multi-view images, camera geometry, voxel grid, optional targets.

use burn::prelude::*;
use occ_geometry::{Mat4, VoxelGrid};

/// One camera of one sample.
#[derive(Clone, Debug)]
pub struct CameraInput {
    /// Pixel coordinates of the NETWORK INPUT image (after resize/crop/flip/rotate) from LiDAR-frame
    /// points in metres: `[u*d, v*d, d, 1] = img_from_lidar * [x, y, z, 1]`.
    pub img_from_lidar: Mat4,
    /// Camera frame from LiDAR frame (metres), for depth and camera-parameter conditioning.
    pub cam_from_lidar: Mat4,
}

/// A batch of samples.
#[derive(Clone, Debug)]
pub struct Batch<B: Backend> {
    /// ImageNet-normalised images `[B, V, 3, H, W]`.
    pub images: Tensor<B, 5>,
    /// `cameras[b][v]` for batch item `b`, view `v`.
    pub cameras: Vec<Vec<CameraInput>>,
    /// The full-resolution label grid (e.g. SemanticKITTI 256x256x32 at 0.2 m).
    pub grid: VoxelGrid,
    /// Full-resolution targets per item, `grid.num_voxels()` class ids (0 = empty, 255 = ignore).
    pub target: Option<Vec<Vec<u8>>>,
    /// LiDAR points per item (LiDAR frame, metres) for depth supervision, if available.
    pub points: Option<Vec<Vec<[f32; 3]>>>,
}

impl<B: Backend> Batch<B> {
    /// Batch size.
    pub fn batch_size(&self) -> usize {
        self.images.dims()[0]
    }
    /// Number of views.
    pub fn num_views(&self) -> usize {
        self.images.dims()[1]
    }
    /// Input image height and width.
    pub fn image_hw(&self) -> (usize, usize) {
        let d = self.images.dims();
        (d[3], d[4])
    }
}
