//! SparseOcc++ assembly (paper Sec. 4): multi-scale image features → sparse anchors
//! ([`crate::sparseocc_pp::anchors`]) → SCF heads ([`crate::sparseocc_pp::scf_head`]) → geometry-guided propagation
//! ([`crate::sparseocc_pp::propagation`]) → DCA on the completed set ([`crate::sparseocc_pp::dca`]) → sparse U-Net
//! ([`crate::sparseocc_pp::unet`]) → per-voxel class logits at `1/2` resolution (or, with
//! [`OutputResolution::SubVoxel`], at full resolution through [`crate::sparseocc_pp::extras::subvoxel`]).
//!
//! The image encoder is not part of this module: `forward` takes its multi-scale features. Losses are
//! not computed here either: [`PPOutput`] carries every prediction and [`pp_targets`] builds the
//! host-side labels for all of them (`L_occ` on the final logits, `L_anchor` on every anchor level,
//! `L_scf` on the SCF heads).
//!
//! Ablation switches (paper Sec. 5.5): anchors coarse-to-fine / uniform, SCF decomposed / scalar,
//! bins / regression, propagation on / off ("off" = the "sparse anchor voxel only" row: the final
//! stage runs on the anchors themselves and no SCF heads exist).

pub mod anchors;
pub mod dca;
pub mod extras;
pub mod propagation;
pub mod scf_head;
pub mod unet;

use crate::batch::Batch;
use crate::error::ModelError;
use crate::kernels::ModelBackend;
use crate::loss::{ce::cross_entropy, occ_loss, LossKey};
use crate::output::ModelOutput;
use crate::profile::Stage;
use crate::sparseocc_pp::anchors::{column_floor_z_m, combined_gate};
use crate::sparseocc_pp::anchors::{
    AnchorGenerator, AnchorGeneratorConfig, AnchorMode, LevelPrediction,
};
use crate::sparseocc_pp::dca::{
    project_column_bases, project_queries, DcaConfig, DeformableCrossAttention, FeatureRows,
};
use crate::sparseocc_pp::extras::depth_gate::{DepthGate, DepthGateConfig, DepthMap};
use crate::sparseocc_pp::extras::depth_oracle::DepthOracle;
use crate::sparseocc_pp::extras::scan_oracle::ScanOracle;
use crate::sparseocc_pp::extras::sem2d::{Sem2dHead, Sem2dHeadConfig, Sem2dMap};
use crate::sparseocc_pp::extras::subvoxel::{SubVoxelHead, SubVoxelHeadConfig};
use crate::sparseocc_pp::propagation::propagate_anchors;
use crate::sparseocc_pp::scf_head::{
    scf_targets, ScfDecomposition, ScfHead, ScfHeadConfig, ScfLearning, ScfPrediction, ScfTargets,
};
use crate::sparseocc_pp::unet::{SparseUNet, SparseUNetConfig};
use burn::nn::{Linear, LinearConfig};
use burn::prelude::*;
use occ_labels::{downsample_monoscene, EMPTY, IGNORE};
use occ_sparse::Coord;

/// Resolution of the final logits.
#[derive(Config, Debug, Copy, PartialEq, Eq)]
pub enum OutputResolution {
    /// The paper's: logits at `1/2` of the label grid (upsampled ×2 for scoring).
    Half,
    /// Not in the paper: a learned split of every `1/2` voxel into its 8 full-resolution children
    /// ([`crate::sparseocc_pp::extras::subvoxel`]); `L_occ` is then computed at full resolution.
    SubVoxel,
}

