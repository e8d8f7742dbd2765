//! Deformable cross attention (DCA) from sparse voxel queries to multi-view, multi-scale image features
//! (SparseOcc++, paper Sec. 4.2 "Contextualization via Deformable Cross Attention", after Deformable DETR
//! and BEVFormer's spatial cross attention):
//!
//! `DCA(q) = 1/|V_hit| · Σ_{v ∈ V_hit} Σ_l Σ_j w_{lj} · F_{v,l}(π(p, T_v)/s_l + Δp_{lj})`
//!
//! - The reference point of a voxel is its centre (metres, from the [`VoxelGrid`] of its level) projected
//!   with `CameraInput::img_from_lidar` into NETWORK-INPUT pixels `(u, v)` (pixel centres at integer
//!   coordinates, as in `occ_geometry::camera`).
//! - A view "sees" a voxel when the projected depth exceeds `occ_geometry::MIN_DEPTH_M` and
//!   `0 <= u < W`, `0 <= v < H` (the same test as `occ_geometry::CameraView::in_view`). Views that do not
//!   see a voxel are excluded from the average (`V_hit`); a voxel seen by no view gets a zero update.
//! - On level `l` with stride `s_l` (input pixels per feature pixel), feature pixel `j` covers input
//!   pixels `[j·s_l, (j+1)·s_l)`, so the feature coordinate of input pixel `u` is `(u + 0.5)/s_l - 0.5`.
//!   Sampling is bilinear with zero padding and `align_corners = false`, i.e. the normalised coordinate
//!   is `2(u + 0.5)/(s_l·w_l) - 1`.
//! - `N_s` sampling points per head and level with offsets `Δp` (in feature pixels of that level) and
//!   softmax attention weights (over levels × points, per head), both predicted from the query
//!   (`feature + position encoding`) by linear layers. As in BEVFormer, offsets and weights depend on
//!   the query only and are shared by all views (the paper's `Δp_{vj}`, `w_{vj}` carry a view index; a
//!   query has no view-specific input to predict different ones from).
//! - Values are the image features projected to `embed_dim` (a 1×1 linear map) and split into heads.
//!
//! The block around the attention is the usual post-norm transformer layer:
//! `x = LN(f + W_o·DCA(f + pos))`, `x = LN(x + FFN(x))`.
//!
//! Cost: host work is one projection per (voxel, view) (a loop over coordinates). The sampling is
//! the backend's [`ModelBackend::dca_sample`] on a [`DcaSample`] (offsets and weights predicted here,
//! values projected here): on the CPU one host loop over the (voxel, view) hits
//! (`M·L·N_s·4·D/M` multiply-adds per hit, no intermediate tensors), in training registered as one
//! autodiff op with its own backward pass; on other backends (CUDA) one batched `grid_sample` per
//! level over all hits, padded per image to the largest number of hits of one image
//! ([`crate::kernels::dca`]). The inputs of the attention travel together as [`DcaInputs`].

use crate::batch::CameraInput;
use crate::error::ModelError;
pub use crate::kernels::dca::FeatureRows;
use crate::kernels::dca::{sample_tensor_ops, DcaSample};
use crate::kernels::ModelBackend;
use burn::module::Param;
use burn::nn::{Initializer, LayerNorm, LayerNormConfig, Linear, LinearConfig};
use burn::prelude::*;
use burn::tensor::TensorData;
use occ_geometry::{project_with, VoxelGrid};
use occ_sparse::Coord;

