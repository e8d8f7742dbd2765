//! Sparse transformer head (paper Sec. 3.4; official `SparseMask2FormerOccHead`; docs/reference_models.md §1,
//! rows "head", "targets", "matching", "losses").
//!
//! 1. **Coarse non-empty filter.** A small MLP on the *detached* mask features (official
//!    `occ_pred_conv`: Linear C→C/2, GroupNorm, ReLU, Linear → `num_classes`) gives coarse semantic
//!    logits per level-0 site; the non-empty score is `1 − softmax[empty]`. Per batch item the sites
//!    are ranked by score and the best `coarse_max_ratio · X·Y·Z` are kept (the official top-k
//!    `int(0.6·X·Y·Z)` over the prediction grid), among them only those with score
//!    `>= coarse_threshold`, at least one. The default threshold 0 is the official behaviour; 0.5 is
//!    the paper's wording ("only preserve voxels classified as non-empty"), which on a tiny frame
//!    measurably hurt training (the classifier sees detached features, drops occupied sites early,
//!    and their masks then fall back to the empty token). All other voxels — dropped sites and voxels
//!    outside the sparse set — share a single learnable **empty token** `p_φ`.
//! 2. **Queries.** `N_q` learned query features and positional embeddings.
//! 3. **Decoder layers** (post-norm, order cross-attn → LN → self-attn → LN → FFN → LN). Layer `i`
//!    attends to memory level `i % n_mem` (the pyramid levels ordered coarse → fine). Memory keys are
//!    the level's active sites (features + 3D sine position encoding + level embedding); attending
//!    only to active sites equals dense attention with the empty voxels masked out.
//! 4. **Masked attention.** Before layer `i`, the previous prediction's mask logits over the level-0
//!    grid (kept sites: their own logit; every other voxel: the empty-token logit) are max-pooled to the
//!    memory level (voxel `o` of level `l` pools the level-0 voxels `[o·2^l, (o+1)·2^l)`, the
//!    official `adaptive_max_pool3d`), and a key is masked for a query when `sigmoid(pooled) < 0.5`,
//!    i.e. `pooled < 0`. Rows with every key masked are unmasked. Masks carry no gradient.
//! 5. **Predictions** (after the queries are initialised and after every layer, shared heads):
//!    `LN` → class logits `Linear → [N_q, C+1]` (last = no object) and mask embedding `MLP C-C-C`;
//!    mask logits = `embed · f_i` for kept sites `[N_q, N_kept]` and `embed · p_φ` `[N_q, 1]`.
//! 6. **Inference**: `einsum(softmax(cls)[:, :C], sigmoid(mask))` → per-voxel class scores on the kept
//!    sites; the model output carries `ln(score)` as logits (same argmax).

use crate::error::ModelError;
use crate::loss::{LossKey, MaskTerm};
use crate::sparseocc::hungarian::hungarian;
use crate::sparseocc::pyramid::parent_coord;
use burn::module::{Initializer, Param};
use burn::nn::{GroupNorm, GroupNormConfig, LayerNorm, LayerNormConfig, Linear, LinearConfig};
use burn::prelude::*;
use burn::tensor::activation::{log_softmax, relu, sigmoid, softmax};
use burn::tensor::TensorData;
use occ_labels::IGNORE;
use occ_sparse::{Coord, SparseTensor};
use std::collections::HashMap;

/// Additive attention bias of a masked key (exp underflows to exactly 0 in f32 and f64).
pub const MASKED_BIAS: f64 = -1.0e9;

/// Configuration of [`MaskHead`].
#[derive(Config, Debug)]
pub struct MaskHeadConfig {
    /// Feature channels `C` of the mask features and memory levels (192 officially).
    pub channels: usize,
    /// Number of classes including empty (class 0).
    pub num_classes: usize,
    /// Number of queries `N_q`.
    #[config(default = 100)]
    pub num_queries: usize,
    /// Number of decoder layers.
    #[config(default = 9)]
    pub num_layers: usize,
    /// Attention heads (must divide `channels`).
    #[config(default = 6)]
    pub num_heads: usize,
    /// FFN hidden channels.
    #[config(default = 1536)]
    pub ffn_channels: usize,
    /// Number of memory levels cycled through by the layers.
    #[config(default = 3)]
    pub num_memory_levels: usize,
    /// Coarse filter: keep only sites whose non-empty probability is at least this (0 = official
    /// top-k only; 0.5 = the paper's "classified as non-empty").
    #[config(default = 0.0)]
    pub coarse_threshold: f64,
    /// Coarse filter: keep at most this fraction of the level-0 grid volume per item.
    #[config(default = 0.6)]
    pub coarse_max_ratio: f64,
    /// GroupNorm groups of the coarse MLP (reduced to a divisor of its width).
    #[config(default = 32)]
    pub norm_groups: usize,
}

fn gcd(a: usize, b: usize) -> usize {
    if b == 0 {
        a
    } else {
        gcd(b, a % b)
    }
}

