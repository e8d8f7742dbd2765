//! Sparse anchor voxel generation (SparseOcc++, paper Sec. 4.2 "Sparse Anchor Voxel Generation").
//!
//! **Coarse-to-fine** (default, the paper's pyramidal strategy): levels `r = 0, 1, 2` at `1/8, 1/4, 1/2` of
//! the full label resolution.
//! 1. Level 0: the dense candidate grid `full/8` with one learned embedding per voxel (shared by all
//!    batch items) plus a position encoding.
//! 2. At every level: DCA over the image features ([`crate::sparseocc_pp::dca`]) → lightweight MLP `M` → class logits
//!    `[N, num_classes]` (class 0 = empty). The paper supervises these with "the same occupancy loss" as
//!    the final output (CE + Lovasz + geo/sem scal, `L_anchor`), which needs class logits; the
//!    occupancy score used for ranking is the log-odds of "not empty",
//!    `logsumexp(logits[1..]) - logits[0]` (monotone in `1 - p_empty`, SparseOcc's coarse top-k score).
//! 3. Top-k per batch item: keep `k = clamp(round(ratio_r · n_r), 1, n_r)` of the `n_r` CANDIDATES of
//!    that level. The paper: "we retain the top {1/5, 1/10} candidates for levels 1 and 2", and its
//!    recursion `Ã^r = Top-k(Split(Ã^{r-1}), …)` starts from the dense `Ã^0` without pruning it, so the
//!    default ratios are `[1.0, 0.2, 0.1]` (level 0 keeps everything; its DCA still gives the children
//!    their image context, and its logits are supervised). With these, level 1 sees the dense `full/4`
//!    grid and keeps 1/5 of it, level 2 sees `8/5` of that (1/5 of the `full/2` grid) and keeps 1/10,
//!    i.e. the anchors are 2 % of the `full/2` grid (5243 of 128×128×16 for SemanticKITTI).
//! 4. Split (levels 1, 2): every kept voxel becomes its 8 children `(2x+dx, 2y+dy, 2z+dz)`; a child's
//!    feature is its parent's (after DCA) plus a learned child-position embedding `E_r[4dx+2dy+dz]`.
//!
//! The kept level-2 voxels with their features are the anchors `A`.
//!
//! **Uniform** (ablation, paper Tab. "Sparse Anchor Voxel Generation"): the same number of anchors as
//! the coarse-to-fine chain would produce, placed evenly over the `full/2` grid of each batch item
//! (flat `[x][y][z]` index `floor((i + 0.5)·X·Y·Z/k)`, deterministic). Their initial feature is the
//! level-0 embedding of the `full/8` voxel containing them plus the position encoding; one DCA + MLP
//! stage gives features and (supervised) logits, and all of them are kept.
//!
//! The position encoding is an MLP `3 → D → D` on the voxel centre normalised to `(0, 1)` per axis
//! (`(idx + 0.5)/dims`), so the same physical position gets the same code at every level.

use crate::batch::Batch;
use crate::sparseocc_pp::dca::ViewHits;
use crate::sparseocc_pp::dca::{
    project_column_bases, project_queries, DcaConfig, DeformableCrossAttention, FeatureRows,
};
use crate::sparseocc_pp::extras::depth_gate::DepthMap;
use crate::sparseocc_pp::extras::depth_oracle::DepthOracle;
use crate::sparseocc_pp::extras::scan_oracle::ScanOracle;

/// Height (metres, LiDAR frame) of the column bases of option `dca_column_base`: the centre of the
/// lowest layer of the full-resolution grid `full` (the synthetic ground; 0.37 m under SemanticKITTI's
/// ground at -1.73 m).
pub(crate) fn column_floor_z_m(full: &occ_geometry::VoxelGrid) -> f64 {
    full.origin_m[2] + 0.5 * full.voxel_size_m
}

