//! Depth-gated deformable cross attention (NOT in the SparseOcc++ paper; an option of
//! [`crate::sparseocc_pp`], off in the paper configs).
//!
//! Why: DCA gives a voxel the image features around the pixel its centre projects onto, and every
//! voxel on the same camera ray gets the same pixel. An empty voxel in front of a wall "sees" the wall
//! exactly as the wall voxel does, so occupancy along the ray has to be inferred from context alone.
//! The paper trains long enough (24 epochs from an ImageNet backbone) to learn that; a short run does
//! not (the demo's anchor scorer learnt the ground, where the ambiguity does not arise, and ranked
//! every object as empty). DFA3D (Li et al., ICCV 2023, "3D Deformable Attention for 2D-to-3D
//! Feature Lifting") removes the ambiguity by weighting the image features with a predicted depth
//! distribution; this module does the light version of that:
//!
//! 1. A depth head (3×3 conv `C → C`, ReLU, 1×1 conv `C → D`) on the finest image feature level
//!    predicts depth logits over the LSS bins `arange(d_min, d_max, step)` (bin `k` centred at
//!    `d_min + k·step`), supervised by the LiDAR depth exactly like SparseOcc's LSS depth net
//!    ([`crate::lss::depth_targets`] / [`crate::lss::depth_loss`], per-patch minimum depth).
//! 2. The gate of a (voxel, view) hit is the *relative* likelihood of the voxel's depth at its
//!    reference pixel: `R_k = p_k / max_j p_j = exp(l_k − max_j l_j)`, bilinear over the four feature
//!    pixels around the reference point (zero outside the map, the same sampling convention as DCA)
//!    and linear between the two bins around `t = (d − d_min)/step` (clamped to `[0, D − 1]`).
//!    `R` is 1 at the most likely depth and for a flat (untrained) distribution, so an untrained gate
//!    leaves DCA as it is; a confident depth map shuts the views of voxels in front of (or behind)
//!    the visible surface.
//! 3. DCA multiplies each hit's sampled features by its gate before averaging over views.
//!
//! The gate is differentiable in the depth logits (a gather), so the occupancy losses train the depth
//! head too.

use crate::batch::Batch;
use crate::error::ModelError;
use crate::loss::DepthBins;
use crate::sparseocc_pp::dca::ViewHits;
use burn::nn::conv::{Conv2d, Conv2dConfig};
use burn::nn::PaddingConfig2d;
use burn::prelude::*;
use burn::tensor::TensorData;

/// Configuration of [`DepthGate`].
#[derive(Config, Debug)]
pub struct DepthGateConfig {
    /// Channels of the image features it reads.
    pub in_channels: usize,
    /// Depth bins `[d_min, d_max, step]` in metres (`arange(d_min, d_max, step)`).
    #[config(default = "[2.0, 58.0, 1.0]")]
    pub dbound: [f64; 3],
}

impl DepthGateConfig {
    /// The bins.
    pub fn bins(&self) -> Result<DepthBins, ModelError> {
        DepthBins::from_dbound(self.dbound)
    }

    /// Checks sizes and bins.
    pub fn validate(&self) -> Result<(), ModelError> {
        if self.in_channels == 0 {
            return Err(ModelError::Config(
                "depth gate: in_channels must be > 0".into(),
            ));
        }
        self.bins().map(|_| ())
    }

    /// Initialises the head (does not validate; [`DepthGate::forward`] reports bad bins).
    pub fn init<B: Backend>(&self, device: &B::Device) -> DepthGate<B> {
        let c = self.in_channels.max(1);
        let d = self.bins().map(|b| b.num_bins).unwrap_or(1).max(1);
        DepthGate {
            conv1: Conv2dConfig::new([c, c], [3, 3])
                .with_padding(PaddingConfig2d::Explicit(1, 1, 1, 1))
                .init(device),
            conv2: Conv2dConfig::new([c, d], [1, 1]).init(device),
            dbound: self.dbound,
        }
    }
}

/// The depth head (see the module docs).
#[derive(Module, Debug)]
pub struct DepthGate<B: Backend> {
    /// 3×3 `C → C`.
    pub conv1: Conv2d<B>,
    /// 1×1 `C → D`.
    pub conv2: Conv2d<B>,
    dbound: [f64; 3],
}

/// The depth prediction of one forward pass.
#[derive(Clone, Debug)]
pub struct DepthMap<B: Backend> {
    /// Logits `[B·V, D, h, w]` (for the depth loss).
    pub logits: Tensor<B, 4>,
    /// Relative likelihood `exp(l − max l)` `[B·V, D, h, w]`, flattened for gathering.
    rel_flat: Tensor<B, 1>,
    dims: [usize; 4],
    /// Input pixels per depth-map pixel.
    pub stride: usize,
    /// `[d_min, d_max, step]`.
    pub dbound: [f64; 3],
}