impl MaskHeadConfig {
    /// Initialises the head; errors on zero sizes or heads not dividing the channels.
    pub fn init<B: occ_sparse::SparseConvBackend>(
        &self,
        device: &B::Device,
    ) -> Result<MaskHead<B>, ModelError> {
        let c = self.channels;
        if c == 0
            || self.num_classes < 2
            || self.num_queries == 0
            || self.num_heads == 0
            || self.ffn_channels == 0
            || self.num_memory_levels == 0
        {
            return Err(ModelError::Config(format!(
                "mask_head.rs: invalid sizes (channels {c}, classes {}, queries {}, heads {}, ffn {}, memory levels {})",
                self.num_classes, self.num_queries, self.num_heads, self.ffn_channels, self.num_memory_levels
            )));
        }
        if !c.is_multiple_of(self.num_heads) {
            return Err(ModelError::Config(format!(
                "mask_head.rs: {} heads do not divide {c} channels",
                self.num_heads
            )));
        }
        if !(0.0..=1.0).contains(&self.coarse_threshold)
            || self.coarse_max_ratio.is_nan()
            || self.coarse_max_ratio <= 0.0
        {
            return Err(ModelError::Config(format!(
                "mask_head.rs: coarse_threshold {} must be in [0, 1], coarse_max_ratio {} > 0",
                self.coarse_threshold, self.coarse_max_ratio
            )));
        }
        let hidden = (c / 2).max(1);
        let groups = gcd(self.norm_groups.max(1), hidden).max(1);
        let lin = |i: usize, o: usize| LinearConfig::new(i, o).init(device);
        let normal = Initializer::Normal {
            mean: 0.0,
            std: 1.0,
        };
        Ok(MaskHead {
            coarse_fc1: lin(c, hidden),
            coarse_norm: GroupNormConfig::new(groups, hidden).init(device),
            coarse_fc2: lin(hidden, self.num_classes),
            empty_token: normal.init([1, c], device),
            query_feat: normal.init([self.num_queries, c], device),
            query_pos: normal.init([self.num_queries, c], device),
            level_embed: normal.init([self.num_memory_levels, c], device),
            layers: (0..self.num_layers)
                .map(|_| DecoderLayer {
                    cross_attn: Attention::new(c, self.num_heads, device),
                    norm1: LayerNormConfig::new(c).init(device),
                    self_attn: Attention::new(c, self.num_heads, device),
                    norm2: LayerNormConfig::new(c).init(device),
                    ffn1: lin(c, self.ffn_channels),
                    ffn2: lin(self.ffn_channels, c),
                    norm3: LayerNormConfig::new(c).init(device),
                })
                .collect(),
            decoder_norm: LayerNormConfig::new(c).init(device),
            class_embed: lin(c, self.num_classes + 1),
            mask_embed: vec![lin(c, c), lin(c, c), lin(c, c)],
            num_classes: self.num_classes,
            coarse_threshold: self.coarse_threshold,
            coarse_max_ratio: self.coarse_max_ratio,
        })
    }
}

/// Multi-head attention with an additive bias `[N_q, N_k]` (0 or [`MASKED_BIAS`]).
#[derive(Module, Debug)]
pub struct Attention<B: Backend> {
    q: Linear<B>,
    k: Linear<B>,
    v: Linear<B>,
    o: Linear<B>,
    heads: usize,
}

impl<B: occ_sparse::SparseConvBackend> Attention<B> {
    /// New attention with `heads` heads over `channels` (heads must divide channels).
    pub fn new(channels: usize, heads: usize, device: &B::Device) -> Self {
        let lin = || LinearConfig::new(channels, channels).init(device);
        Self {
            q: lin(),
            k: lin(),
            v: lin(),
            o: lin(),
            heads,
        }
    }

    /// `softmax(Q Kᵀ/√d + bias) V` per head, then the output projection.
    ///
    /// # Shapes
    /// - query `[N_q, C]`, key `[N_k, C]`, value `[N_k, C]`, bias `[N_q, N_k]` -> `[N_q, C]`
    pub fn forward(
        &self,
        query: Tensor<B, 2>,
        key: Tensor<B, 2>,
        value: Tensor<B, 2>,
        bias: Option<Tensor<B, 2>>,
    ) -> Tensor<B, 2> {
        let [nq, c] = query.dims();
        let nk = key.dims()[0];
        let h = self.heads;
        let dh = c / h;
        let split = |x: Tensor<B, 2>, n: usize| x.reshape([n, h, dh]).swap_dims(0, 1);
        let q = split(crate::profile::linear(&self.q, query), nq);
        let k = split(crate::profile::linear(&self.k, key), nk);
        let v = split(crate::profile::linear(&self.v, value), nk);
        // Scores q·kᵀ and the weighted sum of values, per head.
        crate::profile::add_matmul("attention", 2 * h, nq, dh, nk);
        let mut scores = q.matmul(k.swap_dims(1, 2)).div_scalar((dh as f64).sqrt());
        if let Some(b) = bias {
            scores = scores + b.unsqueeze_dim(0);
        }
        let attn = softmax(scores, 2);
        let out = attn.matmul(v).swap_dims(0, 1).reshape([nq, c]);
        crate::profile::linear(&self.o, out)
    }
}