/// The gate of every hit: the learned depth map's ([`crate::sparseocc_pp::extras::depth_gate`]), the diagnostic oracle's
/// ([`crate::sparseocc_pp::extras::depth_oracle`]) for voxels of `voxel_m`, their product when both are on, or `None`.
pub(crate) fn combined_gate<B: Backend>(
    depth: Option<&DepthMap<B>>,
    oracle: Option<&DepthOracle>,
    hits: &ViewHits,
    voxel_m: f64,
    device: &B::Device,
) -> Result<Option<Tensor<B, 1>>, ModelError> {
    let learned = depth.map(|m| m.hit_gate(hits)).transpose()?;
    let oracle = oracle
        .map(|o| o.hit_gate::<B>(hits, voxel_m, device))
        .transpose()?;
    Ok(match (learned, oracle) {
        (Some(a), Some(b)) => Some(a * b),
        (a, b) => a.or(b),
    })
}
use crate::error::ModelError;
use crate::kernels::ModelBackend;
use burn::module::Param;
use burn::nn::{Initializer, Linear, LinearConfig};
use burn::prelude::*;
use burn::tensor::TensorData;
use occ_sparse::backend::index_tensor;
use occ_sparse::{Coord, SparseTensor};

/// How anchors are generated.
#[derive(Config, Debug, Copy, PartialEq, Eq)]
pub enum AnchorMode {
    /// The paper's pyramidal coarse-to-fine generation (DCA + score + top-k + split at 1/8, 1/4, 1/2).
    CoarseToFine,
    /// Ablation: evenly spaced anchors on the 1/2-resolution grid, same count.
    Uniform,
}

/// Downsampling factor (full-resolution voxels per axis) of anchor level `r` (0, 1, 2 → 8, 4, 2).
pub const LEVEL_FACTORS: [usize; 3] = [8, 4, 2];

/// Predictions of one anchor level, for `L_anchor`.
#[derive(Clone, Debug)]
pub struct LevelPrediction<B: Backend> {
    /// Candidate voxels `(b, x, y, z)` on the level grid `dims` (all candidates, before top-k).
    pub coords: Vec<Coord>,
    /// Level grid `full_dims / factor`.
    pub dims: [usize; 3],
    /// Full-resolution voxels per level voxel along each axis (8, 4 or 2).
    pub factor: usize,
    /// Class logits `[N, num_classes]` (class 0 = empty).
    pub logits: Tensor<B, 2>,
    /// Rows of `coords` that were kept (ascending).
    pub kept: Vec<usize>,
}

/// Learned position encoding: MLP on normalised voxel centres.
#[derive(Module, Debug)]
pub struct PositionEncoding<B: Backend> {
    /// `3 → D`.
    pub fc1: Linear<B>,
    /// `D → D`.
    pub fc2: Linear<B>,
}

impl<B: Backend> PositionEncoding<B> {
    /// New encoding of width `d`.
    pub fn new(d: usize, device: &B::Device) -> Self {
        Self {
            fc1: LinearConfig::new(3, d).init(device),
            fc2: LinearConfig::new(d, d).init(device),
        }
    }
}

impl<B: ModelBackend> PositionEncoding<B> {
    /// Codes `[N, D]` of voxels `(b, x, y, z)` on a grid of `dims`.
    pub fn encode(&self, coords: &[Coord], dims: [usize; 3], device: &B::Device) -> Tensor<B, 2> {
        let mut v = Vec::with_capacity(coords.len() * 3);
        for c in coords {
            for a in 0..3 {
                v.push((c[a + 1] as f64 + 0.5) / dims[a].max(1) as f64);
            }
        }
        let x = Tensor::<B, 2>::from_data(TensorData::new(v, [coords.len(), 3]), device);
        crate::profile::row_linear(&self.fc2, crate::profile::row_linear_relu(&self.fc1, x))
    }
}

/// The occupancy MLP `M`: `D → D → num_classes`.
#[derive(Module, Debug)]
pub struct ScoreHead<B: Backend> {
    /// Hidden layer.
    pub fc1: Linear<B>,
    /// Output layer.
    pub fc2: Linear<B>,
}

impl<B: Backend> ScoreHead<B> {
    /// New head.
    pub fn new(d: usize, num_classes: usize, device: &B::Device) -> Self {
        Self {
            fc1: LinearConfig::new(d, d).init(device),
            fc2: LinearConfig::new(d, num_classes).init(device),
        }
    }
}

impl<B: ModelBackend> ScoreHead<B> {
    /// `[N, D]` → logits `[N, num_classes]`.
    pub fn forward(&self, x: Tensor<B, 2>) -> Tensor<B, 2> {
        crate::profile::row_linear(&self.fc2, crate::profile::row_linear_relu(&self.fc1, x))
    }
}