/// Configuration of [`SparseOccPP`]. Defaults follow the paper where it is explicit; the choices
/// where it is silent are documented on each field and in the module docs of the stages.
#[derive(Config, Debug)]
pub struct SparseOccPPConfig {
    /// Classes including empty (class 0).
    pub num_classes: usize,
    /// Width `D` of anchor / voxel features.
    pub embed_dim: usize,
    /// Channels of the image features given to `forward`.
    pub feat_channels: usize,
    /// Full-resolution label grid `[X, Y, Z]` (each a multiple of 8).
    pub full_dims: [usize; 3],
    /// Number of image feature levels given to `forward`.
    #[config(default = 1)]
    pub num_feature_levels: usize,
    /// DCA heads.
    #[config(default = 4)]
    pub dca_heads: usize,
    /// DCA sampling points per head and level (`N_s`).
    #[config(default = 4)]
    pub dca_points: usize,
    /// DCA feed-forward width as a multiple of `embed_dim`.
    #[config(default = 2)]
    pub dca_ffn_ratio: usize,
    /// Initial DCA sampling offsets in units of Deformable DETR's pattern (1.0, `(j+1)` feature
    /// pixels for point `j`); see [`DcaConfig::offset_init_scale`].
    #[config(default = 1.0)]
    pub dca_offset_init_scale: f64,
    /// Anchor generation (paper default coarse-to-fine).
    #[config(default = "AnchorMode::CoarseToFine")]
    pub anchor_mode: AnchorMode,
    /// Fraction of the CANDIDATES kept at the 1/8, 1/4, 1/2 levels (paper: 1/5 and 1/10 at levels 1
    /// and 2; level 0 unpruned).
    #[config(default = "vec![1.0, 0.2, 0.1]")]
    pub keep_ratios: Vec<f64>,
    /// `s_max^{X-Y}` (Sec. 5.4: 10).
    #[config(default = 10)]
    pub s_max_planar: u32,
    /// `s_max^{Z}` (Sec. 5.4 says 5, the chosen ablation row (10, 3); docs/paper_notes.md §2 picks 3).
    #[config(default = 3)]
    pub s_max_vertical: u32,
    /// SCF decomposition (paper default decomposed).
    #[config(default = "ScfDecomposition::Decomposed")]
    pub scf_decomposition: ScfDecomposition,
    /// SCF learning (paper default bins).
    #[config(default = "ScfLearning::Bins")]
    pub scf_learning: ScfLearning,
    /// Geometry-guided propagation on / off.
    #[config(default = true)]
    pub propagation: bool,
    /// U-Net level widths as multiples of `embed_dim` (four levels).
    #[config(default = "vec![1, 1, 2, 2]")]
    pub unet_channel_mult: Vec<usize>,
    /// Weight of `L_anchor` (the occupancy loss on every anchor level, summed over levels).
    #[config(default = 1.0)]
    pub anchor_loss_weight: f64,
    /// Not in the paper: supervise the anchor candidates whose label is "ignore" (255: never
    /// observed, e.g. behind walls or inside buildings) as empty in `L_anchor`. Their scores are
    /// otherwise unsupervised and drift into the top-k: in the demo they took 965 of the 1638
    /// kept level-1 voxels and 3300 of the 5242 anchors, leaving 10-15 % of the occupied
    /// above-ground voxels in the anchor set. The evaluation ignores these voxels, so ranking them
    /// low costs nothing there; the final loss `L_occ` still ignores them.
    #[config(default = false)]
    pub anchor_unknown_as_empty: bool,
    /// Weight of `L_scf` (CE on the planar and vertical bins, or L1 in the regression ablation).
    #[config(default = 1.0)]
    pub scf_loss_weight: f64,
    /// Resolution of the final logits (paper: `1/2`).
    #[config(default = "OutputResolution::Half")]
    pub output: OutputResolution,
    /// Not in the paper: gate every DCA sample by a LiDAR-supervised depth map of the finest image
    /// level ([`crate::sparseocc_pp::extras::depth_gate`]; DFA3D's remedy for the depth ambiguity of 2D-to-3D attention).
    #[config(default = false)]
    pub depth_gate: bool,
    /// Depth bins `[d_min, d_max, step]` (metres) of the depth gate.
    #[config(default = "[2.0, 58.0, 1.0]")]
    pub depth_dbound: [f64; 3],
    /// Weight of the depth loss of the depth gate (docs/losses.md §6 depth BCE; applied when the batch
    /// carries LiDAR points).
    #[config(default = 1.0)]
    pub depth_loss_weight: f64,
    /// Not in the paper: an auxiliary per-pixel class head on the finest image level, supervised by
    /// the voxel labels of the LiDAR points projected into the image ([`crate::sparseocc_pp::extras::sem2d`]). Only a
    /// training signal for the image encoder; the 3D network does not read its output.
    #[config(default = false)]
    pub sem2d_aux: bool,
    /// Weight of the image semantic loss (applied when the batch carries LiDAR points and targets).
    #[config(default = 1.0)]
    pub sem2d_loss_weight: f64,
    /// DIAGNOSTIC, not a model option (needs the LiDAR scan at test time): gate every DCA sample by
    /// whether its voxel lies at the LiDAR surface depth of its reference pixel
    /// ([`crate::sparseocc_pp::extras::depth_oracle`]).
    #[config(default = false)]
    pub depth_oracle: bool,
    /// Not in the paper: follow every DCA (the three anchor stages and the final one) by a second DCA
    /// block whose reference points are the projections of the voxels' column bases, the lowest layer
    /// of the grid under each voxel ([`crate::sparseocc_pp::dca::project_column_bases`]): the pixel where what
    /// stands under a voxel meets the ground, the depth cue of ground-standing objects (BEVFormer's
    /// pillar reference points). About twice the DCA cost.
    #[config(default = false)]
    pub dca_column_base: bool,
    /// DIAGNOSTIC, not a model option (needs the LiDAR scan at test time): tell every anchor
    /// candidate and every final voxel which share of it holds a return of the frame's scan and
    /// which share a ray crossed, through a learned embedding added to its query
    /// ([`crate::sparseocc_pp::extras::scan_oracle`]): what perfect depth would give the 3D part.
    #[config(default = false)]
    pub scan_oracle: bool,
    /// With `scan_oracle`: use the whole 360° scan, not only the returns the cameras see.
    #[config(default = false)]
    pub scan_oracle_full_scan: bool,
}