/// One transformer decoder layer (cross-attn → LN → self-attn → LN → FFN → LN).
#[derive(Module, Debug)]
pub struct DecoderLayer<B: Backend> {
    /// Masked cross-attention to the memory level.
    pub cross_attn: Attention<B>,
    norm1: LayerNorm<B>,
    self_attn: Attention<B>,
    norm2: LayerNorm<B>,
    ffn1: Linear<B>,
    ffn2: Linear<B>,
    norm3: LayerNorm<B>,
}

impl<B: occ_sparse::SparseConvBackend> DecoderLayer<B> {
    /// Updates the queries.
    ///
    /// # Shapes
    /// - queries, query_pos `[N_q, C]`; memory, memory_pos `[M, C]`; bias `[N_q, M]` -> `[N_q, C]`
    pub fn forward(
        &self,
        queries: Tensor<B, 2>,
        query_pos: Tensor<B, 2>,
        memory: Tensor<B, 2>,
        memory_pos: Tensor<B, 2>,
        bias: Option<Tensor<B, 2>>,
    ) -> Tensor<B, 2> {
        let ca = self.cross_attn.forward(
            queries.clone() + query_pos.clone(),
            memory.clone() + memory_pos,
            memory,
            bias,
        );
        let q = self.norm1.forward(queries + ca);
        let qp = q.clone() + query_pos;
        let sa = self.self_attn.forward(qp.clone(), qp, q.clone(), None);
        let q = self.norm2.forward(q + sa);
        let ff = crate::profile::linear(
            &self.ffn2,
            relu(crate::profile::linear(&self.ffn1, q.clone())),
        );
        self.norm3.forward(q + ff)
    }
}

/// The sparse transformer head (see the module documentation).
#[derive(Module, Debug)]
pub struct MaskHead<B: Backend> {
    coarse_fc1: Linear<B>,
    coarse_norm: GroupNorm<B>,
    coarse_fc2: Linear<B>,
    /// The learnable empty token `p_φ` `[1, C]`.
    pub empty_token: Param<Tensor<B, 2>>,
    query_feat: Param<Tensor<B, 2>>,
    query_pos: Param<Tensor<B, 2>>,
    level_embed: Param<Tensor<B, 2>>,
    /// Decoder layers.
    pub layers: Vec<DecoderLayer<B>>,
    decoder_norm: LayerNorm<B>,
    class_embed: Linear<B>,
    mask_embed: Vec<Linear<B>>,
    num_classes: usize,
    coarse_threshold: f64,
    coarse_max_ratio: f64,
}

/// One set prediction of the head.
#[derive(Clone, Debug)]
pub struct QueryPrediction<B: Backend> {
    /// Class logits `[N_q, C+1]` (last column: no object).
    pub class_logits: Tensor<B, 2>,
    /// Mask logits on the kept sites `[N_q, N_kept]` (column order = [`HeadItem::kept`]).
    pub mask_kept: Tensor<B, 2>,
    /// Mask logit of the empty token `[N_q, 1]`, used for every other voxel.
    pub mask_empty: Tensor<B, 2>,
}

/// Head results for one batch item.
#[derive(Clone, Debug)]
pub struct HeadItem<B: Backend> {
    /// Batch index.
    pub batch: usize,
    /// Rows of the mask-feature tensor kept by the coarse filter (ascending).
    pub kept: Vec<usize>,
    /// Predictions: after query initialisation, then after each decoder layer.
    pub predictions: Vec<QueryPrediction<B>>,
}

/// Output of [`MaskHead::forward`].
#[derive(Clone, Debug)]
pub struct HeadOutput<B: Backend> {
    /// Coarse semantic logits on every level-0 site `[N_0, num_classes]`.
    pub coarse_logits: Tensor<B, 2>,
    /// Per batch item results.
    pub items: Vec<HeadItem<B>>,
    /// Kept sites `(b, x, y, z)` of all items (item order, then ascending row).
    pub kept_coords: Vec<Coord>,
    /// `ln` of the per-voxel class scores of the last prediction on the kept sites
    /// `[N_kept_total, num_classes]`.
    pub log_scores: Tensor<B, 2>,
    /// Counts for logs (`head.kept`, `head.l{i}.all_masked_rows`, ...).
    pub stats: Vec<(String, usize)>,
}

/// A memory level for the head: a pyramid level and its stride (in level-0 voxels).
#[derive(Clone, Debug)]
pub struct MemoryLevel<B: Backend> {
    /// Features `[M, C]` on the level's sites.
    pub tensor: SparseTensor<B>,
    /// Stride relative to the mask-feature grid (`2^l`).
    pub stride: usize,
}

/// 3D sine position encoding (DETR style, normalised to `2π`, temperature 10000): for each axis
/// `npf = 2·⌊C/6⌋` features of `(o + 0.5)/dims · 2π` (sin on even, cos on odd feature indices), axes
/// concatenated x, y, z, remaining channels zero. Row-major `[N, C]`.
pub fn sine_position_encoding(coords: &[Coord], dims: [usize; 3], channels: usize) -> Vec<f32> {
    let npf = 2 * (channels / 6);
    let mut out = vec![0f32; coords.len() * channels];
    if npf == 0 {
        return out;
    }
    let two_pi = 2.0 * std::f64::consts::PI;
    let dim_t: Vec<f64> = (0..npf)
        .map(|i| 10000f64.powf((2 * (i / 2)) as f64 / npf as f64))
        .collect();
    for (n, c) in coords.iter().enumerate() {
        for a in 0..3 {
            let pos = (c[a + 1] as f64 + 0.5) / dims[a].max(1) as f64 * two_pi;
            for (i, dt) in dim_t.iter().enumerate() {
                let x = pos / dt;
                out[n * channels + a * npf + i] = if i % 2 == 0 { x.sin() } else { x.cos() } as f32;
            }
        }
    }
    out
}