impl<B: crate::kernels::ModelBackend> DepthGate<B> {
    /// `[d_min, d_max, step]`.
    pub fn dbound(&self) -> [f64; 3] {
        self.dbound
    }

    /// Depth logits of one feature level.
    ///
    /// # Shapes
    /// - feat: `[B·V, C, h, w]` with `stride` input pixels per feature pixel → `DepthMap` with logits
    ///   `[B·V, D, h, w]`
    pub fn forward(&self, feat: Tensor<B, 4>, stride: usize) -> Result<DepthMap<B>, ModelError> {
        let bins = DepthBins::from_dbound(self.dbound)?;
        if stride == 0 {
            return Err(ModelError::Input("depth gate: stride 0".into()));
        }
        let hidden = crate::kernels::conv2d_host::conv_bn(&self.conv1, None, feat, true);
        let logits = crate::kernels::conv2d_host::conv_bn(&self.conv2, None, hidden, false);
        let dims = logits.dims();
        if dims[1] != bins.num_bins {
            return Err(ModelError::Config(format!(
                "depth gate: head predicts {} bins, dbound {:?} has {}",
                dims[1], self.dbound, bins.num_bins
            )));
        }
        Ok(DepthMap::from_logits(logits, stride, self.dbound))
    }
}

/// Gather positions and weights of the gate of every hit: 4 pixels × 2 bins per hit (weight 0 for
/// pixels outside the map, index 0 then). `depth_m[i]` is hit `i`'s depth along the optical axis.
pub fn gate_taps(
    hits: &ViewHits,
    dims: [usize; 4],
    stride: usize,
    dbound: [f64; 3],
) -> (Vec<u32>, Vec<f64>) {
    let [_, d, h, w] = dims;
    let [lo, _, step] = dbound;
    let n = hits.len();
    let mut idx = Vec::with_capacity(n * 8);
    let mut wt = Vec::with_capacity(n * 8);
    let s = stride.max(1) as f64;
    for i in 0..n {
        let img = hits.image[i] as usize;
        let [u, v] = hits.uv[i];
        let (x, y) = ((u + 0.5) / s - 0.5, (v + 0.5) / s - 0.5);
        let (x0, y0) = (x.floor(), y.floor());
        let (fx, fy) = (x - x0, y - y0);
        let t = ((hits.depth_m.get(i).copied().unwrap_or(lo) - lo) / step)
            .clamp(0.0, (d.max(1) - 1) as f64);
        let k0 = t.floor() as usize;
        let k1 = (k0 + 1).min(d.max(1) - 1);
        let ft = t - k0 as f64;
        for (yy, wy) in [(y0 as i64, 1.0 - fy), (y0 as i64 + 1, fy)] {
            for (xx, wx) in [(x0 as i64, 1.0 - fx), (x0 as i64 + 1, fx)] {
                let inside = yy >= 0 && xx >= 0 && (yy as usize) < h && (xx as usize) < w;
                for (k, wk) in [(k0, 1.0 - ft), (k1, ft)] {
                    if inside {
                        idx.push((((img * d + k) * h + yy as usize) * w + xx as usize) as u32);
                        wt.push(wx * wy * wk);
                    } else {
                        idx.push(0);
                        wt.push(0.0);
                    }
                }
            }
        }
    }
    (idx, wt)
}

impl<B: Backend> DepthMap<B> {
    /// A depth map from logits `[B·V, D, h, w]` on feature pixels of `stride` input pixels.
    pub fn from_logits(logits: Tensor<B, 4>, stride: usize, dbound: [f64; 3]) -> Self {
        let dims = logits.dims();
        let max = logits.clone().max_dim(1);
        let rel = (logits.clone() - max).exp();
        DepthMap {
            logits,
            rel_flat: rel.reshape([dims.iter().product::<usize>()]),
            dims,
            stride,
            dbound,
        }
    }

