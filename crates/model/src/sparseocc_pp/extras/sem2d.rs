//! Auxiliary image semantics (NOT in the SparseOcc++ paper; an option of [`crate::sparseocc_pp`],
//! off in the paper configs).
//!
//! Why: the paper starts from an ImageNet-pretrained backbone and trains for 24 epochs; the image
//! features it samples with deformable cross attention already separate surfaces by class. A short
//! run from a random backbone (the `sparseocc demo`) only teaches the image encoder through the 3D
//! losses, back through the DCA samples, and the demo's model ended up level with a per-voxel prior:
//! it confused the ground classes with each other although each has its own colour, and predicted
//! every object as empty. Per-pixel semantic supervision of the perspective features is the
//! usual remedy in camera occupancy work (e.g. FB-OCC's joint depth and semantic pre-training of the
//! image encoder); this module is its light form:
//!
//! 1. A head (3×3 conv `C → C`, ReLU, 1×1 conv `C → K`) on the finest image feature level predicts
//!    class logits per feature pixel.
//! 2. Its targets come from data every training set here already has, the LiDAR scan and the voxel
//!    labels: each point is projected into each view; a feature pixel takes the class of the voxel
//!    holding its nearest point (camera depth) among the points whose voxel is occupied and
//!    labelled (class 0 = empty and 255 = ignore are skipped). Pixels without such a point are
//!    ignored.
//! 3. The loss is the class-weighted cross-entropy of [`crate::loss::cross_entropy_weighted`] (ignore 255).
//!
//! The head's output is not used by the 3D network: its only effect is the gradient it sends into
//! the image encoder.
//!
//! Measured on `sparseocc demo` (BENCHMARKS.md, "image semantic head"): the head learns the 2D
//! classes within 100 steps, but the held-out 3D mIoU does not change (0.102 / 0.084 against 0.105 /
//! 0.072 without it, seeds 0 / 1), so `configs/synthetic_tiny.toml` leaves it off.

use crate::batch::Batch;
use crate::error::ModelError;
use crate::loss::cross_entropy_weighted;
use crate::lss::feature_pixel_of_point;
use burn::nn::conv::{Conv2d, Conv2dConfig};
use burn::nn::PaddingConfig2d;
use burn::prelude::*;
use occ_labels::{is_occupied, IGNORE};

/// Configuration of [`Sem2dHead`].
#[derive(Config, Debug)]
pub struct Sem2dHeadConfig {
    /// Channels of the image features it reads.
    pub in_channels: usize,
    /// Classes including empty (class 0 is never a target).
    pub num_classes: usize,
}

impl Sem2dHeadConfig {
    /// Checks sizes.
    pub fn validate(&self) -> Result<(), ModelError> {
        if self.in_channels == 0 || self.num_classes < 2 {
            return Err(ModelError::Config(format!(
                "image semantic head: need in_channels > 0 and num_classes >= 2, got {} / {}",
                self.in_channels, self.num_classes
            )));
        }
        Ok(())
    }

    /// Initialises the head.
    pub fn init<B: Backend>(&self, device: &B::Device) -> Sem2dHead<B> {
        let c = self.in_channels.max(1);
        Sem2dHead {
            conv1: Conv2dConfig::new([c, c], [3, 3])
                .with_padding(PaddingConfig2d::Explicit(1, 1, 1, 1))
                .init(device),
            conv2: Conv2dConfig::new([c, self.num_classes.max(1)], [1, 1]).init(device),
        }
    }
}

/// The image semantic head (see the module docs).
#[derive(Module, Debug)]
pub struct Sem2dHead<B: Backend> {
    /// 3×3 `C → C`.
    pub conv1: Conv2d<B>,
    /// 1×1 `C → K`.
    pub conv2: Conv2d<B>,
}

/// Class logits of one feature level.
#[derive(Clone, Debug)]
pub struct Sem2dMap<B: Backend> {
    /// Logits `[B·V, K, h, w]`.
    pub logits: Tensor<B, 4>,
    /// Input pixels per feature pixel.
    pub stride: usize,
}

impl<B: crate::kernels::ModelBackend> Sem2dHead<B> {
    /// # Shapes
    /// - feat: `[B·V, C, h, w]` → logits `[B·V, K, h, w]`
    pub fn forward(&self, feat: Tensor<B, 4>, stride: usize) -> Sem2dMap<B> {
        Sem2dMap {
            logits: crate::kernels::conv2d_host::conv_bn(
                &self.conv2,
                None,
                crate::kernels::conv2d_host::conv_bn(&self.conv1, None, feat, true),
                false,
            ),
            stride: stride.max(1),
        }
    }
}