/// One stage: DCA then the score MLP.
#[derive(Module, Debug)]
pub struct AnchorStage<B: Backend> {
    /// Deformable cross attention.
    pub dca: DeformableCrossAttention<B>,
    /// Occupancy / class MLP.
    pub score: ScoreHead<B>,
    /// Not in the paper (`dca_column_base`): a second DCA block whose reference points are the
    /// projections of the candidates' column bases ([`crate::sparseocc_pp::dca::project_column_bases`]).
    pub base_dca: Option<DeformableCrossAttention<B>>,
}

/// Occupancy score `logsumexp(logits[:, 1..]) - logits[:, 0]` (log-odds of "not empty") on the host.
pub fn occupancy_score<B: occ_sparse::SparseConvBackend>(logits: &Tensor<B, 2>) -> Vec<f32> {
    let [n, k] = logits.dims();
    if n == 0 {
        return Vec::new();
    }
    if k < 2 {
        return vec![0.0; n];
    }
    // Row reductions over the candidates, their rows padded (see `rows_bucketed`).
    let s = crate::kernels::rows_bucketed(logits.clone().detach(), B::ROW_BUCKET, |l| {
        let rest = l.clone().narrow(1, 1, k - 1);
        let m = rest.clone().max_dim(1);
        let lse = (rest - m.clone()).exp().sum_dim(1).log() + m;
        lse - l.narrow(1, 0, 1)
    })
    .reshape([n]);
    s.into_data()
        .convert::<f32>()
        .to_vec::<f32>()
        .unwrap_or_else(|_| vec![0.0; n])
}

/// Number kept of `n` candidates at ratio `ratio`: `clamp(round(ratio·n), 1, n)` (0 when `n = 0`).
pub fn keep_count(n: usize, ratio: f64) -> usize {
    if n == 0 {
        return 0;
    }
    ((ratio * n as f64).round() as usize).clamp(1, n)
}

/// Anchors per batch item of the coarse-to-fine chain from `n0` level-0 candidates:
/// `k0 = keep(n0, r0)`, `k1 = keep(8·k0, r1)`, `k2 = keep(8·k1, r2)` (missing ratios count as 1).
pub fn chain_anchor_count(n0: usize, ratios: &[f64]) -> usize {
    let ratio = |r: usize| ratios.get(r).copied().unwrap_or(1.0);
    let k0 = keep_count(n0, ratio(0));
    let k1 = keep_count(8 * k0, ratio(1));
    keep_count(8 * k1, ratio(2))
}

/// Per batch item, the rows with the `keep_count(n_b, ratio)` highest scores among that item's `n_b`
/// rows (ties: lower row first; NaN ranks lowest). Returned ascending.
pub fn topk_per_batch(scores: &[f32], coords: &[Coord], ratio: f64) -> Vec<usize> {
    let mut by_batch: std::collections::BTreeMap<i32, Vec<usize>> = Default::default();
    for (i, c) in coords.iter().enumerate() {
        by_batch.entry(c[0]).or_default().push(i);
    }
    let key = |i: usize| {
        let s = scores.get(i).copied().unwrap_or(f32::NEG_INFINITY);
        if s.is_nan() {
            f32::NEG_INFINITY
        } else {
            s
        }
    };
    let mut out = Vec::new();
    for rows in by_batch.values() {
        let k = keep_count(rows.len(), ratio);
        let mut order = rows.clone();
        order.sort_by(|&a, &b| key(b).total_cmp(&key(a)).then(a.cmp(&b)));
        out.extend_from_slice(&order[..k]);
    }
    out.sort_unstable();
    out
}

/// Configuration of [`AnchorGenerator`].
#[derive(Config, Debug)]
pub struct AnchorGeneratorConfig {
    /// Feature width `D`.
    pub embed_dim: usize,
    /// Classes including empty (0).
    pub num_classes: usize,
    /// Full-resolution label grid `[X, Y, Z]` (each divisible by 8).
    pub full_dims: [usize; 3],
    /// DCA settings (shared by all stages; each stage has its own weights).
    pub dca: DcaConfig,
    /// Generation strategy.
    #[config(default = "AnchorMode::CoarseToFine")]
    pub mode: AnchorMode,
    /// Fraction of the candidates kept at levels 0, 1, 2 (see the module docs).
    #[config(default = "vec![1.0, 0.2, 0.1]")]
    pub keep_ratios: Vec<f64>,
    /// Not in the paper: follow every stage's DCA by a second DCA block sampling at the projection of
    /// each candidate's column base (see [`crate::sparseocc_pp::dca::project_column_bases`]).
    #[config(default = false)]
    pub column_base: bool,
    /// DIAGNOSTIC ([`crate::sparseocc_pp::extras::scan_oracle`]): add a learned embedding of the candidates' scan evidence
    /// to their queries.
    #[config(default = false)]
    pub scan_oracle: bool,
}