/// Which level-0 voxels each memory site pools (host-side structure for the attention masks).
#[derive(Clone, Debug)]
pub struct PoolMap {
    /// For each level-0 row of the item (in item order): the local memory index of its parent, if the
    /// parent is an active memory site.
    pub parent: Vec<Option<usize>>,
    /// For each memory site of the item: how many level-0 grid voxels its block covers.
    pub block_volume: Vec<usize>,
    /// Number of memory sites of the item.
    pub num_sites: usize,
}

impl PoolMap {
    /// Builds the map for one item.
    /// - `level0`: coordinates of the item's level-0 sites; `level0_dims`: level-0 grid shape
    /// - `memory`: coordinates of the item's memory sites; `stride`, `memory_dims`: the level's
    pub fn new(
        level0: &[Coord],
        level0_dims: [usize; 3],
        memory: &[Coord],
        stride: usize,
        memory_dims: [usize; 3],
    ) -> Self {
        let index: HashMap<Coord, usize> =
            memory.iter().enumerate().map(|(i, &c)| (c, i)).collect();
        let parent = level0
            .iter()
            .map(|&c| index.get(&parent_coord(c, 1, stride, memory_dims)).copied())
            .collect();
        // Level-0 voxels per memory voxel along each axis, with the last memory voxel of a
        // collapsed axis absorbing the remainder.
        let stride = stride.max(1);
        let counts: Vec<Vec<usize>> = (0..3)
            .map(|a| {
                let mut v = vec![0usize; memory_dims[a]];
                for x in 0..level0_dims[a] {
                    if let Some(c) = v.get_mut((x / stride).min(memory_dims[a].saturating_sub(1))) {
                        *c += 1;
                    }
                }
                v
            })
            .collect();
        let block_volume = memory
            .iter()
            .map(|c| {
                (0..3)
                    .map(|a| {
                        counts[a]
                            .get(c[a + 1].max(0) as usize)
                            .copied()
                            .unwrap_or(0)
                    })
                    .product()
            })
            .collect();
        Self {
            parent,
            block_volume,
            num_sites: memory.len(),
        }
    }
}

/// Attention bias `[N_q, M]` (row-major) from the previous mask logits (module doc, step 4).
///
/// - `kept_logits`: `[N_q, N_kept]` row-major; `kept_rows[j]` = the item-local level-0 row of column j
/// - `empty_logits`: `[N_q]`
///
/// Returns the bias (0 or [`MASKED_BIAS`]) and the number of rows that were fully masked (and hence
/// unmasked).
pub fn attention_bias(
    kept_logits: &[f32],
    kept_rows: &[usize],
    empty_logits: &[f32],
    map: &PoolMap,
) -> (Vec<f32>, usize) {
    let nq = empty_logits.len();
    let m = map.num_sites;
    let nk = kept_rows.len();
    let mut bias = vec![MASKED_BIAS as f32; nq * m];
    // Kept children per memory site.
    let mut kept_children = vec![0usize; m];
    let col_parent: Vec<Option<usize>> = kept_rows
        .iter()
        .map(|&r| map.parent.get(r).copied().flatten())
        .collect();
    for p in col_parent.iter().flatten() {
        kept_children[*p] += 1;
    }
    let mut all_masked = 0;
    for q in 0..nq {
        let mut pooled = vec![f32::NEG_INFINITY; m];
        for (s, p) in pooled.iter_mut().enumerate() {
            if kept_children[s] < map.block_volume[s] {
                *p = empty_logits[q];
            }
        }
        for (j, par) in col_parent.iter().enumerate() {
            if let Some(s) = *par {
                let v = kept_logits[q * nk + j];
                if v > pooled[s] {
                    pooled[s] = v;
                }
            }
        }
        let row = &mut bias[q * m..(q + 1) * m];
        let mut any = false;
        for (b, &p) in row.iter_mut().zip(&pooled) {
            if p >= 0.0 {
                *b = 0.0;
                any = true;
            }
        }
        if !any {
            row.iter_mut().for_each(|b| *b = 0.0);
            all_masked += 1;
        }
    }
    (bias, all_masked)
}

fn to_f32<B: Backend, const D: usize>(t: Tensor<B, D>) -> Result<Vec<f32>, ModelError> {
    t.into_data()
        .convert::<f32>()
        .to_vec::<f32>()
        .map_err(|e| ModelError::Numerical(format!("mask_head.rs: tensor readback: {e:?}")))
}

fn index<B: Backend>(v: &[usize], device: &B::Device) -> Tensor<B, 1, Int> {
    let data: Vec<i64> = v.iter().map(|&x| x as i64).collect();
    Tensor::from_data(TensorData::new(data, [v.len()]), device)
}