/// Configuration of [`DeformableCrossAttention`].
#[derive(Config, Debug)]
pub struct DcaConfig {
    /// Query / value width `D` (divisible by `num_heads`).
    pub embed_dim: usize,
    /// Channels `C` of the image feature maps.
    pub feat_channels: usize,
    /// Number of image feature levels `L`.
    #[config(default = 1)]
    pub num_levels: usize,
    /// Attention heads `M`.
    #[config(default = 4)]
    pub num_heads: usize,
    /// Sampling points per head and level (`N_s`).
    #[config(default = 4)]
    pub num_points: usize,
    /// Hidden width of the feed-forward layer, as a multiple of `embed_dim`.
    #[config(default = 2)]
    pub ffn_ratio: usize,
    /// Scale of the initial sampling offsets: point `j` starts `(j + 1)·scale` feature pixels from the
    /// reference point. 1.0 is Deformable DETR's pattern; small input images (a few dozen feature
    /// pixels across) want less, or the initial points miss the object the voxel projects onto.
    #[config(default = 1.0)]
    pub offset_init_scale: f64,
}

impl DcaConfig {
    /// Checks the sizes.
    pub fn validate(&self) -> Result<(), ModelError> {
        if self.embed_dim == 0
            || self.num_heads == 0
            || !self.embed_dim.is_multiple_of(self.num_heads)
        {
            return Err(ModelError::Config(format!(
                "DCA: embed_dim {} must be a positive multiple of num_heads {}",
                self.embed_dim, self.num_heads
            )));
        }
        if !(self.offset_init_scale.is_finite() && self.offset_init_scale >= 0.0) {
            return Err(ModelError::Config(format!(
                "DCA: offset_init_scale {} must be finite and non-negative",
                self.offset_init_scale
            )));
        }
        if self.num_levels == 0 || self.num_points == 0 || self.feat_channels == 0 {
            return Err(ModelError::Config(format!(
                "DCA: num_levels {}, num_points {} and feat_channels {} must be positive",
                self.num_levels, self.num_points, self.feat_channels
            )));
        }
        Ok(())
    }

    /// Initialises the block. Offsets start at Deformable DETR's pattern (head `m` points in direction
    /// `2πm/M`, point `j` at distance `(j+1)·offset_init_scale` feature pixels, weight matrix zero);
    /// attention weights start uniform (zero weight and bias).
    pub fn init<B: Backend>(&self, device: &B::Device) -> DeformableCrossAttention<B> {
        let d = self.embed_dim;
        let (m, l, p) = (self.num_heads, self.num_levels, self.num_points);
        let mut sampling_offsets = LinearConfig::new(d, m * l * p * 2)
            .with_initializer(Initializer::Zeros)
            .init(device);
        let mut bias = Vec::with_capacity(m * l * p * 2);
        for head in 0..m {
            let theta = 2.0 * std::f64::consts::PI * head as f64 / m as f64;
            let (c, s) = (theta.cos(), theta.sin());
            let norm = c.abs().max(s.abs()).max(1e-12);
            for _ in 0..l {
                for j in 0..p {
                    let r = (j + 1) as f64 * self.offset_init_scale;
                    bias.push((c / norm * r) as f32);
                    bias.push((s / norm * r) as f32);
                }
            }
        }
        sampling_offsets.bias = Some(Param::from_tensor(Tensor::from_data(
            TensorData::new(bias, [m * l * p * 2]).convert::<B::FloatElem>(),
            device,
        )));
        let attention_weights = LinearConfig::new(d, m * l * p)
            .with_initializer(Initializer::Zeros)
            .init(device);
        let hidden = (d * self.ffn_ratio).max(1);
        DeformableCrossAttention {
            value_proj: LinearConfig::new(self.feat_channels, d).init(device),
            sampling_offsets,
            attention_weights,
            output_proj: LinearConfig::new(d, d).init(device),
            norm1: LayerNormConfig::new(d)
                .with_epsilon(crate::kernels::LAYER_NORM_EPSILON)
                .init(device),
            ffn1: LinearConfig::new(d, hidden).init(device),
            ffn2: LinearConfig::new(hidden, d).init(device),
            norm2: LayerNormConfig::new(d)
                .with_epsilon(crate::kernels::LAYER_NORM_EPSILON)
                .init(device),
            embed_dim: d,
            feat_channels: self.feat_channels,
            num_heads: m,
            num_levels: l,
            num_points: p,
        }
    }
}