impl SparseOccPPConfig {
    fn dca(&self) -> DcaConfig {
        DcaConfig::new(self.embed_dim, self.feat_channels)
            .with_num_levels(self.num_feature_levels)
            .with_num_heads(self.dca_heads)
            .with_num_points(self.dca_points)
            .with_ffn_ratio(self.dca_ffn_ratio)
            .with_offset_init_scale(self.dca_offset_init_scale)
    }

    /// The anchor generator's configuration.
    pub fn anchor_config(&self) -> AnchorGeneratorConfig {
        AnchorGeneratorConfig::new(self.embed_dim, self.num_classes, self.full_dims, self.dca())
            .with_mode(self.anchor_mode)
            .with_keep_ratios(self.keep_ratios.clone())
            .with_column_base(self.dca_column_base)
            .with_scan_oracle(self.scan_oracle)
    }

    /// The SCF heads' configuration.
    pub fn scf_config(&self) -> ScfHeadConfig {
        ScfHeadConfig::new(self.embed_dim)
            .with_s_max_planar(self.s_max_planar)
            .with_s_max_vertical(self.s_max_vertical)
            .with_decomposition(self.scf_decomposition)
            .with_learning(self.scf_learning)
    }

    /// The U-Net's configuration.
    pub fn unet_config(&self) -> SparseUNetConfig {
        SparseUNetConfig::new(
            self.embed_dim,
            self.unet_channel_mult
                .iter()
                .map(|m| m * self.embed_dim)
                .collect(),
        )
    }

    /// The output grid `full_dims / 2`.
    pub fn out_dims(&self) -> [usize; 3] {
        self.full_dims.map(|d| d / 2)
    }

    /// The depth gate's configuration.
    pub fn depth_gate_config(&self) -> DepthGateConfig {
        DepthGateConfig::new(self.feat_channels).with_dbound(self.depth_dbound)
    }

    /// The image semantic head's configuration.
    pub fn sem2d_config(&self) -> Sem2dHeadConfig {
        Sem2dHeadConfig::new(self.feat_channels, self.num_classes)
    }

    /// Whether training reads the LiDAR scans: the depth gate, the image semantic head and the two
    /// oracle diagnostics do.
    pub fn reads_points_in_training(&self) -> bool {
        self.depth_gate || self.sem2d_aux || self.depth_oracle || self.scan_oracle
    }

    /// Whether inference reads the LiDAR scan: only the oracle diagnostics do (they are no
    /// camera-only models).
    pub fn reads_points_at_test(&self) -> bool {
        self.depth_oracle || self.scan_oracle
    }