impl<B: occ_sparse::SparseConvBackend> MaskHead<B> {
    /// Number of classes (including empty).
    pub fn num_classes(&self) -> usize {
        self.num_classes
    }

    /// Class logits and mask logits of the current queries.
    fn predict(&self, queries: Tensor<B, 2>, kept_feats: &Tensor<B, 2>) -> QueryPrediction<B> {
        let decoded = self.decoder_norm.forward(queries);
        let class_logits = crate::profile::linear(&self.class_embed, decoded.clone());
        let n = self.mask_embed.len();
        let mut e = decoded;
        for (i, l) in self.mask_embed.iter().enumerate() {
            e = crate::profile::linear(l, e);
            if i + 1 < n {
                e = relu(e);
            }
        }
        let [nq, c] = e.dims();
        crate::profile::add_matmul("mask", 1, nq, c, kept_feats.dims()[0] + 1);
        let mask_kept = e.clone().matmul(kept_feats.clone().transpose());
        let mask_empty = e.matmul(self.empty_token.val().transpose());
        QueryPrediction {
            class_logits,
            mask_kept,
            mask_empty,
        }
    }

    /// Coarse semantic logits on the mask features (detached, official `occ_pred_conv`).
    pub fn coarse_logits(&self, mask_features: &Tensor<B, 2>) -> Tensor<B, 2> {
        let x = crate::profile::linear(&self.coarse_fc1, mask_features.clone().detach());
        crate::profile::linear(&self.coarse_fc2, relu(self.coarse_norm.forward(x)))
    }

    /// Runs the head.
    ///
    /// # Shapes
    /// - mask_features: `N_0` level-0 sites x C; memory: levels ordered coarse → fine, `M_l x C`
    pub fn forward(
        &self,
        mask_features: &SparseTensor<B>,
        memory: &[MemoryLevel<B>],
    ) -> Result<HeadOutput<B>, ModelError> {
        let device = mask_features.device();
        let n0 = mask_features.num_active();
        if n0 == 0 {
            return Err(ModelError::Input("mask_head.rs: no level-0 site".into()));
        }
        if memory.is_empty() {
            return Err(ModelError::Input("mask_head.rs: no memory level".into()));
        }
        let n_levels = self.level_embed.val().dims()[0];
        let c = mask_features.channels();
        let batch_size = mask_features.batch_size();
        let dims0 = mask_features.spatial_shape();
        let volume: usize = dims0.iter().product();
        let max_keep = ((self.coarse_max_ratio * volume as f64) as usize).max(1);

        let coarse_logits = self.coarse_logits(mask_features.feats());
        let nonempty: Vec<f32> = to_f32(
            softmax(coarse_logits.clone().detach(), 1)
                .slice([0..n0, 0..1])
                .neg()
                .add_scalar(1.0)
                .reshape([n0]),
        )?;

        // Rows per batch item.
        let rows_of = |coords: &[Coord]| {
            let mut per = vec![Vec::new(); batch_size];
            for (r, c) in coords.iter().enumerate() {
                if let Some(v) = per.get_mut(c[0] as usize) {
                    v.push(r);
                }
            }
            per
        };
        let coords0 = mask_features.coords();
        let rows0 = rows_of(coords0);
        let mem_rows: Vec<Vec<Vec<usize>>> =
            memory.iter().map(|m| rows_of(m.tensor.coords())).collect();

        let mut stats = Vec::new();
        let mut items = Vec::with_capacity(batch_size);
        let mut kept_coords = Vec::new();
        let mut log_scores = Vec::new();
        let query_feat = self.query_feat.val();
        let query_pos = self.query_pos.val();
        let level_embed = self.level_embed.val();
        for b in 0..batch_size {
            let r0 = &rows0[b];
            if r0.is_empty() {
                return Err(ModelError::Input(format!(
                    "mask_head.rs: batch item {b} has no level-0 site"
                )));
            }
            // Coarse filter.
            let mut order: Vec<usize> = (0..r0.len()).collect();
            order.sort_by(|&a, &bb| {
                nonempty[r0[bb]]
                    .total_cmp(&nonempty[r0[a]])
                    .then(a.cmp(&bb))
            });
            let mut kept_local: Vec<usize> = order
                .iter()
                .copied()
                .filter(|&i| nonempty[r0[i]] as f64 >= self.coarse_threshold)
                .take(max_keep)
                .collect();
            if kept_local.is_empty() {
                kept_local.push(order[0]);
            }
            kept_local.sort_unstable();
            let kept: Vec<usize> = kept_local.iter().map(|&i| r0[i]).collect();
            stats.push((format!("head.b{b}.kept"), kept.len()));
            let kept_feats = mask_features
                .feats()
                .clone()
                .select(0, index::<B>(&kept, &device));

            // Memory of this item.
            let item_coords0: Vec<Coord> = r0.iter().map(|&r| coords0[r]).collect();
            let mut mem_feats = Vec::with_capacity(memory.len());
            let mut mem_pos = Vec::with_capacity(memory.len());
            let mut maps = Vec::with_capacity(memory.len());
            for (li, m) in memory.iter().enumerate() {
                let rows = &mem_rows[li][b];
                if rows.is_empty() {
                    return Err(ModelError::Input(format!(
                        "mask_head.rs: batch item {b} has no site on memory level {li}"
                    )));
                }
                let mc: Vec<Coord> = rows.iter().map(|&r| m.tensor.coords()[r]).collect();
                let dims = m.tensor.spatial_shape();
                let pe = sine_position_encoding(&mc, dims, c);
                let pe = Tensor::<B, 2>::from_data(TensorData::new(pe, [mc.len(), c]), &device)
                    + level_embed
                        .clone()
                        .slice([(li % n_levels)..(li % n_levels + 1), 0..c]);
                mem_feats.push(
                    m.tensor
                        .feats()
                        .clone()
                        .select(0, index::<B>(rows, &device)),
                );
                mem_pos.push(pe);
                maps.push(PoolMap::new(&item_coords0, dims0, &mc, m.stride, dims));
            }

            let mut q = query_feat.clone();
            let mut predictions = Vec::with_capacity(self.layers.len() + 1);
            predictions.push(self.predict(q.clone(), &kept_feats));
            for (i, layer) in self.layers.iter().enumerate() {
                let li = i % memory.len();
                let prev = predictions.last().ok_or_else(|| {
                    ModelError::Numerical("mask_head.rs: missing prediction".into())
                })?;
                let kl = to_f32(prev.mask_kept.clone().detach())?;
                let el = to_f32(prev.mask_empty.clone().detach())?;
                let (bias, all_masked) = attention_bias(&kl, &kept_local, &el, &maps[li]);
                stats.push((format!("head.b{b}.l{i}.all_masked_rows"), all_masked));
                let nq = el.len();
                let bias = Tensor::<B, 2>::from_data(
                    TensorData::new(bias, [nq, maps[li].num_sites]),
                    &device,
                );
                q = layer.forward(
                    q,
                    query_pos.clone(),
                    mem_feats[li].clone(),
                    mem_pos[li].clone(),
                    Some(bias),
                );
                predictions.push(self.predict(q.clone(), &kept_feats));
            }
            let last = predictions
                .last()
                .ok_or_else(|| ModelError::Numerical("mask_head.rs: missing prediction".into()))?;
            let nc = self.num_classes;
            let nq = last.class_logits.dims()[0];
            let probs = softmax(last.class_logits.clone(), 1).slice([0..nq, 0..nc]);
            let nk = last.mask_kept.dims()[1];
            crate::profile::add_matmul("mask", 1, nk, nq, nc);
            let scores = sigmoid(last.mask_kept.clone()).transpose().matmul(probs);
            log_scores.push(scores.clamp_min(1e-12).log());
            kept_coords.extend(kept.iter().map(|&r| coords0[r]));
            items.push(HeadItem {
                batch: b,
                kept,
                predictions,
            });
        }
        Ok(HeadOutput {
            coarse_logits,
            items,
            kept_coords,
            log_scores: Tensor::cat(log_scores, 0),
            stats,
        })
    }
}