/// Deformable cross attention block (see the module docs).
#[derive(Module, Debug)]
pub struct DeformableCrossAttention<B: Backend> {
    /// Image features `C → D` (1×1).
    pub value_proj: Linear<B>,
    /// Query → offsets `[M, L, N_s, 2]` in feature pixels of each level.
    pub sampling_offsets: Linear<B>,
    /// Query → attention logits `[M, L·N_s]`.
    pub attention_weights: Linear<B>,
    /// Attention output `D → D`.
    pub output_proj: Linear<B>,
    /// Post-attention norm.
    pub norm1: LayerNorm<B>,
    /// FFN first layer.
    pub ffn1: Linear<B>,
    /// FFN second layer.
    pub ffn2: Linear<B>,
    /// Post-FFN norm.
    pub norm2: LayerNorm<B>,
    embed_dim: usize,
    feat_channels: usize,
    num_heads: usize,
    num_levels: usize,
    num_points: usize,
}

pub use crate::kernels::dca::ViewHits;

/// The inputs of the attention ([`DeformableCrossAttention::aggregate_gated`] and its two paths,
/// [`DeformableCrossAttention::aggregate_host`] and [`DeformableCrossAttention::aggregate_tensor_ops`]).
#[derive(Clone, Debug)]
pub struct DcaInputs<'a, B: Backend> {
    /// Queries `[N, D]` (feature + position encoding).
    pub query: Tensor<B, 2>,
    /// Which views see which query ([`project_queries`]).
    pub hits: &'a ViewHits,
    /// Image features of every level as channel-last rows ([`FeatureRows::from_nchw`] of the
    /// `[B·V, C, h_l, w_l]` maps; laid out once per frame and shared by its DCA blocks).
    pub feats: &'a FeatureRows<B>,
    /// Input pixels per feature pixel of each level.
    pub strides: &'a [usize],
    /// Per-hit gate `[hits.len()]` on the samples before the average over views (e.g. the depth
    /// gate of [`crate::sparseocc_pp::extras::depth_gate`]); `None` = all ones.
    pub gate: Option<Tensor<B, 1>>,
}

/// Projects the centres of the voxels `coords` (`(b, x, y, z)` on `grid`) into every view of their batch
/// item and keeps the views that see them (depth > `MIN_DEPTH_M`, inside the `image_hw` image).
///
/// `cameras[b][v]`; every batch item must have the same number of views `V` (images are `b·V + v`).
pub fn project_queries(
    coords: &[Coord],
    grid: &VoxelGrid,
    cameras: &[Vec<CameraInput>],
    image_hw: (usize, usize),
) -> Result<ViewHits, ModelError> {
    project_points(coords, grid, cameras, image_hw, |c| c)
}

/// Not in the paper (option `dca_column_base`): like [`project_queries`], but each voxel is represented
/// by the base of its vertical column, its centre moved down to the height `floor_z_m` (metres, LiDAR
/// frame). The pixel of a voxel's column base shows what stands on the ground under it: an object's
/// bottom when the voxel is over the object's footprint, the ground in front of it otherwise. This is
/// the depth cue of a ground-standing object that the voxel's own pixel lacks (every voxel of one ray
/// projects to the same pixel), the idea of BEVFormer's pillar reference points.
/// `depth_m` is the depth of the base point.
pub fn project_column_bases(
    coords: &[Coord],
    grid: &VoxelGrid,
    cameras: &[Vec<CameraInput>],
    image_hw: (usize, usize),
    floor_z_m: f64,
) -> Result<ViewHits, ModelError> {
    if !floor_z_m.is_finite() {
        return Err(ModelError::Input(format!(
            "DCA: column-base height {floor_z_m} is not finite"
        )));
    }
    project_points(coords, grid, cameras, image_hw, |c| [c[0], c[1], floor_z_m])
}