    /// Checks every size and switch.
    pub fn validate(&self) -> Result<(), ModelError> {
        if self.depth_gate {
            self.depth_gate_config().validate()?;
        }
        if self.sem2d_aux {
            self.sem2d_config().validate()?;
        }
        for (name, w) in [
            ("depth_loss_weight", self.depth_loss_weight),
            ("sem2d_loss_weight", self.sem2d_loss_weight),
        ] {
            if !(w.is_finite() && w >= 0.0) {
                return Err(ModelError::Config(format!(
                    "SparseOcc++: {name} {w} must be finite and >= 0"
                )));
            }
        }
        self.anchor_config().validate()?;
        self.scf_config().validate()?;
        self.unet_config().validate()
    }

    /// Initialises the model. Never panics on a bad configuration: [`SparseOccPP::forward`] validates
    /// it first (use [`SparseOccPPConfig::try_init`] to fail early).
    pub fn init<B: ModelBackend>(&self, device: &B::Device) -> SparseOccPP<B> {
        let unet = self.unet_config();
        let c0 = unet.channels.first().copied().unwrap_or(1).max(1);
        SparseOccPP {
            anchors: self.anchor_config().init(device),
            scf: self.propagation.then(|| self.scf_config().init(device)),
            dca: self.dca().init(device),
            base_dca: self.dca_column_base.then(|| self.dca().init(device)),
            unet: unet.init(device),
            head: LinearConfig::new(c0, self.num_classes.max(1)).init(device),
            subvoxel: (self.output == OutputResolution::SubVoxel)
                .then(|| SubVoxelHeadConfig::new(c0).init(device)),
            depth: self
                .depth_gate
                .then(|| self.depth_gate_config().init(device)),
            sem2d: self.sem2d_aux.then(|| self.sem2d_config().init(device)),
            scan_embed: self
                .scan_oracle
                .then(|| LinearConfig::new(2, self.embed_dim).init(device)),
            config: self.clone(),
        }
    }

    /// Validates, then initialises.
    pub fn try_init<B: ModelBackend>(
        &self,
        device: &B::Device,
    ) -> Result<SparseOccPP<B>, ModelError> {
        self.validate()?;
        Ok(self.init(device))
    }
}

/// The SparseOcc++ network (without the image encoder).
#[derive(Module, Debug)]
pub struct SparseOccPP<B: Backend> {
    /// Sparse anchor generation.
    pub anchors: AnchorGenerator<B>,
    /// SCF heads (present when propagation is on).
    pub scf: Option<ScfHead<B>>,
    /// DCA on the completed voxel set.
    pub dca: DeformableCrossAttention<B>,
    /// Column-base DCA after it (present with `dca_column_base`, not in the paper).
    pub base_dca: Option<DeformableCrossAttention<B>>,
    /// Sparse U-Net.
    pub unet: SparseUNet<B>,
    /// Final classifier (of the `1/2` voxels, or of their children with the sub-voxel head).
    pub head: Linear<B>,
    /// Full-resolution output head (present with [`OutputResolution::SubVoxel`]).
    pub subvoxel: Option<SubVoxelHead<B>>,
    /// Depth head of the depth gate (present with `depth_gate`).
    pub depth: Option<DepthGate<B>>,
    /// Image semantic head (present with `sem2d_aux`).
    pub sem2d: Option<Sem2dHead<B>>,
    /// Embedding `2 → D` of the scan oracle's evidence for the final stage (present with
    /// `scan_oracle`, a diagnostic).
    pub scan_embed: Option<Linear<B>>,
    config: SparseOccPPConfig,
}

/// Everything SparseOcc++ predicts.
#[derive(Clone, Debug)]
pub struct PPOutput<B: Backend> {
    /// Final voxels `(b, x, y, z)` on `full/2`, logits `[N, num_classes]`, `upsample = 2`, stats
    /// (with [`OutputResolution::SubVoxel`]: the children on `full`, `upsample = 1`); `losses` is
    /// left empty.
    pub out: ModelOutput<B>,
    /// Per anchor level (1/8, 1/4, 1/2; one level for uniform anchors): candidates and class logits.
    pub anchor_levels: Vec<LevelPrediction<B>>,
    /// SCF predictions on the anchors (`None` when propagation is off).
    pub scf: Option<ScfPrediction<B>>,
    /// Depth map of the depth gate (`None` without it).
    pub depth: Option<DepthMap<B>>,
    /// Class logits of the image semantic head (`None` without `sem2d_aux`).
    pub sem2d: Option<Sem2dMap<B>>,
}