/// Weights and options of the set-prediction losses (docs/losses.md §5).
#[derive(Clone, Debug)]
pub struct SetLossWeights {
    /// Class cross-entropy weight (2.0).
    pub class: f64,
    /// Mask binary cross-entropy weight (5.0).
    pub mask: f64,
    /// Dice weight (5.0).
    pub dice: f64,
    /// Class weight of "no object" (0.1).
    pub no_object: f64,
    /// Points sampled per item for matching and mask losses (50,176); all labelled voxels when fewer.
    pub num_points: usize,
}

/// Host matching costs `2·class + 5·BCE + 5·dice` `[N_q, G]` between predictions and binary targets on
/// sampled points (class cost = −softmax probability of the target class; BCE = mean over points;
/// dice = `1 − (2·Σσ(x)t + 1)/(Σσ(x) + Σt + 1)`), computed with detached tensors.
///
/// # Shapes
/// - class_logits `[N_q, C+1]`, point_logits `[N_q, P]`, targets `[G, P]`, labels `G`
pub fn matching_cost<B: Backend>(
    class_logits: Tensor<B, 2>,
    point_logits: Tensor<B, 2>,
    targets: Tensor<B, 2>,
    labels: &[usize],
    weights: &SetLossWeights,
) -> Result<Vec<f64>, ModelError> {
    let [nq, _] = class_logits.dims();
    let [_, p] = point_logits.dims();
    let g = labels.len();
    let probs = to_f32(softmax(class_logits.detach(), 1))?;
    let ncls = probs.len() / nq.max(1);
    let x = point_logits.detach();
    let t = targets.detach();
    // softplus(-x) = BCE against 1, softplus(x) = BCE against 0 (stable forms).
    let sp = |z: Tensor<B, 2>| relu(z.clone()) + z.abs().neg().exp().add_scalar(1.0).log();
    let pos = sp(x.clone().neg());
    let neg = sp(x.clone());
    let bce = (pos.matmul(t.clone().transpose())
        + neg.matmul(t.clone().neg().add_scalar(1.0).transpose()))
    .div_scalar(p.max(1) as f64);
    let s = sigmoid(x);
    let numer = s
        .clone()
        .matmul(t.clone().transpose())
        .mul_scalar(2.0)
        .add_scalar(1.0);
    let denom = s.sum_dim(1) + t.sum_dim(1).transpose() + 1.0;
    let dice = (numer / denom).neg().add_scalar(1.0);
    let bce = to_f32(bce)?;
    let dice = to_f32(dice)?;
    let mut cost = vec![0.0f64; nq * g];
    for q in 0..nq {
        for (j, &l) in labels.iter().enumerate() {
            let pc = probs.get(q * ncls + l).copied().unwrap_or(0.0) as f64;
            cost[q * g + j] = weights.class * (-pc)
                + weights.mask * bce[q * g + j] as f64
                + weights.dice * dice[q * g + j] as f64;
        }
    }
    Ok(cost)
}