impl AnchorGeneratorConfig {
    /// Level-`r` grid `full_dims / LEVEL_FACTORS[r]`.
    pub fn level_dims(&self, r: usize) -> [usize; 3] {
        let f = LEVEL_FACTORS[r.min(2)];
        self.full_dims.map(|d| d / f)
    }

    /// Checks sizes and ratios.
    pub fn validate(&self) -> Result<(), ModelError> {
        self.dca.validate()?;
        if self.dca.embed_dim != self.embed_dim {
            return Err(ModelError::Config(format!(
                "anchors: DCA width {} != embed_dim {}",
                self.dca.embed_dim, self.embed_dim
            )));
        }
        if self.full_dims.iter().any(|&d| d == 0 || d % 8 != 0) {
            return Err(ModelError::Config(format!(
                "anchors: full_dims {:?} must be positive multiples of 8 (levels 1/8, 1/4, 1/2)",
                self.full_dims
            )));
        }
        if self.num_classes < 2 {
            return Err(ModelError::Config(format!(
                "anchors: num_classes {} must include empty and at least one class",
                self.num_classes
            )));
        }
        if self.keep_ratios.len() != 3
            || self
                .keep_ratios
                .iter()
                .any(|&r| !(r.is_finite() && r > 0.0 && r <= 1.0))
        {
            return Err(ModelError::Config(format!(
                "anchors: keep_ratios {:?} must be 3 values in (0, 1]",
                self.keep_ratios
            )));
        }
        Ok(())
    }

    /// Anchors per batch item that the coarse-to-fine chain produces (also the uniform count).
    pub fn anchors_per_item(&self) -> usize {
        chain_anchor_count(self.level_dims(0).iter().product(), &self.keep_ratios)
    }

    /// Initialises the generator (does not validate; `forward` does).
    pub fn init<B: Backend>(&self, device: &B::Device) -> AnchorGenerator<B> {
        let d = self.embed_dim;
        let n0: usize = self.level_dims(0).iter().product();
        let normal = Initializer::Normal {
            mean: 0.0,
            std: 1.0,
        };
        let stages = match self.mode {
            AnchorMode::CoarseToFine => 3,
            AnchorMode::Uniform => 1,
        };
        let child_tables = match self.mode {
            AnchorMode::CoarseToFine => 2,
            AnchorMode::Uniform => 0,
        };
        AnchorGenerator {
            embed0: normal.init([n0, d], device),
            child_embed: (0..child_tables)
                .map(|_| normal.init([8, d], device))
                .collect(),
            pos: PositionEncoding::new(d, device),
            stages: (0..stages)
                .map(|_| AnchorStage {
                    dca: self.dca.init(device),
                    score: ScoreHead::new(d, self.num_classes, device),
                    base_dca: self.column_base.then(|| self.dca.init(device)),
                })
                .collect(),
            scan_embed: self
                .scan_oracle
                .then(|| LinearConfig::new(2, d).init(device)),
            mode: self.mode,
            keep_ratios: self.keep_ratios.clone(),
            full_dims: self.full_dims,
            embed_dim: d,
        }
    }
}

/// The anchor generator (see the module docs).
#[derive(Module, Debug)]
pub struct AnchorGenerator<B: Backend> {
    /// Level-0 embeddings `[X/8·Y/8·Z/8, D]` (flat `[x][y][z]`).
    pub embed0: Param<Tensor<B, 2>>,
    /// Child-position embeddings `[8, D]` for the splits into levels 1 and 2 (coarse-to-fine only).
    pub child_embed: Vec<Param<Tensor<B, 2>>>,
    /// Position encoding (also used by the final DCA of the model).
    pub pos: PositionEncoding<B>,
    /// DCA + score per level (3 coarse-to-fine, 1 uniform).
    pub stages: Vec<AnchorStage<B>>,
    /// Embedding `2 → D` of the scan oracle's evidence (present with `scan_oracle`, a diagnostic).
    pub scan_embed: Option<Linear<B>>,
    mode: AnchorMode,
    keep_ratios: Vec<f64>,
    full_dims: [usize; 3],
    embed_dim: usize,
}