impl<B: Backend> Sem2dMap<B> {
    /// Class-weighted CE against [`sem2d_targets`]; `None` when the batch has no points or no
    /// targets, or no pixel got a label.
    pub fn loss(
        &self,
        batch: &Batch<B>,
        class_weights: &[f64],
    ) -> Result<Option<Tensor<B, 1>>, ModelError> {
        let [n, k, h, w] = self.logits.dims();
        let Some(t) = sem2d_targets(batch, h, w, self.stride)? else {
            return Ok(None);
        };
        if t.len() != n * h * w {
            return Err(ModelError::Input(format!(
                "sem2d.rs: {} targets for logits [{n}, {k}, {h}, {w}]",
                t.len()
            )));
        }
        if t.iter().all(|&l| l == IGNORE) {
            return Ok(None);
        }
        let rows = self
            .logits
            .clone()
            .permute([0, 2, 3, 1])
            .reshape([n * h * w, k]);
        cross_entropy_weighted(rows, &t, class_weights, IGNORE).map(Some)
    }
}

/// Per-pixel class targets `[B·V, h, w]` (row-major, 255 = no label) of a feature map with
/// `stride` input pixels per pixel: the class of the voxel of the nearest (camera depth) LiDAR point
/// projecting into the pixel (rounded, as [`crate::lss::depth_targets`]) whose voxel is labelled and occupied. `None` without points or targets.
pub fn sem2d_targets<B: Backend>(
    batch: &Batch<B>,
    h: usize,
    w: usize,
    stride: usize,
) -> Result<Option<Vec<u8>>, ModelError> {
    let (Some(points), Some(targets)) = (&batch.points, &batch.target) else {
        return Ok(None);
    };
    let (b, v) = (batch.batch_size(), batch.num_views());
    if points.len() != b || targets.len() != b || batch.cameras.len() != b {
        return Err(ModelError::Input(format!(
            "sem2d.rs: batch of {b} with {} point sets, {} targets, {} camera sets",
            points.len(),
            targets.len(),
            batch.cameras.len()
        )));
    }
    let grid = batch.grid;
    let img_hw = batch.image_hw();
    let mut best = vec![(f64::INFINITY, IGNORE); b * v * h * w];
    for (bi, (pts, target)) in points.iter().zip(targets).enumerate() {
        if target.len() != grid.num_voxels() {
            return Err(ModelError::Input(format!(
                "sem2d.rs: item {bi} has {} targets for a grid of {} voxels",
                target.len(),
                grid.num_voxels()
            )));
        }
        if batch.cameras[bi].len() != v {
            return Err(ModelError::Input(format!(
                "sem2d.rs: item {bi} has {} cameras for {v} views",
                batch.cameras[bi].len()
            )));
        }
        // Labels of the points first: most points are outside the grid or in unlabelled voxels.
        let labelled: Vec<([f64; 3], u8)> = pts
            .iter()
            .filter_map(|p| {
                let p = [p[0] as f64, p[1] as f64, p[2] as f64];
                let ijk = grid.voxel_of_point_m(p)?;
                let l = target[grid.linear_index(ijk)];
                is_occupied(l).then_some((p, l))
            })
            .collect();
        for (vi, cam) in batch.cameras[bi].iter().enumerate() {
            let m = cam.img_from_lidar;
            let base = (bi * v + vi) * h * w;
            for &(p, l) in &labelled {
                if let Some((cell, depth)) = feature_pixel_of_point(&m, p, img_hw, (h, w), stride) {
                    let c = &mut best[base + cell];
                    if depth < c.0 {
                        *c = (depth, l);
                    }
                }
            }
        }
    }
    Ok(Some(best.into_iter().map(|(_, l)| l).collect()))
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::batch::CameraInput;
    use burn::backend::NdArray;
    use occ_geometry::VoxelGrid;

    type B = NdArray<f32>;

    /// A 4x4 image looking down +x: a pinhole with f = 2 px and the principal point at (2, 2)
    /// (`u = 2 − 2y/x`, `v = 2 − 2z/x`, depth = x).
    fn camera() -> CameraInput {
        // Camera axes: z_cam = x, x_cam = -y, y_cam = -z.
        let f = 2.0;
        let m = [
            [2.0, -f, 0.0, 0.0],
            [2.0, 0.0, -f, 0.0],
            [1.0, 0.0, 0.0, 0.0],
            [0.0, 0.0, 0.0, 1.0],
        ];
        CameraInput {
            img_from_lidar: m,
            cam_from_lidar: m,
        }
    }

    #[test]
    fn each_pixel_takes_the_class_of_its_nearest_labelled_point() {
        let device = Default::default();
        let grid = VoxelGrid {
            origin_m: [0.0, -4.0, -4.0],
            voxel_size_m: 1.0,
            dims: [8, 8, 8],
        };
        let mut target = vec![0u8; grid.num_voxels()];
        let mut set = |p: [f64; 3], l: u8| {
            let ijk = grid.voxel_of_point_m(p).unwrap();
            target[grid.linear_index(ijk)] = l;
        };
        // On the optical axis (pixel (2, 2)): class 3 at 6.5 m behind class 5 at 4.5 m, and an
        // unlabelled point at 2.5 m (empty voxel) that must be skipped.
        set([6.5, 0.0, 0.0], 3);
        set([4.5, 0.0, 0.0], 5);
        // Up-left of the axis (pixel (1, 1)): only an ignored voxel.
        set([4.5, 1.5, 1.5], IGNORE);
        let points = vec![vec![
            [6.5f32, 0.0, 0.0],
            [4.5, 0.0, 0.0],
            [2.5, 0.0, 0.0],
            [4.5, 1.5, 1.5],
            [-3.0, 0.0, 0.0], // behind the camera
        ]];
        let batch = Batch::<B> {
            images: Tensor::zeros([1, 1, 3, 4, 4], &device),
            cameras: vec![vec![camera()]],
            grid,
            target: Some(vec![target]),
            points: Some(points),
        };
        let t = sem2d_targets(&batch, 4, 4, 1).unwrap().unwrap();
        let mut expected = vec![IGNORE; 16];
        expected[2 * 4 + 2] = 5;
        assert_eq!(t, expected);
        // At stride 2 the same point lands in feature pixel (1, 1).
        let t2 = sem2d_targets(&batch, 2, 2, 2).unwrap().unwrap();
        assert_eq!(t2, vec![IGNORE, IGNORE, IGNORE, 5]);
        // No points: no targets.
        let mut nopts = batch.clone();
        nopts.points = None;
        assert!(sem2d_targets(&nopts, 4, 4, 1).unwrap().is_none());
    }

    #[test]
    fn the_loss_trains_the_head_towards_the_projected_class() {
        let device = Default::default();
        type A = burn::backend::Autodiff<B>;
        let grid = VoxelGrid {
            origin_m: [0.0, -4.0, -4.0],
            voxel_size_m: 1.0,
            dims: [8, 8, 8],
        };
        let mut target = vec![0u8; grid.num_voxels()];
        let ijk = grid.voxel_of_point_m([4.5, 0.0, 0.0]).unwrap();
        target[grid.linear_index(ijk)] = 2;
        let batch = Batch::<A> {
            images: Tensor::zeros([1, 1, 3, 4, 4], &device),
            cameras: vec![vec![camera()]],
            grid,
            target: Some(vec![target]),
            points: Some(vec![vec![[4.5, 0.0, 0.0]]]),
        };
        let head = Sem2dHeadConfig::new(3, 4).init::<A>(&device);
        let feat = Tensor::<A, 4>::ones([1, 3, 4, 4], &device);
        let map = head.forward(feat, 1);
        let loss = map.loss(&batch, &[1.0; 4]).unwrap().unwrap();
        // CE of one pixel equals −log softmax at class 2 of that pixel's logits.
        let px: Vec<f32> = map
            .logits
            .clone()
            .slice([0..1, 0..4, 2..3, 2..3])
            .reshape([4])
            .into_data()
            .to_vec()
            .unwrap();
        let mx = px.iter().cloned().fold(f32::NEG_INFINITY, f32::max);
        let lse = mx + px.iter().map(|v| (v - mx).exp()).sum::<f32>().ln();
        let want = lse - px[2];
        let got: f32 = loss.clone().into_scalar();
        assert!((got - want).abs() < 1e-5, "loss {got} vs {want}");
        // The labelled pixel's logits get the gradient softmax − onehot, so the output bias gets
        // exactly that (the weights may get none where the ReLU is off for this constant input).
        let grads = loss.backward();
        let gb: Vec<f32> = head
            .conv2
            .bias
            .as_ref()
            .unwrap()
            .grad(&grads)
            .unwrap()
            .into_data()
            .to_vec()
            .unwrap();
        for (c, g) in gb.iter().enumerate() {
            let p = (px[c] - lse).exp();
            let want = if c == 2 { p - 1.0 } else { p };
            assert!(
                (g - want).abs() < 1e-5,
                "class {c}: bias grad {g} vs {want}"
            );
        }
    }
}