/// Deterministic SplitMix64 stream (point sampling without an RNG dependency).
struct SplitMix(u64);
impl SplitMix {
    fn next_f64(&mut self) -> f64 {
        self.0 = self.0.wrapping_add(0x9E37_79B9_7F4A_7C15);
        let mut z = self.0;
        z = (z ^ (z >> 30)).wrapping_mul(0xBF58_476D_1CE4_E5B9);
        z = (z ^ (z >> 27)).wrapping_mul(0x94D0_49BB_1331_11EB);
        z ^= z >> 31;
        ((z >> 11) as f64 + 0.5) / (1u64 << 53) as f64
    }
}

/// Points (flat voxel indices of the level-0 grid) supervising one item: every labelled voxel (label
/// != 255) when there are at most `num_points`, otherwise `num_points` drawn without replacement with
/// probability proportional to the class weight of their label (a stand-in for the official
/// `(f_max/f_c)^0.25` frequency weights; Efraimidis–Spirakis keys, seeded by the labels so the draw is
/// deterministic per frame). Sorted ascending.
pub fn sample_points(labels: &[u8], class_weights: &[f64], num_points: usize) -> Vec<usize> {
    let valid: Vec<usize> = (0..labels.len()).filter(|&i| labels[i] != IGNORE).collect();
    if valid.len() <= num_points {
        return valid;
    }
    let seed = labels.iter().fold(0xC0FF_EE00u64, |h, &l| {
        h.wrapping_mul(31).wrapping_add(l as u64)
    });
    let mut rng = SplitMix(seed);
    let mut keyed: Vec<(f64, usize)> = valid
        .into_iter()
        .map(|i| {
            let w = class_weights
                .get(labels[i] as usize)
                .copied()
                .unwrap_or(1.0)
                .max(1e-6);
            (rng.next_f64().ln() / w, i)
        })
        .collect();
    keyed.sort_by(|a, b| b.0.total_cmp(&a.0).then(a.1.cmp(&b.1)));
    let mut out: Vec<usize> = keyed.into_iter().take(num_points).map(|(_, i)| i).collect();
    out.sort_unstable();
    out
}

/// Numerically stable BCE with logits, elementwise.
fn bce_with_logits<B: Backend>(x: Tensor<B, 2>, t: Tensor<B, 2>) -> Tensor<B, 2> {
    relu(x.clone()) - x.clone() * t + x.abs().neg().exp().add_scalar(1.0).log()
}