    /// The gate of every hit `[nh]` (module docs, step 2); `hits` must come from the same images.
    pub fn hit_gate(&self, hits: &ViewHits) -> Result<Tensor<B, 1>, ModelError> {
        let device = self.logits.device();
        if hits.num_images != self.dims[0] || hits.depth_m.len() != hits.len() {
            return Err(ModelError::Input(format!(
                "depth gate: hits of {} images ({} depths for {} hits) for a depth map {:?}",
                hits.num_images,
                hits.depth_m.len(),
                hits.len(),
                self.dims
            )));
        }
        let nh = hits.len();
        if nh == 0 {
            return Ok(Tensor::zeros([0], &device));
        }
        let (idx, wt) = gate_taps(hits, self.dims, self.stride, self.dbound);
        let idx = occ_sparse::backend::index_tensor::<B>(&idx, &device);
        let wt = Tensor::<B, 1>::from_data(
            TensorData::new(wt, [nh * 8]).convert::<B::FloatElem>(),
            &device,
        );
        Ok((self.rel_flat.clone().select(0, idx) * wt)
            .reshape([nh, 8])
            .sum_dim(1)
            .reshape([nh]))
    }

    /// Depth loss against the LiDAR points of `batch` (`None` when the batch has no points).
    pub fn loss(&self, batch: &Batch<B>) -> Result<Option<Tensor<B, 1>>, ModelError> {
        let [_, _, h, w] = self.dims;
        match crate::lss::depth_targets(batch, h, w, self.stride, self.dbound)? {
            Some(t) => Ok(Some(crate::lss::depth_loss(self.logits.clone(), &t)?)),
            None => Ok(None),
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    type B64 = burn::backend::NdArray<f64>;

    fn hits_at(uv: Vec<[f64; 2]>, depth_m: Vec<f64>) -> ViewHits {
        let n = uv.len();
        ViewHits {
            num_queries: n,
            num_images: 1,
            query: (0..n as u32).collect(),
            image: vec![0; n],
            slot: (0..n as u32).collect(),
            uv,
            depth_m,
            views_per_query: vec![1; n],
            max_per_image: n,
        }
    }

    /// With logits that put all mass on bin 3 at every pixel, the gate is 1 at depth 3 (bin centre
    /// `d_min + 3·step`), 0.5 half a bin away, 0 two bins away, and halves at the map's border where
    /// half of the bilinear taps fall outside; a flat distribution gives 1 everywhere.
    #[test]
    fn gate_is_the_interpolated_relative_likelihood() {
        let device = Default::default();
        let dbound = [2.0, 10.0, 1.0];
        let (h, w, d, stride) = (3usize, 5usize, 8usize, 4usize);
        let mut l = vec![0.0f64; d * h * w];
        for k in 0..d {
            for p in 0..h * w {
                l[k * h * w + p] = if k == 3 { 50.0 } else { 0.0 };
            }
        }
        let logits = Tensor::<B64, 4>::from_data(TensorData::new(l, [1, d, h, w]), &device);
        let map = DepthMap::from_logits(logits, stride, dbound);
        // Pixel centre of feature pixel (2, 1): u = 2·4 + 1.5, v = 1·4 + 1.5.
        let c = [9.5, 5.5];
        let hits = hits_at(
            vec![c, c, c, c, [-0.5 * stride as f64 + 1.5, 5.5]],
            vec![5.0, 5.5, 7.0, 1.0, 5.0],
        );
        // burn fixes a device type's float dtype process-wide at its first use (another test of
        // this binary may have made it f32): read back converted, compare at f32 precision.
        let g: Vec<f64> = map
            .hit_gate(&hits)
            .unwrap()
            .into_data()
            .convert::<f64>()
            .to_vec()
            .unwrap();
        let want = [1.0, 0.5, 0.0, 0.0, 0.5];
        for (i, (a, b)) in g.iter().zip(want).enumerate() {
            assert!((a - b).abs() < 1e-6, "hit {i}: {a} vs {b}");
        }
        // Flat logits: every in-map hit gets 1.
        let flat =
            DepthMap::<B64>::from_logits(Tensor::zeros([1, d, h, w], &device), stride, dbound);
        let g: Vec<f64> = flat
            .hit_gate(&hits_at(vec![c], vec![6.2]))
            .unwrap()
            .into_data()
            .convert::<f64>()
            .to_vec()
            .unwrap();
        assert!((g[0] - 1.0).abs() < 1e-6, "{g:?}");
        // Hits from another number of images are refused.
        let mut bad = hits_at(vec![c], vec![6.0]);
        bad.num_images = 2;
        assert!(flat.hit_gate(&bad).is_err());
        // The head's output has one channel per bin.
        let head = DepthGateConfig::new(4)
            .with_dbound(dbound)
            .init::<B64>(&device);
        let m = head
            .forward(Tensor::zeros([2, 4, h, w], &device), stride)
            .unwrap();
        assert_eq!(m.logits.dims(), [2, d, h, w]);
    }
}