/// [`project_queries`] with the projected point of each voxel given by `point_of(centre)`.
fn project_points(
    coords: &[Coord],
    grid: &VoxelGrid,
    cameras: &[Vec<CameraInput>],
    image_hw: (usize, usize),
    point_of: impl Fn([f64; 3]) -> [f64; 3],
) -> Result<ViewHits, ModelError> {
    let num_views = cameras.first().map_or(0, Vec::len);
    if cameras.iter().any(|c| c.len() != num_views) {
        return Err(ModelError::Input(
            "DCA: every batch item must have the same number of cameras".into(),
        ));
    }
    let (h, w) = (image_hw.0 as f64, image_hw.1 as f64);
    let num_images = cameras.len() * num_views;
    let mut per_image: Vec<Vec<(u32, [f64; 2], f64)>> = vec![Vec::new(); num_images];
    let mut views_per_query = vec![0u32; coords.len()];
    for (q, c) in coords.iter().enumerate() {
        let b = usize::try_from(c[0])
            .ok()
            .filter(|&b| b < cameras.len())
            .ok_or_else(|| {
                ModelError::Input(format!(
                    "DCA: voxel {q} has batch index {} but there are {} camera sets",
                    c[0],
                    cameras.len()
                ))
            })?;
        let mut ijk = [0usize; 3];
        for a in 0..3 {
            ijk[a] = usize::try_from(c[a + 1])
                .ok()
                .filter(|&i| i < grid.dims[a])
                .ok_or_else(|| {
                    ModelError::Input(format!(
                        "DCA: voxel {q} at {c:?} lies outside the grid {:?}",
                        grid.dims
                    ))
                })?;
        }
        let centre = point_of(grid.voxel_center_m(ijk));
        for (v, cam) in cameras[b].iter().enumerate() {
            if let Some([u, vv, d]) = project_with(&cam.img_from_lidar, centre) {
                if u >= 0.0 && vv >= 0.0 && u < w && vv < h {
                    per_image[b * num_views + v].push((q as u32, [u, vv], d));
                    views_per_query[q] += 1;
                }
            }
        }
    }
    let total: usize = per_image.iter().map(Vec::len).sum();
    let mut hits = ViewHits {
        num_queries: coords.len(),
        num_images,
        query: Vec::with_capacity(total),
        image: Vec::with_capacity(total),
        slot: Vec::with_capacity(total),
        uv: Vec::with_capacity(total),
        depth_m: Vec::with_capacity(total),
        views_per_query,
        max_per_image: per_image.iter().map(Vec::len).max().unwrap_or(0),
    };
    for (n, list) in per_image.iter().enumerate() {
        for (s, &(q, uv, d)) in list.iter().enumerate() {
            hits.query.push(q);
            hits.image.push(n as u32);
            hits.slot.push(s as u32);
            hits.uv.push(uv);
            hits.depth_m.push(d);
        }
    }
    Ok(hits)
}

impl<B: ModelBackend> DeformableCrossAttention<B> {
    /// Query width `D`.
    pub fn embed_dim(&self) -> usize {
        self.embed_dim
    }

    /// Multiply-adds of the sampling for `num_hits` (query, view) hits: per hit, head, level and
    /// point, the four bilinear corners of each of the head's `D / M` channels, each one
    /// multiply-add with the attention weight folded into the corner weight (as the host loop does):
    /// `hits * L * N_s * D * 4`. The projections (value, offsets, weights, output, FFN) are counted
    /// by their linear layers.
    pub fn sampling_macs(&self, num_hits: usize) -> u64 {
        (num_hits * self.num_levels * self.num_points * self.embed_dim * 4) as u64
    }

    /// Sampling offsets `[N, M, L, N_s, 2]` (feature pixels, `(x, y)`) and softmax attention weights
    /// `[N, M, L, N_s]` (summing to 1 over `L·N_s` per head) predicted from `query [N, D]`.
    pub fn sampling(&self, query: Tensor<B, 2>) -> (Tensor<B, 5>, Tensor<B, 4>) {
        let n = query.dims()[0];
        let (m, l, p) = (self.num_heads, self.num_levels, self.num_points);
        let offsets = crate::profile::row_linear(&self.sampling_offsets, query.clone())
            .reshape([n, m, l, p, 2]);
        let logits =
            crate::profile::row_linear(&self.attention_weights, query).reshape([n, m, l * p]);
        let weights = B::row_softmax(logits).reshape([n, m, l, p]);
        (offsets, weights)
    }