impl<B: ModelBackend> SparseOccPP<B> {
    /// The configuration the model was built from.
    pub fn config(&self) -> &SparseOccPPConfig {
        &self.config
    }

    fn check_inputs(
        &self,
        feats: &[Tensor<B, 4>],
        strides: &[usize],
        batch: &Batch<B>,
    ) -> Result<(), ModelError> {
        let cfg = &self.config;
        if batch.grid.dims != cfg.full_dims {
            return Err(ModelError::Input(format!(
                "SparseOcc++: batch grid {:?} but the model was built for {:?}",
                batch.grid.dims, cfg.full_dims
            )));
        }
        let (bsz, nv) = (batch.batch_size(), batch.num_views());
        if batch.cameras.len() != bsz || batch.cameras.iter().any(|c| c.len() != nv) {
            return Err(ModelError::Input(format!(
                "SparseOcc++: images are [{bsz}, {nv}, ...] but cameras are {:?}",
                batch.cameras.iter().map(Vec::len).collect::<Vec<_>>()
            )));
        }
        if feats.len() != cfg.num_feature_levels || strides.len() != feats.len() {
            return Err(ModelError::Input(format!(
                "SparseOcc++: {} feature levels and {} strides, configured for {}",
                feats.len(),
                strides.len(),
                cfg.num_feature_levels
            )));
        }
        for (l, f) in feats.iter().enumerate() {
            let [n, c, _, _] = f.dims();
            if n != bsz * nv || c != cfg.feat_channels {
                return Err(ModelError::Input(format!(
                    "SparseOcc++: feature level {l} is {:?}, expected [{}, {}, h, w] (view-major per item)",
                    f.dims(),
                    bsz * nv,
                    cfg.feat_channels
                )));
            }
        }
        Ok(())
    }

