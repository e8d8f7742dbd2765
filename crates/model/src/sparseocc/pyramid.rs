//! Sparse feature pyramid and interpolation voxel decoder (paper Sec. 3.3).
//!
//! Every propagator level `V_l` (stride `2^l`) is projected to `out_channels` (per-voxel linear map +
//! GroupNorm, the official "SubM k1 + GN") giving `P_l`, then fused with all other scales:
//!
//! `V̂_l = P_l + Σ_{j≠l} W_j · Interp(P_j → sites of V_l)`
//!
//! with one learned scalar weight `W_j` per source scale (initialised to 1). The paper's equation writes
//! only the sum over `j ≠ l`; keeping `P_l` itself is the reading where the scale is "augmented by
//! fusing all the other scales".
//!
//! `Interp` ("linear interpolation of features from the sparse tensor X to the coordinates of Y"):
//! voxel `o` of level `l` covers the level-0 voxels `[o·2^l, (o+1)·2^l)` (the dense layout of the
//! official code; axes whose size collapsed to 1 are clamped), centre `(o + 0.5)·2^l − 0.5`.
//! - from a **coarser** source: trilinear interpolation at the target centre over the (up to 8) source
//!   neighbours, **normalised over the neighbours that are active** (missing sparse sites are unknown,
//!   not zero; this is what lets "the denser low-resolution features resist dilution");
//! - from a **finer** source: the mean of the active source sites inside the target voxel (trilinear
//!   interpolation at stride 2 is exactly this mean; at larger strides it would only read the central
//!   2x2x2 children).
//!
//! Sites with no active source neighbour receive zero from that scale.
//!
//! Outputs: the fused levels, and the **mask features** `Linear(ReLU(V̂_0))` on the level-0 sites
//! (the official head's `mask_feature` 1x1 projection), used by the transformer head.

use crate::error::ModelError;
use burn::module::{Initializer, Param};
use burn::nn::{GroupNorm, GroupNormConfig, Linear, LinearConfig};
use burn::prelude::*;
use burn::tensor::activation::relu;
use burn::tensor::TensorData;
use occ_sparse::{gather_rows, scatter_add_rows, Coord, RowPlan, SparseConvBackend, SparseTensor};
use std::sync::Arc;

/// Configuration of [`SparsePyramid`].
#[derive(Config, Debug)]
pub struct PyramidConfig {
    /// Channels of each input level (the propagator's `channels`).
    pub in_channels: Vec<usize>,
    /// Decoder channels (paper/official: 192).
    #[config(default = 192)]
    pub out_channels: usize,
    /// GroupNorm groups (official 32); must divide `out_channels`.
    #[config(default = 32)]
    pub norm_groups: usize,
}

impl PyramidConfig {
    /// Initialises the pyramid; errors on an empty level list or indivisible groups.
    pub fn init<B: Backend>(&self, device: &B::Device) -> Result<SparsePyramid<B>, ModelError> {
        let l = self.in_channels.len();
        if l == 0 || self.in_channels.contains(&0) || self.out_channels == 0 {
            return Err(ModelError::Config(format!(
                "pyramid.rs: need >= 1 level with positive channels (levels {:?}, out {})",
                self.in_channels, self.out_channels
            )));
        }
        if self.norm_groups == 0 || !self.out_channels.is_multiple_of(self.norm_groups) {
            return Err(ModelError::Config(format!(
                "pyramid.rs: {} GroupNorm groups do not divide {} channels",
                self.norm_groups, self.out_channels
            )));
        }
        let c = self.out_channels;
        Ok(SparsePyramid {
            proj: self
                .in_channels
                .iter()
                .map(|&ci| LinearConfig::new(ci, c).init(device))
                .collect(),
            norms: (0..l)
                .map(|_| GroupNormConfig::new(self.norm_groups, c).init(device))
                .collect(),
            scale_weights: Initializer::Ones.init([l], device),
            mask_proj: LinearConfig::new(c, c).init(device),
        })
    }
}

/// Sparse feature pyramid with the interpolation voxel decoder (see the module documentation).
#[derive(Module, Debug)]
pub struct SparsePyramid<B: Backend> {
    proj: Vec<Linear<B>>,
    norms: Vec<GroupNorm<B>>,
    /// Learned weight `W_j` of each source scale `[L]`.
    pub scale_weights: Param<Tensor<B, 1>>,
    mask_proj: Linear<B>,
}

/// Output of [`SparsePyramid::forward`].
#[derive(Clone, Debug)]
pub struct PyramidOutput<B: Backend> {
    /// Fused levels `V̂_l` (`out_channels`), level `l` at stride `2^l`.
    pub levels: Vec<SparseTensor<B>>,
    /// Mask features on the level-0 sites `[N_0, out_channels]`.
    pub mask_features: SparseTensor<B>,
}