    /// Value maps of one level: `feats [B·V, C, h, w]` → `[B·V·M, D/M, h, w]` (head-major per image).
    pub fn project_values(&self, feats: Tensor<B, 4>) -> Tensor<B, 4> {
        let [n, c, h, w] = feats.dims();
        let m = self.num_heads;
        let dh = self.embed_dim / m;
        let rows = feats.permute([0, 2, 3, 1]).reshape([n * h * w, c]);
        crate::profile::row_linear(&self.value_proj, rows)
            .reshape([n, h, w, m, dh])
            .permute([0, 3, 4, 1, 2])
            .reshape([n * m, dh, h, w])
    }

    /// The projected values of every level: the feature rows `[Σ_l B·V·h_l·w_l, C]` →
    /// `[Σ_l B·V·h_l·w_l, D]` (`D` head-major), one linear map over all levels at once.
    fn value_maps(&self, feats: &FeatureRows<B>) -> FeatureRows<B> {
        feats.map_rows(|rows| crate::profile::row_linear(&self.value_proj, rows))
    }

    /// The sampling op's inputs: offsets and weights predicted from the query, values projected.
    fn sample_inputs<'a>(&self, inputs: DcaInputs<'a, B>) -> DcaSample<'a, B> {
        let (offsets, weights) = self.sampling(inputs.query);
        crate::profile::trace_mark("dca offsets and weights", &weights);
        let values = self.value_maps(inputs.feats);
        crate::profile::trace_mark("dca value maps", &values.rows);
        DcaSample {
            hits: inputs.hits,
            strides: inputs.strides,
            values,
            offsets,
            weights,
            gate: inputs.gate,
        }
    }

    fn check_inputs(&self, inputs: &DcaInputs<'_, B>) -> Result<(), ModelError> {
        let DcaInputs {
            query,
            hits,
            feats,
            strides,
            gate,
        } = inputs;
        if let Some(g) = gate {
            if g.dims()[0] != hits.len() {
                return Err(ModelError::Input(format!(
                    "DCA: {} gate values for {} hits",
                    g.dims()[0],
                    hits.len()
                )));
            }
        }
        let [n, d] = query.dims();
        if d != self.embed_dim || n != hits.num_queries {
            return Err(ModelError::Input(format!(
                "DCA: query is [{n}, {d}] but the block has D = {} and the hits were built for {} queries",
                self.embed_dim, hits.num_queries
            )));
        }
        if feats.levels.len() != self.num_levels || strides.len() != self.num_levels {
            return Err(ModelError::Input(format!(
                "DCA: {} feature levels and {} strides given, the block was built for {}",
                feats.levels.len(),
                strides.len(),
                self.num_levels
            )));
        }
        let c = feats.width();
        for (l, (&[bv, h, w], &s)) in feats.levels.iter().zip(strides.iter()).enumerate() {
            if bv != hits.num_images || c != self.feat_channels || h == 0 || w == 0 || s == 0 {
                return Err(ModelError::Input(format!(
                    "DCA: level {l} features [{bv}, {c}, {h}, {w}] (stride {s}) do not match {} images x {} channels",
                    hits.num_images,
                    self.feat_channels
                )));
            }
        }
        Ok(())
    }

    /// Checks the inputs; `Some(zeros [N, D])` when no view sees any query (nothing to sample).
    fn checked_or_zeros(
        &self,
        inputs: &DcaInputs<'_, B>,
    ) -> Result<Option<Tensor<B, 2>>, ModelError> {
        self.check_inputs(inputs)?;
        let query = &inputs.query;
        Ok(inputs
            .hits
            .is_empty()
            .then(|| Tensor::zeros(query.dims(), &query.device())))
    }

    /// [`Self::aggregate_gated`] as one host loop, parallel over queries: per hit of the query, per
    /// head, level and point, the bilinear sample of the channel-last value map at
    /// `(u + 0.5)/s_l − 0.5 + Δp` (zero outside the map) weighted by the attention weight; summed
    /// over the query's hits and divided by its number of views. Coordinates and bilinear weights are
    /// computed in f64, the channel sums in the tensors' float type (f32 or f64, else an error). The
    /// path `NdArray` takes for inference; it is not differentiable.
    pub fn aggregate_host(&self, inputs: DcaInputs<'_, B>) -> Result<Tensor<B, 2>, ModelError> {
        if let Some(zeros) = self.checked_or_zeros(&inputs)? {
            return Ok(zeros);
        }
        crate::kernels::dca_host::sample_host(self.sample_inputs(inputs))
            .map_err(|_| ModelError::Input("DCA: the host loop needs f32 or f64 tensors".into()))
    }

    /// [`Self::aggregate_gated`] composed of burn tensor ops (differentiable; any backend): the hits
    /// are laid out per image in a padded sampling grid, one `grid_sample` per level
    /// ([`crate::kernels::dca::sample_tensor_ops`]). The path of the backends without host kernels
    /// (CUDA).
    pub fn aggregate_tensor_ops(
        &self,
        inputs: DcaInputs<'_, B>,
    ) -> Result<Tensor<B, 2>, ModelError> {
        if let Some(zeros) = self.checked_or_zeros(&inputs)? {
            return Ok(zeros);
        }
        Ok(sample_tensor_ops(self.sample_inputs(inputs)))
    }
}