    /// Runs the network.
    ///
    /// # Shapes
    /// - `feats[l]`: `[B·V, C, h_l, w_l]` (image `b·V + v`), `strides[l]` input pixels per feature pixel
    /// - returns logits `[N, num_classes]` on `N` voxels of `full_dims / 2` (of `full_dims` with
    ///   [`OutputResolution::SubVoxel`])
    pub fn forward(
        &self,
        feats: &[Tensor<B, 4>],
        strides: &[usize],
        batch: &Batch<B>,
    ) -> Result<PPOutput<B>, ModelError> {
        self.config.validate()?;
        self.check_inputs(feats, strides, batch)?;
        let cfg = &self.config;
        let out_dims = cfg.out_dims();
        let depth = match &self.depth {
            Some(head) => Some(head.forward(feats[0].clone(), strides[0])?),
            None => None,
        };
        let sem2d = self
            .sem2d
            .as_ref()
            .map(|head| head.forward(feats[0].clone(), strides[0]));
        let oracle = if cfg.depth_oracle {
            DepthOracle::from_batch(batch)?
        } else {
            None
        };
        let scan = if cfg.scan_oracle {
            ScanOracle::from_batch(batch, cfg.scan_oracle_full_scan)?
        } else {
            None
        };
        // The image features as channel-last rows, laid out once for every DCA block of the frame.
        let images = FeatureRows::from_nchw(feats)?;
        crate::profile::trace_mark("image feature rows", &images.rows);
        let gen = self.anchors.forward(
            &images,
            strides,
            batch,
            depth.as_ref(),
            oracle.as_ref(),
            scan.as_ref(),
        )?;
        crate::profile::mark(Stage::Anchors, gen.anchors.feats());
        let mut stats = gen.stats;
        let anchors = gen.anchors;
        stats.push(("anchors".to_string(), anchors.num_active()));

        let (completed, scf) = match &self.scf {
            Some(head) if cfg.propagation => {
                let pred =
                    head.predict(anchors.coords().to_vec(), out_dims, anchors.feats().clone());
                let (completed, new) = propagate_anchors(
                    &anchors,
                    &pred.s_planar,
                    &pred.s_vertical,
                    pred.decomposition,
                )?;
                stats.push(("propagated_new".to_string(), new));
                (completed, Some(pred))
            }
            _ => (anchors, None),
        };
        stats.push(("completed".to_string(), completed.num_active()));
        crate::profile::mark(Stage::ScfPropagation, completed.feats());

        // DCA on the completed set (new voxels start from zero features).
        let device = completed.device();
        let grid = batch.grid.downsampled(2);
        let pos = self
            .anchors
            .pos
            .encode(completed.coords(), out_dims, &device);
        let hits = project_queries(completed.coords(), &grid, &batch.cameras, batch.image_hw())?;
        let gate = combined_gate(
            depth.as_ref(),
            oracle.as_ref(),
            &hits,
            grid.voxel_size_m,
            &device,
        )?;
        let query = match (&scan, &self.scan_embed) {
            (Some(scan), Some(embed)) => {
                completed.feats().clone()
                    + embed.forward(scan.features(completed.coords(), 2, &device)?)
            }
            _ => completed.feats().clone(),
        };
        let x = self
            .dca
            .forward_gated(query, pos.clone(), &hits, &images, strides, gate)?;
        let x = match &self.base_dca {
            Some(base) => {
                let hits = project_column_bases(
                    completed.coords(),
                    &grid,
                    &batch.cameras,
                    batch.image_hw(),
                    column_floor_z_m(&batch.grid),
                )?;
                base.forward(x, pos, &hits, &images, strides)?
            }
            None => x,
        };
        crate::profile::mark(Stage::Dca, &x);
        let x = self.unet.forward(completed.with_feats(x)?)?;
        crate::profile::mark(Stage::Unet, x.feats());
        let coords: Vec<Coord> = x.coords().to_vec();
        stats.push(("final".to_string(), coords.len()));
        let (coords, logits, out_dims, upsample) = match &self.subvoxel {
            Some(sv) => {
                let (children, logits) = sv.forward(&coords, x.into_feats(), &self.head)?;
                stats.push(("final_full_res".to_string(), children.len()));
                (children, logits, cfg.full_dims, 1)
            }
            None => (
                coords,
                crate::profile::linear(&self.head, x.into_feats()),
                out_dims,
                2,
            ),
        };
        crate::profile::mark(Stage::Head, &logits);
        Ok(PPOutput {
            out: ModelOutput {
                coords,
                logits,
                out_dims,
                upsample,
                losses: Vec::new(),
                stats,
            },
            anchor_levels: gen.levels,
            scf,
            depth,
            sem2d,
        })
    }
}

/// Host-side labels for every prediction of [`PPOutput`] (255 = ignore everywhere).
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct PPTargets {
    /// Class label of each final voxel (`out.coords` order): the MonoScene rule on its 2×2×2 children
    /// (the full-resolution label itself for a full-resolution output).
    pub labels: Vec<u8>,
    /// Per anchor level, the class label of each candidate (`coords` order): the MonoScene rule on its
    /// `factor³` full-resolution children.
    pub anchor_labels: Vec<Vec<u8>>,
    /// SCF bin targets of the anchors (present when `scf` is).
    pub scf: Option<ScfTargets>,
}

fn lookup(coords: &[Coord], grids: &[Vec<u8>], dims: [usize; 3]) -> Result<Vec<u8>, ModelError> {
    coords
        .iter()
        .enumerate()
        .map(|(i, c)| {
            let b = usize::try_from(c[0]).ok().filter(|&b| b < grids.len());
            let inside = (0..3).all(|a| c[a + 1] >= 0 && (c[a + 1] as usize) < dims[a]);
            match (b, inside) {
                (Some(b), true) => {
                    Ok(grids[b]
                        [(c[1] as usize * dims[1] + c[2] as usize) * dims[2] + c[3] as usize])
                }
                _ => Err(ModelError::Input(format!(
                    "targets: voxel {i} at {c:?} outside {} items of {dims:?}",
                    grids.len()
                ))),
            }
        })
        .collect()
}