impl<B: Backend> HeadOutput<B> {
    /// Set-prediction losses of every prediction (Hungarian matching per item and prediction),
    /// averaged over batch items. Names: `mask_cls`, `mask_bce`, `mask_dice` for the last prediction
    /// and `d{i}.mask_cls` ... for the earlier ones (`i = 0` is the prediction before the first layer).
    ///
    /// - `labels`: per item, the level-0 grid labels (flat C order over `dims`, 0 empty, 255 ignore)
    /// - `class_weights`: `num_classes` weights (class 0 = empty included)
    ///
    /// Targets: one binary mask per class present among the item's labelled voxels (empty included).
    /// Class loss: weighted cross-entropy over all queries (no-object weight `weights.no_object`),
    /// normalised by the sum of the target weights. Mask BCE (mean over points) and dice (eps 1) over
    /// the matched queries, each weighted by its class weight and normalised by their sum.
    pub fn set_losses(
        &self,
        labels: &[Vec<u8>],
        dims: [usize; 3],
        class_weights: &[f64],
        weights: &SetLossWeights,
    ) -> Result<Vec<(LossKey, Tensor<B, 1>)>, ModelError> {
        let nc = class_weights.len();
        let [dx, dy, dz] = dims;
        let n_pred = self.items.first().map(|i| i.predictions.len()).unwrap_or(0);
        let mut sums: Vec<[Option<Tensor<B, 1>>; 3]> =
            (0..n_pred).map(|_| [None, None, None]).collect();
        let n_items = self.items.len();
        for item in &self.items {
            let lab = labels.get(item.batch).ok_or_else(|| {
                ModelError::Input(format!(
                    "mask_head.rs: no labels for batch item {}",
                    item.batch
                ))
            })?;
            if lab.len() != dx * dy * dz {
                return Err(ModelError::Input(format!(
                    "mask_head.rs: {} labels for a {dims:?} grid",
                    lab.len()
                )));
            }
            if let Some(&bad) = lab.iter().find(|&&l| l != IGNORE && l as usize >= nc) {
                return Err(ModelError::Input(format!(
                    "mask_head.rs: label {bad} >= {nc} classes"
                )));
            }
            let first = item
                .predictions
                .first()
                .ok_or_else(|| ModelError::Numerical("mask_head.rs: no prediction".into()))?;
            let device = first.class_logits.device();
            let nq = first.class_logits.dims()[0];
            let nk = item.kept.len();
            // Kept site -> column.
            let coords = &self.kept_coords;
            let offset: usize = self
                .items
                .iter()
                .take_while(|i| i.batch != item.batch)
                .map(|i| i.kept.len())
                .sum();
            let mut col_of: HashMap<usize, usize> = HashMap::with_capacity(nk);
            for j in 0..nk {
                let c = coords[offset + j];
                col_of.insert((c[1] as usize * dy + c[2] as usize) * dz + c[3] as usize, j);
            }
            let points = sample_points(lab, class_weights, weights.num_points);
            if points.is_empty() {
                continue;
            }
            let p = points.len();
            let cols: Vec<usize> = points
                .iter()
                .map(|v| col_of.get(v).copied().unwrap_or(nk))
                .collect();
            let mut present = vec![false; nc];
            for &l in lab.iter().filter(|&&l| l != IGNORE) {
                present[l as usize] = true;
            }
            let classes: Vec<usize> = (0..nc).filter(|&c| present[c]).collect();
            let g = classes.len();
            let mut tgt = vec![0f32; g * p];
            for (j, &cls) in classes.iter().enumerate() {
                for (k, &v) in points.iter().enumerate() {
                    if lab[v] as usize == cls {
                        tgt[j * p + k] = 1.0;
                    }
                }
            }
            let targets = Tensor::<B, 2>::from_data(TensorData::new(tgt.clone(), [g, p]), &device);
            let col_idx = index::<B>(&cols, &device);
            for (pi, pred) in item.predictions.iter().enumerate() {
                let all = Tensor::cat(vec![pred.mask_kept.clone(), pred.mask_empty.clone()], 1);
                let point_logits = all.select(1, col_idx.clone());
                let cost = matching_cost(
                    pred.class_logits.clone(),
                    point_logits.clone(),
                    targets.clone(),
                    &classes,
                    weights,
                )?;
                let pairs = hungarian(&cost, nq, g)?;
                // Class loss.
                let mut target_cls = vec![nc; nq];
                for &(q, j) in &pairs {
                    target_cls[q] = classes[j];
                }
                let wt = |c: usize| {
                    if c == nc {
                        weights.no_object
                    } else {
                        class_weights[c]
                    }
                };
                let wsum: f64 = target_cls.iter().map(|&c| wt(c)).sum();
                let mut onehot_w = vec![0f32; nq * (nc + 1)];
                for (q, &c) in target_cls.iter().enumerate() {
                    onehot_w[q * (nc + 1) + c] = (wt(c) / wsum.max(1e-12)) as f32;
                }
                let ow =
                    Tensor::<B, 2>::from_data(TensorData::new(onehot_w, [nq, nc + 1]), &device);
                let l_cls = (log_softmax(pred.class_logits.clone(), 1) * ow).sum().neg();
                // Mask losses on matched queries.
                let qs: Vec<usize> = pairs.iter().map(|&(q, _)| q).collect();
                let js: Vec<usize> = pairs.iter().map(|&(_, j)| j).collect();
                let m = pairs.len();
                let xw: Vec<f32> = js
                    .iter()
                    .map(|&j| class_weights[classes[j]] as f32)
                    .collect();
                let wsum_m: f32 = xw.iter().sum::<f32>().max(1e-12);
                let mw = Tensor::<B, 1>::from_data(
                    TensorData::new(xw.iter().map(|w| w / wsum_m).collect::<Vec<_>>(), [m]),
                    &device,
                );
                let x = point_logits.select(0, index::<B>(&qs, &device));
                let t = targets.clone().select(0, index::<B>(&js, &device));
                let bce = bce_with_logits(x.clone(), t.clone())
                    .mean_dim(1)
                    .reshape([m]);
                let s = sigmoid(x);
                let numer = (s.clone() * t.clone())
                    .sum_dim(1)
                    .mul_scalar(2.0)
                    .add_scalar(1.0);
                let denom = s.sum_dim(1) + t.sum_dim(1) + 1.0;
                let dice = (numer / denom).neg().add_scalar(1.0).reshape([m]);
                let l_bce = (bce * mw.clone()).sum();
                let l_dice = (dice * mw).sum();
                let terms = [
                    l_cls.mul_scalar(weights.class / n_items as f64),
                    l_bce.mul_scalar(weights.mask / n_items as f64),
                    l_dice.mul_scalar(weights.dice / n_items as f64),
                ];
                for (slot, t) in sums[pi].iter_mut().zip(terms) {
                    *slot = Some(match slot.take() {
                        Some(acc) => acc + t,
                        None => t,
                    });
                }
            }
        }
        let mut out = Vec::new();
        for (pi, s) in sums.into_iter().enumerate() {
            let aux = (pi + 1 != n_pred).then_some(pi);
            for (term, t) in [MaskTerm::Class, MaskTerm::Bce, MaskTerm::Dice]
                .into_iter()
                .zip(s)
            {
                if let Some(t) = t {
                    out.push((LossKey::Mask { aux, term }, t));
                }
            }
        }
        Ok(out)
    }
}