impl<B: ModelBackend> DeformableCrossAttention<B> {
    /// The attention itself: the view-averaged, weighted samples `[N, D]` (heads concatenated) before
    /// the output projection, for `query [N, D]` (feature + position), image features
    /// `feats[l] [B·V, C, h_l, w_l]` with `strides[l]` input pixels per feature pixel.
    pub fn aggregate(
        &self,
        query: Tensor<B, 2>,
        hits: &ViewHits,
        feats: &[Tensor<B, 4>],
        strides: &[usize],
    ) -> Result<Tensor<B, 2>, ModelError> {
        self.aggregate_gated(DcaInputs {
            query,
            hits,
            feats: &FeatureRows::from_nchw(feats)?,
            strides,
            gate: None,
        })
    }

    /// [`Self::aggregate`] with every hit's samples multiplied by `inputs.gate[hit]` before the
    /// average over views. The sampling is the backend's [`ModelBackend::dca_sample`]: on the CPU
    /// one host loop over the (voxel, view) hits ([`Self::aggregate_host`]), in CPU training
    /// registered as one autodiff op with its own backward pass; elsewhere (CUDA) composed of burn
    /// tensor ops ([`Self::aggregate_tensor_ops`]). All compute the same function.
    pub fn aggregate_gated(&self, inputs: DcaInputs<'_, B>) -> Result<Tensor<B, 2>, ModelError> {
        if let Some(zeros) = self.checked_or_zeros(&inputs)? {
            return Ok(zeros);
        }
        if crate::profile::counting() {
            crate::profile::add_macs("dca_sampling", self.sampling_macs(inputs.hits.len()));
        }
        Ok(B::dca_sample(self.sample_inputs(inputs)))
    }

    /// The full block: `x = LN(feats + W_o·DCA(feats + pos))`, `x = LN(x + FFN(x))`.
    ///
    /// # Shapes
    /// - feats, pos: `[N, D]`; `images`: the rows of the `[B·V, C, h_l, w_l]` feature maps
    ///   ([`FeatureRows::from_nchw`]) → `[N, D]`
    pub fn forward(
        &self,
        feats: Tensor<B, 2>,
        pos: Tensor<B, 2>,
        hits: &ViewHits,
        images: &FeatureRows<B>,
        strides: &[usize],
    ) -> Result<Tensor<B, 2>, ModelError> {
        self.forward_gated(feats, pos, hits, images, strides, None)
    }