/// Builds the labels for every prediction in `out` from the full-resolution `batch.target`.
pub fn pp_targets<B: Backend>(
    out: &PPOutput<B>,
    batch: &Batch<B>,
    cfg: &SparseOccPPConfig,
) -> Result<PPTargets, ModelError> {
    let target = batch
        .target
        .as_ref()
        .ok_or_else(|| ModelError::Input("targets: the batch has no target".into()))?;
    let full_dims = batch.grid.dims;
    if full_dims != cfg.full_dims {
        return Err(ModelError::Input(format!(
            "targets: batch grid {full_dims:?} but the config has {:?}",
            cfg.full_dims
        )));
    }
    let volume: usize = full_dims.iter().product();
    if let Some((b, t)) = target.iter().enumerate().find(|(_, t)| t.len() != volume) {
        return Err(ModelError::Input(format!(
            "targets: item {b} has {} labels, the grid {full_dims:?} has {volume}",
            t.len()
        )));
    }
    let mut cache: Vec<(usize, Vec<Vec<u8>>)> = Vec::new();
    let mut grids_for = |ds: usize| -> Result<Vec<Vec<u8>>, ModelError> {
        if let Some((_, g)) = cache.iter().find(|(f, _)| *f == ds) {
            return Ok(g.clone());
        }
        let g = target
            .iter()
            .map(|t| downsample_monoscene(t, full_dims, ds))
            .collect::<Result<Vec<_>, _>>()
            .map_err(|e| ModelError::Input(format!("targets: {e}")))?;
        cache.push((ds, g.clone()));
        Ok(g)
    };
    let half = grids_for(2)?;
    let half_dims = full_dims.map(|d| d / 2);
    let labels = if out.out.upsample == 1 {
        lookup(&out.out.coords, target, full_dims)?
    } else {
        lookup(&out.out.coords, &half, half_dims)?
    };
    let mut anchor_labels = Vec::with_capacity(out.anchor_levels.len());
    for lvl in &out.anchor_levels {
        let g = if lvl.factor == 2 {
            half.clone()
        } else {
            grids_for(lvl.factor)?
        };
        anchor_labels.push(lookup(&lvl.coords, &g, lvl.dims)?);
    }
    let scf = match &out.scf {
        Some(p) => Some(scf_targets(
            &p.coords,
            &half,
            half_dims,
            p.decomposition,
            p.s_max_planar,
            p.s_max_vertical,
        )?),
        None => None,
    };
    Ok(PPTargets {
        labels,
        anchor_labels,
        scf,
    })
}

