//! Depth oracle: a DIAGNOSTIC, not a model component (NOT in the SparseOcc++ paper, and it needs the
//! LiDAR scan at test time, so it is no camera-only model). It answers one question: if every DCA
//! sample knew whether its voxel lies at the depth of the surface its reference pixel shows, would the
//! rest of SparseOcc++ (anchor scoring, SCF, propagation, U-Net, head) find the objects? If it does,
//! the 3D part works and the missing depth signal of the image features is the bottleneck.
//!
//! The surface depth of a pixel is the smallest depth along the optical axis of the LiDAR points
//! whose rounded pixel is within `radius` pixels (a min over a square window: the LiDAR is not
//! dense in the image). The gate of a (voxel, view) hit with voxel centre depth `d`, voxel size `s`
//! and surface depth `d_s` is `clamp(1.75 - |d - d_s| / s, 0, 1)`: 1 when the surface is within
//! 3/4 of a voxel of its centre, 0 one voxel further away; 1 where no point is near (no evidence).
//! DCA multiplies each hit's sampled features by it, like the learned [`crate::sparseocc_pp::extras::depth_gate`].

use crate::batch::Batch;
use crate::error::ModelError;
use crate::sparseocc_pp::dca::ViewHits;
use burn::prelude::*;
use burn::tensor::TensorData;

/// Window half-size (input pixels) of the surface-depth min filter.
const RADIUS_PX: i64 = 1;

/// Surface depth per input pixel of every image of a batch.
#[derive(Clone, Debug)]
pub struct DepthOracle {
    /// `[B·V][H·W]` depths (m), `f32::INFINITY` where no point is near.
    depth: Vec<Vec<f32>>,
    hw: (usize, usize),
}

impl DepthOracle {
    /// From the batch's LiDAR points (`None` when it has none).
    pub fn from_batch<B: Backend>(batch: &Batch<B>) -> Result<Option<Self>, ModelError> {
        let Some(points) = &batch.points else {
            return Ok(None);
        };
        let (b, v) = (batch.batch_size(), batch.num_views());
        if points.len() != b || batch.cameras.len() != b {
            return Err(ModelError::Input(format!(
                "depth oracle: {} point sets and {} camera sets for a batch of {b}",
                points.len(),
                batch.cameras.len()
            )));
        }
        let (h, w) = batch.image_hw();
        let mut depth = Vec::with_capacity(b * v);
        for (bi, pts) in points.iter().enumerate() {
            for cam in &batch.cameras[bi] {
                let m = cam.img_from_lidar;
                let mut raw = vec![f32::INFINITY; h * w];
                for p in pts {
                    let p = [p[0] as f64, p[1] as f64, p[2] as f64];
                    let q: [f64; 3] = std::array::from_fn(|r| {
                        m[r][0] * p[0] + m[r][1] * p[1] + m[r][2] * p[2] + m[r][3]
                    });
                    if !(q[2].is_finite() && q[2] > 1e-6) {
                        continue;
                    }
                    let (u, vv) = ((q[0] / q[2]).round(), (q[1] / q[2]).round());
                    if u >= 0.0 && vv >= 0.0 && u < w as f64 && vv < h as f64 {
                        let c = &mut raw[vv as usize * w + u as usize];
                        *c = c.min(q[2] as f32);
                    }
                }
                let mut out = vec![f32::INFINITY; h * w];
                for y in 0..h as i64 {
                    for x in 0..w as i64 {
                        let mut best = f32::INFINITY;
                        for yy in (y - RADIUS_PX).max(0)..=(y + RADIUS_PX).min(h as i64 - 1) {
                            for xx in (x - RADIUS_PX).max(0)..=(x + RADIUS_PX).min(w as i64 - 1) {
                                best = best.min(raw[yy as usize * w + xx as usize]);
                            }
                        }
                        out[y as usize * w + x as usize] = best;
                    }
                }
                depth.push(out);
            }
        }
        Ok(Some(DepthOracle { depth, hw: (h, w) }))
    }

    /// The gate of every hit `[nh]` (module docs) for voxels of size `voxel_m`.
    pub fn hit_gate<B: Backend>(
        &self,
        hits: &ViewHits,
        voxel_m: f64,
        device: &B::Device,
    ) -> Result<Tensor<B, 1>, ModelError> {
        if hits.num_images != self.depth.len() || hits.depth_m.len() != hits.len() {
            return Err(ModelError::Input(format!(
                "depth oracle: hits of {} images for {} depth images",
                hits.num_images,
                self.depth.len()
            )));
        }
        let (h, w) = self.hw;
        let g: Vec<f32> = (0..hits.len())
            .map(|i| {
                let [u, v] = hits.uv[i];
                let (x, y) = (
                    u.floor().clamp(0.0, w as f64 - 1.0),
                    v.floor().clamp(0.0, h as f64 - 1.0),
                );
                let ds = self.depth[hits.image[i] as usize][y as usize * w + x as usize];
                if !ds.is_finite() {
                    return 1.0;
                }
                let r = (hits.depth_m[i] - ds as f64).abs() / voxel_m.max(1e-6);
                (1.75 - r).clamp(0.0, 1.0) as f32
            })
            .collect();
        let n = g.len();
        Ok(Tensor::from_data(
            TensorData::new(g, [n]).convert::<B::FloatElem>(),
            device,
        ))
    }
}