/// What the generator returns.
#[derive(Clone, Debug)]
pub struct AnchorOutput<B: Backend> {
    /// Anchors on the `full/2` grid with their features `[N, D]`.
    pub anchors: SparseTensor<B>,
    /// Per level (3 coarse-to-fine, 1 uniform): candidates, logits, kept rows.
    pub levels: Vec<LevelPrediction<B>>,
    /// Candidate and kept counts per level.
    pub stats: Vec<(String, usize)>,
}

impl<B: crate::kernels::ModelBackend> AnchorGenerator<B> {
    /// The generation mode.
    pub fn mode(&self) -> AnchorMode {
        self.mode
    }

    pub fn level_dims(&self, r: usize) -> [usize; 3] {
        self.full_dims.map(|d| d / LEVEL_FACTORS[r])
    }

    /// Runs DCA + score on candidates and returns (DCA features, prediction without `kept`).
    #[allow(clippy::too_many_arguments)]
    fn run_stage(
        &self,
        stage: &AnchorStage<B>,
        r: usize,
        coords: Vec<Coord>,
        feats: Tensor<B, 2>,
        images: &FeatureRows<B>,
        strides: &[usize],
        batch: &Batch<B>,
        depth: Option<&DepthMap<B>>,
        oracle: Option<&DepthOracle>,
        scan: Option<&ScanOracle>,
    ) -> Result<(Tensor<B, 2>, LevelPrediction<B>), ModelError> {
        let device = feats.device();
        let dims = self.level_dims(r);
        let feats = match (scan, &self.scan_embed) {
            (Some(scan), Some(embed)) => {
                feats + embed.forward(scan.features(&coords, LEVEL_FACTORS[r], &device)?)
            }
            _ => feats,
        };
        let grid = batch.grid.downsampled(LEVEL_FACTORS[r]);
        let pos = self.pos.encode(&coords, dims, &device);
        crate::profile::trace_mark("anchors position encoding", &pos);
        let hits = project_queries(&coords, &grid, &batch.cameras, batch.image_hw())?;
        let gate = combined_gate(depth, oracle, &hits, grid.voxel_size_m, &device)?;
        crate::profile::trace_mark("anchors projection into the views", &pos);
        let x = stage
            .dca
            .forward_gated(feats, pos.clone(), &hits, images, strides, gate)?;
        let x = match &stage.base_dca {
            Some(base) => {
                let hits = project_column_bases(
                    &coords,
                    &grid,
                    &batch.cameras,
                    batch.image_hw(),
                    column_floor_z_m(&batch.grid),
                )?;
                base.forward(x, pos, &hits, images, strides)?
            }
            None => x,
        };
        let logits = stage.score.forward(x.clone());
        crate::profile::trace_mark("anchors score head", &logits);
        Ok((
            x,
            LevelPrediction {
                coords,
                dims,
                factor: LEVEL_FACTORS[r],
                logits,
                kept: Vec::new(),
            },
        ))
    }