    /// [`Self::forward`] with a per-hit gate on the samples ([`Self::aggregate_gated`]).
    pub fn forward_gated(
        &self,
        feats: Tensor<B, 2>,
        pos: Tensor<B, 2>,
        hits: &ViewHits,
        images: &FeatureRows<B>,
        strides: &[usize],
        gate: Option<Tensor<B, 1>>,
    ) -> Result<Tensor<B, 2>, ModelError> {
        let attn = self.aggregate_gated(DcaInputs {
            query: feats.clone() + pos,
            hits,
            feats: images,
            strides,
            gate,
        })?;
        crate::profile::trace_mark("dca sampling", &attn);
        let x = B::row_layer_norm(
            &self.norm1,
            feats + crate::profile::row_linear(&self.output_proj, attn),
        );
        crate::profile::trace_mark("dca output projection and norm", &x);
        let y = crate::profile::row_linear(
            &self.ffn2,
            crate::profile::row_linear_relu(&self.ffn1, x.clone()),
        );
        crate::profile::trace_mark("dca ffn", &y);
        let out = B::row_layer_norm(&self.norm2, x + y);
        crate::profile::trace_mark("dca residual and norm", &out);
        Ok(out)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::sample::bilinear_sample;
    type B64 = burn::backend::NdArray<f64>;

    /// The MACs one DCA block counts, against a hand count: D = 8, C = 4, M = 2 heads, L = 2 levels,
    /// N_s = 3 points, FFN 8 → 16 → 8; 2 queries, query 0 seen by both images, query 1 by one
    /// (3 hits); level maps 6x5 and 3x3 on 2 images.
    #[test]
    fn block_macs_match_a_hand_count() {
        // f32, as the other lib tests of this binary: burn 0.21 keeps one default float dtype per
        // device, set by the first backend that uses it, so an f64 NdArray after f32 ones (the
        // backbone tests) gets f32 tensors, which the host loop refuses.
        type B32 = burn::backend::NdArray<f32>;
        let device = Default::default();
        let dca = DcaConfig::new(8, 4)
            .with_num_heads(2)
            .with_num_levels(2)
            .with_num_points(3)
            .with_ffn_ratio(2)
            .init::<B32>(&device);
        let hits = ViewHits {
            num_queries: 2,
            num_images: 2,
            query: vec![0, 1, 0],
            image: vec![0, 0, 1],
            slot: vec![0, 1, 0],
            uv: vec![[5.0, 7.0], [11.0, 3.0], [2.0, 20.0]],
            depth_m: vec![4.0, 6.0, 5.0],
            views_per_query: vec![2, 1],
            max_per_image: 2,
        };
        let images = FeatureRows::from_nchw(&[
            Tensor::<B32, 4>::ones([2, 4, 6, 5], &device),
            Tensor::<B32, 4>::ones([2, 4, 3, 3], &device),
        ])
        .unwrap();
        let feats = Tensor::<B32, 2>::ones([2, 8], &device);
        crate::profile::enable(true);
        dca.forward(feats.clone(), feats.zeros_like(), &hits, &images, &[4, 8])
            .unwrap();
        let total = crate::profile::take_unmarked_macs();
        let mut ops = crate::profile::take_ops();
        ops.sort();
        crate::profile::enable(false);
        let offsets = 2 * 8 * (2 * 2 * 3 * 2); // queries x D x (M L N_s 2)
        let weights = 2 * 8 * (2 * 2 * 3); // queries x D x (M L N_s)
        let values = (2 * 6 * 5 + 2 * 3 * 3) * 4 * 8; // every feature pixel x C x D
        let sampling = 3 * 2 * 3 * 8 * 4; // hits x L x N_s x D x 4 corners
        let out_proj = 2 * 8 * 8;
        let ffn = 2 * 8 * 16 + 2 * 16 * 8;
        let linear = offsets + weights + values + out_proj + ffn;
        assert_eq!(dca.sampling_macs(3), sampling as u64);
        assert_eq!(total, (linear + sampling) as u64);
        assert_eq!(
            ops,
            vec![("dca_sampling", sampling as u64), ("linear", linear as u64)]
        );
        // Off: nothing is counted.
        dca.forward(feats.clone(), feats.zeros_like(), &hits, &images, &[4, 8])
            .unwrap();
        assert_eq!(crate::profile::take_unmarked_macs(), 0);
    }

    /// Initial offsets: Deformable DETR's ring (head `m` along angle `2πm/M`, normalised so the larger
    /// component is 1, point `j` at `j + 1`), times `offset_init_scale`; a negative scale is refused.
    #[test]
    fn initial_offsets_follow_the_scaled_ring() {
        let device = Default::default();
        for scale in [1.0, 0.25] {
            let cfg = DcaConfig::new(8, 4)
                .with_num_heads(4)
                .with_num_levels(2)
                .with_num_points(3)
                .with_offset_init_scale(scale);
            cfg.validate().unwrap();
            let dca = cfg.init::<B64>(&device);
            let b: Vec<f64> = dca
                .sampling_offsets
                .bias
                .unwrap()
                .val()
                .into_data()
                .convert::<f64>()
                .to_vec()
                .unwrap();
            assert_eq!(b.len(), 4 * 2 * 3 * 2);
            let dirs = [[1.0, 0.0], [0.0, 1.0], [-1.0, 0.0], [0.0, -1.0]];
            for (m, dir) in dirs.iter().enumerate() {
                for l in 0..2 {
                    for j in 0..3 {
                        let i = ((m * 2 + l) * 3 + j) * 2;
                        let r = (j + 1) as f64 * scale;
                        assert!((b[i] - dir[0] * r).abs() < 1e-6, "{scale} {m} {l} {j}");
                        assert!((b[i + 1] - dir[1] * r).abs() < 1e-6, "{scale} {m} {l} {j}");
                    }
                }
            }
        }
        assert!(DcaConfig::new(8, 4)
            .with_offset_init_scale(-1.0)
            .validate()
            .is_err());
    }

    fn npy(path: &std::path::Path) -> (Vec<usize>, Vec<f64>) {
        let f = std::fs::File::open(path).unwrap_or_else(|e| panic!("{}: {e}", path.display()));
        let n = npyz::NpyFile::new(std::io::BufReader::new(f)).unwrap();
        let shape = n.shape().iter().map(|&d| d as usize).collect();
        (shape, n.into_vec().unwrap())
    }

    /// The sampling DCA relies on (bilinear, zero padding, align_corners = false) against the
    /// PyTorch `grid_sample` fixture of the external fixtures folder (skipped with a note without it).
    #[test]
    fn bilinear_sample_matches_fixture() {
        let Some(fixtures) = occ_testdata::fixtures() else {
            return;
        };
        let dir = fixtures.join("reference");
        let device = Default::default();
        let (fs, f) = npy(&dir.join("grid_sample_features.npy"));
        let (gs, g) = npy(&dir.join("grid_sample_grid.npy"));
        let (_, expected) = npy(&dir.join("grid_sample_out.npy"));
        let feats =
            Tensor::<B64, 4>::from_data(TensorData::new(f, [fs[0], fs[1], fs[2], fs[3]]), &device);
        let grid =
            Tensor::<B64, 4>::from_data(TensorData::new(g, [gs[0], gs[1], gs[2], gs[3]]), &device);
        let got: Vec<f64> = bilinear_sample(feats, grid)
            .into_data()
            .convert::<f64>()
            .to_vec::<f64>()
            .unwrap();
        assert_eq!(got.len(), expected.len());
        // burn fixes a device type's float dtype process-wide at its first use, so another test of
        // this binary may have made it f32: compare at f32 precision.
        for (i, (a, b)) in got.iter().zip(&expected).enumerate() {
            assert!(
                (a - b).abs() < 1e-5 * (1.0 + b.abs()),
                "entry {i}: {a} vs {b}"
            );
        }
    }
}