impl<B: occ_sparse::SparseConvBackend> PPOutput<B> {
    /// The training objective of paper Sec. 4.4, `L = L_occ + L_anchor + L_scf` (docs/losses.md §7):
    /// - `occ.*`: [`occ_loss`] (weighted CE + Lovasz-softmax + geo_scal + sem_scal) on the final voxels
    ///   against their MonoScene-rule labels;
    /// - `anchor{l}.*`: the same four terms on every candidate of anchor level `l`, times
    ///   `anchor_loss_weight` (with `anchor_unknown_as_empty`, ignored candidates count as empty);
    /// - `scf.planar`, `scf.vertical`: CE on the SCF bins against the Algorithm-2 targets (or an L1
    ///   regression of `bin − s_max` in the regression ablation), times `scf_loss_weight`;
    /// - `depth` (only with the depth gate, not in the paper, and only when the batch has LiDAR
    ///   points): the depth BCE of [`crate::lss::depth_loss`], times `depth_loss_weight`;
    /// - `sem2d` (only with `sem2d_aux`, not in the paper, and only when the batch has LiDAR points):
    ///   the class-weighted CE of the image semantic head ([`crate::sparseocc_pp::extras::sem2d`]), times
    ///   `sem2d_loss_weight`.
    ///
    /// Terms whose labels are all ignored are left out. `class_weights`: `num_classes` weights.
    pub fn losses(
        &self,
        batch: &Batch<B>,
        cfg: &SparseOccPPConfig,
        class_weights: &[f64],
    ) -> Result<Vec<(LossKey, Tensor<B, 1>)>, ModelError> {
        if class_weights.len() != cfg.num_classes {
            return Err(ModelError::Input(format!(
                "SparseOcc++ losses: {} class weights for {} classes",
                class_weights.len(),
                cfg.num_classes
            )));
        }
        let t = pp_targets(self, batch, cfg)?;
        let mut out = Vec::new();
        let any_valid = |l: &[u8]| l.iter().any(|&v| v != IGNORE);
        if any_valid(&t.labels) {
            for (term, l) in occ_loss(self.out.logits.clone(), &t.labels, class_weights)? {
                out.push((LossKey::Occ(term), l));
            }
        }
        if cfg.anchor_loss_weight != 0.0 {
            for (i, (lvl, labels)) in self.anchor_levels.iter().zip(&t.anchor_labels).enumerate() {
                let unknown_as_empty: Vec<u8>;
                let labels = if cfg.anchor_unknown_as_empty {
                    unknown_as_empty = labels
                        .iter()
                        .map(|&l| if l == IGNORE { EMPTY } else { l })
                        .collect();
                    &unknown_as_empty
                } else {
                    labels
                };
                if !any_valid(labels) {
                    continue;
                }
                for (term, l) in occ_loss(lvl.logits.clone(), labels, class_weights)? {
                    out.push((
                        LossKey::Anchor(i, term),
                        l.mul_scalar(cfg.anchor_loss_weight),
                    ));
                }
            }
        }
        if let Some(depth) = &self.depth {
            if cfg.depth_loss_weight != 0.0 {
                if let Some(l) = depth.loss(batch)? {
                    out.push((LossKey::Depth, l.mul_scalar(cfg.depth_loss_weight)));
                }
            }
        }
        if let Some(sem) = &self.sem2d {
            if cfg.sem2d_loss_weight != 0.0 {
                if let Some(l) = sem.loss(batch, class_weights)? {
                    out.push((LossKey::Sem2d, l.mul_scalar(cfg.sem2d_loss_weight)));
                }
            }
        }
        if let (Some(pred), Some(tg)) = (&self.scf, &t.scf) {
            if cfg.scf_loss_weight != 0.0 {
                let parts = [
                    (
                        LossKey::ScfPlanar,
                        Some(&pred.planar),
                        Some(&tg.planar),
                        pred.s_max_planar,
                    ),
                    (
                        LossKey::ScfVertical,
                        pred.vertical.as_ref(),
                        tg.vertical.as_ref(),
                        pred.s_max_vertical,
                    ),
                ];
                for (key, p, labels, s_max) in parts {
                    let (Some(p), Some(labels)) = (p, labels) else {
                        continue;
                    };
                    if !any_valid(labels) {
                        continue;
                    }
                    let l = match pred.learning {
                        ScfLearning::Bins => cross_entropy(p.clone(), labels, IGNORE)?,
                        ScfLearning::Regression => scf_l1(p, labels, s_max)?,
                    };
                    out.push((key, l.mul_scalar(cfg.scf_loss_weight)));
                }
            }
        }
        Ok(out)
    }
}

/// Mean `|p − (bin − s_max)|` over the anchors whose bin is not ignored (`p`: `[N, 1]`).
fn scf_l1<B: Backend>(
    p: &Tensor<B, 2>,
    bins: &[u8],
    s_max: u32,
) -> Result<Tensor<B, 1>, ModelError> {
    let [n, k] = p.dims();
    if bins.len() != n || k != 1 {
        return Err(ModelError::Input(format!(
            "SCF regression: prediction {:?} for {} targets",
            p.dims(),
            bins.len()
        )));
    }
    let device = p.device();
    let (rows, vals): (Vec<i64>, Vec<f32>) = bins
        .iter()
        .enumerate()
        .filter(|(_, &b)| b != IGNORE)
        .map(|(i, &b)| (i as i64, b as f32 - s_max as f32))
        .unzip();
    let m = rows.len();
    let idx = Tensor::<B, 1, Int>::from_data(TensorData::new(rows, [m]), &device);
    let target = Tensor::<B, 1>::from_data(TensorData::new(vals, [m]), &device);
    let sel = p.clone().reshape([n]).select(0, idx);
    Ok((sel - target).abs().mean())
}