    /// Generates the anchors. `depth`: the depth map that gates every DCA stage
    /// ([`crate::sparseocc_pp::extras::depth_gate`]), or `None` (the paper's DCA).
    ///
    /// # Shapes
    /// - `images`: the rows of the `[B·V, C, h_l, w_l]` feature maps ([`FeatureRows::from_nchw`]),
    ///   `strides[l]` input pixels per feature pixel
    /// - returns anchors on `full_dims / 2` with `[N, D]` features
    pub fn forward(
        &self,
        images: &FeatureRows<B>,
        strides: &[usize],
        batch: &Batch<B>,
        depth: Option<&DepthMap<B>>,
        oracle: Option<&DepthOracle>,
        scan: Option<&ScanOracle>,
    ) -> Result<AnchorOutput<B>, ModelError> {
        if batch.grid.dims != self.full_dims {
            return Err(ModelError::Input(format!(
                "anchors: batch grid {:?} but the model was built for {:?}",
                batch.grid.dims, self.full_dims
            )));
        }
        let bsz = batch.batch_size();
        let device = self.embed0.val().device();
        let d = self.embed_dim;
        let n0: usize = self.level_dims(0).iter().product();
        let mut stats = Vec::new();
        let mut levels = Vec::new();
        match self.mode {
            AnchorMode::CoarseToFine => {
                if self.stages.len() != 3 || self.child_embed.len() != 2 {
                    return Err(ModelError::Config(
                        "anchors: coarse-to-fine needs 3 stages and 2 child tables".into(),
                    ));
                }
                let mut coords = occ_sparse::full_grid_coords(bsz, self.level_dims(0));
                let mut feats = self.embed0.val().repeat_dim(0, bsz);
                for r in 0..3 {
                    let n = coords.len();
                    let (x, mut pred) = self.run_stage(
                        &self.stages[r],
                        r,
                        coords,
                        feats,
                        images,
                        strides,
                        batch,
                        depth,
                        oracle,
                        scan,
                    )?;
                    crate::profile::trace_mark(&format!("anchors level {r}"), &x);
                    let scores = occupancy_score(&pred.logits);
                    let kept = topk_per_batch(&scores, &pred.coords, self.keep_ratios[r]);
                    stats.push((format!("anchor_l{r}_candidates"), n));
                    stats.push((format!("anchor_l{r}_kept"), kept.len()));
                    let kept_u32: Vec<u32> = kept.iter().map(|&i| i as u32).collect();
                    let kept_feats = if kept.is_empty() {
                        Tensor::zeros([0, d], &device)
                    } else {
                        x.select(0, index_tensor::<B>(&kept_u32, &device))
                    };
                    crate::profile::trace_mark("anchors top-k", &kept_feats);
                    let kept_coords: Vec<Coord> = kept.iter().map(|&i| pred.coords[i]).collect();
                    pred.kept = kept;
                    levels.push(pred);
                    if r == 2 {
                        let anchors =
                            SparseTensor::new(kept_coords, kept_feats, self.level_dims(2), bsz)?;
                        return Ok(AnchorOutput {
                            anchors,
                            levels,
                            stats,
                        });
                    }
                    // Split into 8 children: parent-major, child index 4dx + 2dy + dz.
                    let k = kept_coords.len();
                    let mut child_coords = Vec::with_capacity(8 * k);
                    let mut parent_rows = Vec::with_capacity(8 * k);
                    for (row, c) in kept_coords.iter().enumerate() {
                        for dx in 0..2 {
                            for dy in 0..2 {
                                for dz in 0..2 {
                                    child_coords.push([
                                        c[0],
                                        2 * c[1] + dx,
                                        2 * c[2] + dy,
                                        2 * c[3] + dz,
                                    ]);
                                    parent_rows.push(row as u32);
                                }
                            }
                        }
                    }
                    feats = if k == 0 {
                        Tensor::zeros([0, d], &device)
                    } else {
                        kept_feats.select(0, index_tensor::<B>(&parent_rows, &device))
                            + self.child_embed[r].val().repeat_dim(0, k)
                    };
                    crate::profile::trace_mark("anchors split", &feats);
                    coords = child_coords;
                }
                Err(ModelError::Config("anchors: unreachable level".into()))
            }
            AnchorMode::Uniform => {
                let stage = self.stages.first().ok_or_else(|| {
                    ModelError::Config("anchors: uniform mode needs one stage".into())
                })?;
                let dims2 = self.level_dims(2);
                let total: usize = dims2.iter().product();
                let k = chain_anchor_count(n0, &self.keep_ratios).min(total);
                let dims0 = self.level_dims(0);
                let mut coords = Vec::with_capacity(bsz * k);
                let mut parents = Vec::with_capacity(bsz * k);
                for b in 0..bsz {
                    for i in 0..k {
                        let lin = (((i as f64 + 0.5) * total as f64 / k as f64).floor() as usize)
                            .min(total - 1);
                        let z = lin % dims2[2];
                        let y = (lin / dims2[2]) % dims2[1];
                        let x = lin / (dims2[2] * dims2[1]);
                        coords.push([b as i32, x as i32, y as i32, z as i32]);
                        let p = ((x / 4) * dims0[1] + y / 4) * dims0[2] + z / 4;
                        parents.push(p.min(n0.saturating_sub(1)) as u32);
                    }
                }
                let feats = if coords.is_empty() {
                    Tensor::zeros([0, d], &device)
                } else {
                    self.embed0
                        .val()
                        .select(0, index_tensor::<B>(&parents, &device))
                };
                let n = coords.len();
                let (x, mut pred) = self.run_stage(
                    stage, 2, coords, feats, images, strides, batch, depth, oracle, scan,
                )?;
                pred.kept = (0..n).collect();
                let anchors = SparseTensor::new(pred.coords.clone(), x, dims2, bsz)?;
                stats.push(("anchor_uniform".to_string(), n));
                levels.push(pred);
                Ok(AnchorOutput {
                    anchors,
                    levels,
                    stats,
                })
            }
        }
    }
}