impl<B: occ_sparse::SparseConvBackend> SparsePyramid<B> {
    /// Fuses the levels.
    ///
    /// # Shapes
    /// - levels: level `l` has `N_l` sites x `in_channels[l]` at stride `2^l`
    /// - returns levels with `N_l` sites x `out_channels`, mask features `N_0 x out_channels`
    pub fn forward(&self, levels: &[SparseTensor<B>]) -> Result<PyramidOutput<B>, ModelError>
    where
        B: SparseConvBackend,
    {
        if levels.len() != self.proj.len() {
            return Err(ModelError::Input(format!(
                "pyramid.rs: {} levels for a pyramid of {}",
                levels.len(),
                self.proj.len()
            )));
        }
        let mut projected = Vec::with_capacity(levels.len());
        for (l, x) in levels.iter().enumerate() {
            if x.num_active() == 0 {
                return Err(ModelError::Input(format!(
                    "pyramid.rs: level {l} has no active site"
                )));
            }
            let f = self.norms[l].forward(crate::profile::linear(&self.proj[l], x.feats().clone()));
            projected.push(x.with_feats(f)?);
        }
        let w = self.scale_weights.val();
        let mut fused = Vec::with_capacity(levels.len());
        for (l, target) in projected.iter().enumerate() {
            let mut acc = target.feats().clone();
            for (j, src) in projected.iter().enumerate() {
                if j == l {
                    continue;
                }
                let wj = w.clone().narrow(0, j, 1).reshape([1, 1]);
                acc = acc + interpolate(src, 1 << j, target, 1 << l)? * wj;
            }
            fused.push(target.with_feats(acc)?);
        }
        let mask_features = fused[0].with_feats(crate::profile::linear(
            &self.mask_proj,
            relu(fused[0].feats().clone()),
        ))?;
        Ok(PyramidOutput {
            levels: fused,
            mask_features,
        })
    }
}

/// The level-`dst` voxel that contains level-`src` voxel `c` (`src_stride < dst_stride`, strides in
/// level-0 voxels), with axes clamped to the destination shape.
pub fn parent_coord(
    c: Coord,
    src_stride: usize,
    dst_stride: usize,
    dst_shape: [usize; 3],
) -> Coord {
    let mut p = [c[0], 0, 0, 0];
    for a in 0..3 {
        let v = (c[a + 1] as i64 * src_stride as i64).div_euclid(dst_stride as i64);
        p[a + 1] = v.clamp(0, dst_shape[a].saturating_sub(1) as i64) as i32;
    }
    p
}

/// Host-side interpolation weights from `src` sites to `dst` sites: triplets
/// `(dst_row, src_row, weight)`, weights of each destination row summing to 1 (or no triplet when no
/// source site is near). See the module documentation for the rule.
pub fn interpolation_weights<B: Backend>(
    src: &SparseTensor<B>,
    src_stride: usize,
    dst: &SparseTensor<B>,
    dst_stride: usize,
) -> Vec<(usize, usize, f64)> {
    let mut out = Vec::new();
    if src_stride < dst_stride {
        // Finer source: mean over the source sites inside each destination voxel.
        let dst_set = dst.coord_set();
        let shape = dst.spatial_shape();
        let mut count = vec![0usize; dst.num_active()];
        let mut pairs = Vec::new();
        for (r, &c) in src.coords().iter().enumerate() {
            if let Some(d) = dst_set.find(parent_coord(c, src_stride, dst_stride, shape)) {
                count[d] += 1;
                pairs.push((d, r));
            }
        }
        for (d, r) in pairs {
            out.push((d, r, 1.0 / count[d] as f64));
        }
    } else {
        // Coarser (or equal) source: normalised trilinear interpolation at the destination centre.
        let set = src.coord_set();
        let ratio = dst_stride as f64 / src_stride as f64;
        for (d, &c) in dst.coords().iter().enumerate() {
            let mut base = [0i32; 3];
            let mut frac = [0f64; 3];
            for a in 0..3 {
                let q = (c[a + 1] as f64 + 0.5) * ratio - 0.5;
                let f = q.floor();
                base[a] = f as i32;
                frac[a] = q - f;
            }
            let start = out.len();
            let mut total = 0.0;
            for corner in 0..8 {
                let mut wgt = 1.0;
                let mut s = [c[0], 0, 0, 0];
                for a in 0..3 {
                    let bit = (corner >> a) & 1;
                    s[a + 1] = base[a] + bit;
                    wgt *= if bit == 1 { frac[a] } else { 1.0 - frac[a] };
                }
                if wgt <= 1e-12 {
                    continue;
                }
                if let Some(r) = set.find(s) {
                    out.push((d, r, wgt));
                    total += wgt;
                }
            }
            for t in &mut out[start..] {
                t.2 /= total;
            }
        }
    }
    out
}

/// `Interp(src → dst)`: features of `src` interpolated at the sites of `dst` (differentiable with
/// respect to the source features).
///
/// # Shapes
/// - src: `N_s x C` -> `[N_d, C]`
pub fn interpolate<B: SparseConvBackend>(
    src: &SparseTensor<B>,
    src_stride: usize,
    dst: &SparseTensor<B>,
    dst_stride: usize,
) -> Result<Tensor<B, 2>, ModelError> {
    if src.batch_size() != dst.batch_size() {
        return Err(ModelError::Input(format!(
            "pyramid.rs interpolate: batch sizes {} and {}",
            src.batch_size(),
            dst.batch_size()
        )));
    }
    let device = src.device();
    let c = src.channels();
    let trip = interpolation_weights(src, src_stride, dst, dst_stride);
    let out = Tensor::<B, 2>::zeros([dst.num_active(), c], &device);
    if trip.is_empty() {
        return Ok(out);
    }
    let n = trip.len();
    let dst_idx: Vec<u32> = trip.iter().map(|t| t.0 as u32).collect();
    let src_idx: Vec<u32> = trip.iter().map(|t| t.1 as u32).collect();
    let wts: Vec<f32> = trip.iter().map(|t| t.2 as f32).collect();
    let from_src = Arc::new(RowPlan::new(src_idx, src.num_active())?);
    let into_dst = Arc::new(RowPlan::new(dst_idx, dst.num_active())?);
    let rows = gather_rows(src.feats().clone(), &from_src)
        * Tensor::<B, 2>::from_data(TensorData::new(wts, [n, 1]), &device);
    Ok(out + scatter_add_rows(rows, &into_dst))
}
