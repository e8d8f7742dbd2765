//! SparseOcc assembly (paper Sec. 3): LSS → non-empty voxels → sparse latent propagator → sparse
//! feature pyramid + interpolation decoder → sparse transformer head.
//!
//! The image encoder is outside: [`SparseOcc::forward`] takes ONE feature map `[B*V, C, h, w]`
//! (row `b*V + v`) at `stride` input pixels. Predictions live on the LSS grid (`full_dims /
//! lss_downsample`, 1/2 resolution by default) and are returned as a [`ModelOutput`] with
//! `upsample = lss_downsample`; the loss terms come from [`SoOutput::losses`] (docs/losses.md §7).
//!
//! Label grid for the losses: the full-resolution target downsampled with the official in-network
//! rule ([`crate::targets::downsample_labels_mode`]) to the prediction grid; the mask targets and the coarse loss are
//! both computed there (the official code also point-samples the full-resolution grid for the masks;
//! here masks and predictions share the 1/2-resolution grid).

pub mod hungarian;
pub mod mask_head;
pub mod propagator;
pub mod pyramid;

use crate::batch::Batch;
use crate::error::ModelError;
use crate::kernels::ModelBackend;
use crate::loss::{cross_entropy_weighted, LossKey};
use crate::lss::{depth_loss, depth_targets, Lss, LssConfig};
use crate::output::ModelOutput;
use crate::profile::Stage;
use crate::sparseocc::mask_head::{
    HeadOutput, MaskHead, MaskHeadConfig, MemoryLevel, SetLossWeights,
};
use crate::sparseocc::propagator::{PropagatorConfig, SparseLatentPropagator};
use crate::sparseocc::pyramid::{PyramidConfig, SparsePyramid};
use crate::targets::{check_input, targets_at};
use burn::prelude::*;
use occ_labels::IGNORE;
use occ_sparse::Coord;

/// Configuration of [`SparseOcc`]. Defaults are the official SemanticKITTI settings (docs/reference_models.md §1);
/// CPU tests shrink the channels, queries and layers.
#[derive(Config, Debug)]
pub struct SparseOccConfig {
    /// Number of classes including empty (class 0): 20 for SemanticKITTI.
    pub num_classes: usize,
    /// Image feature channels of the feature map given to `forward`.
    pub feat_channels: usize,
    /// Full-resolution grid shape (must equal `batch.grid.dims`).
    pub full_dims: [usize; 3],
    /// LSS context (voxel feature) channels.
    #[config(default = 128)]
    pub lss_channels: usize,
    /// LSS depth-net hidden channels.
    #[config(default = 256)]
    pub lss_mid_channels: usize,
    /// Depth bins `[min, max, step]` (m).
    #[config(default = "[2.0, 58.0, 0.5]")]
    pub dbound: [f64; 3],
    /// LSS grid = full grid downsampled by this (2: 0.4 m on SemanticKITTI).
    #[config(default = 2)]
    pub lss_downsample: usize,
    /// Camera-aware depth net.
    #[config(default = true)]
    pub camera_aware: bool,
    /// Propagator stage channels (`L` = length).
    #[config(default = "vec![128, 256, 512, 1024]")]
    pub propagator_channels: Vec<usize>,
    /// Completion layers per stage.
    #[config(default = "vec![3, 2, 2, 1]")]
    pub completion_layers: Vec<usize>,
    /// Planar (2D) stages at the end.
    #[config(default = 2)]
    pub planar_stages: usize,
    /// Decoder channels (pyramid and head).
    #[config(default = 192)]
    pub decoder_channels: usize,
    /// GroupNorm groups.
    #[config(default = 32)]
    pub norm_groups: usize,
    /// Queries.
    #[config(default = 100)]
    pub num_queries: usize,
    /// Decoder layers.
    #[config(default = 9)]
    pub decoder_layers: usize,
    /// Attention heads.
    #[config(default = 6)]
    pub num_heads: usize,
    /// FFN hidden channels.
    #[config(default = 1536)]
    pub ffn_channels: usize,
    /// Coarse filter threshold on the non-empty probability (0: the official top-k only, see
    /// [`crate::sparseocc::mask_head`]).
    #[config(default = 0.0)]
    pub coarse_threshold: f64,
    /// Coarse filter cap as a fraction of the prediction-grid volume.
    #[config(default = 0.6)]
    pub coarse_max_ratio: f64,
    /// Points per item for matching and mask losses.
    #[config(default = 50176)]
    pub num_points: usize,
    /// Class loss weight.
    #[config(default = 2.0)]
    pub class_weight: f64,
    /// Mask BCE weight.
    #[config(default = 5.0)]
    pub mask_weight: f64,
    /// Dice weight.
    #[config(default = 5.0)]
    pub dice_weight: f64,
    /// No-object class weight.
    #[config(default = 0.1)]
    pub no_object_weight: f64,
    /// Depth loss weight.
    #[config(default = 1.0)]
    pub depth_weight: f64,
    /// Coarse segmentation loss weight.
    #[config(default = 1.0)]
    pub coarse_weight: f64,
}

impl SparseOccConfig {
    /// The LSS sub-configuration.
    pub fn lss(&self) -> LssConfig {
        LssConfig::new(self.feat_channels, self.lss_channels)
            .with_mid_channels(self.lss_mid_channels)
            .with_dbound(self.dbound)
            .with_downsample(self.lss_downsample)
            .with_camera_aware(self.camera_aware)
    }

    /// Initialises the model; errors on an inconsistent configuration.
    pub fn init<B: ModelBackend>(&self, device: &B::Device) -> Result<SparseOcc<B>, ModelError> {
        if self.num_classes < 2 || self.full_dims.contains(&0) {
            return Err(ModelError::Config(format!(
                "sparseocc.rs: num_classes {} (need >= 2), full_dims {:?}",
                self.num_classes, self.full_dims
            )));
        }
        let lss = self.lss().init(device)?;
        let propagator = PropagatorConfig::new(self.lss_channels)
            .with_channels(self.propagator_channels.clone())
            .with_completion_layers(self.completion_layers.clone())
            .with_planar_stages(self.planar_stages)
            .init(device)?;
        let pyramid = PyramidConfig::new(self.propagator_channels.clone())
            .with_out_channels(self.decoder_channels)
            .with_norm_groups(self.norm_groups)
            .init(device)?;
        let n_mem = (self.propagator_channels.len() - 1).max(1);
        let head = MaskHeadConfig::new(self.decoder_channels, self.num_classes)
            .with_num_queries(self.num_queries)
            .with_num_layers(self.decoder_layers)
            .with_num_heads(self.num_heads)
            .with_ffn_channels(self.ffn_channels)
            .with_num_memory_levels(n_mem)
            .with_coarse_threshold(self.coarse_threshold)
            .with_coarse_max_ratio(self.coarse_max_ratio)
            .with_norm_groups(self.norm_groups)
            .init(device)?;
        Ok(SparseOcc {
            lss,
            propagator,
            pyramid,
            head,
            num_classes: self.num_classes,
            feat_channels: self.feat_channels,
            full_dims: self.full_dims,
            lss_downsample: self.lss_downsample,
            num_points: self.num_points,
            class_weight: self.class_weight,
            mask_weight: self.mask_weight,
            dice_weight: self.dice_weight,
            no_object_weight: self.no_object_weight,
            depth_weight: self.depth_weight,
            coarse_weight: self.coarse_weight,
        })
    }
}

/// The SparseOcc model.
#[derive(Module, Debug)]
pub struct SparseOcc<B: Backend> {
    /// View transform.
    pub lss: Lss<B>,
    /// Sparse latent propagator.
    pub propagator: SparseLatentPropagator<B>,
    /// Feature pyramid + voxel decoder.
    pub pyramid: SparsePyramid<B>,
    /// Sparse transformer head.
    pub head: MaskHead<B>,
    num_classes: usize,
    feat_channels: usize,
    full_dims: [usize; 3],
    lss_downsample: usize,
    num_points: usize,
    class_weight: f64,
    mask_weight: f64,
    dice_weight: f64,
    no_object_weight: f64,
    depth_weight: f64,
    coarse_weight: f64,
}

/// Everything the SparseOcc losses need.
#[derive(Clone, Debug)]
pub struct SoAux<B: Backend> {
    /// Depth logits `[B*V, D, h, w]`.
    pub depth_logits: Tensor<B, 4>,
    /// Depth target bin per feature pixel (`-1`: none), `None` without LiDAR points.
    pub depth_targets: Option<Vec<i64>>,
    /// Coarse semantic logits on the level-0 sites `[N_0, num_classes]`.
    pub coarse_logits: Tensor<B, 2>,
    /// The level-0 sites `(b, x, y, z)` (rows of `coarse_logits`).
    pub coarse_coords: Vec<Coord>,
    /// The head's outputs (kept sites, class and mask logits of every prediction).
    pub head: HeadOutput<B>,
    /// Prediction grid shape.
    pub out_dims: [usize; 3],
    /// Full-resolution voxels per prediction voxel.
    pub downsample: usize,
    /// Full-resolution grid shape.
    pub full_dims: [usize; 3],
    /// Number of classes.
    pub num_classes: usize,
    /// Loss weights.
    pub weights: SetLossWeights,
    /// Depth loss weight.
    pub depth_weight: f64,
    /// Coarse loss weight.
    pub coarse_weight: f64,
}

/// Output of [`SparseOcc::forward`].
#[derive(Clone, Debug)]
pub struct SoOutput<B: Backend> {
    /// Per-voxel class logits (`ln` of the head's class scores) on the kept non-empty sites at the
    /// prediction resolution (`upsample = lss_downsample`), per-stage statistics; `losses` is empty.
    pub out: ModelOutput<B>,
    /// Intermediate results for [`SoOutput::losses`].
    pub aux: SoAux<B>,
}

impl<B: ModelBackend> SparseOcc<B> {
    /// Runs the model.
    ///
    /// # Shapes
    /// - feats: ONE image feature map `[B*V, feat_channels, h, w]` (row `b*V + v`) at `stride` input
    ///   pixels; `batch.grid.dims` must equal `full_dims`.
    pub fn forward(
        &self,
        feats: Tensor<B, 4>,
        stride: usize,
        batch: &Batch<B>,
    ) -> Result<SoOutput<B>, ModelError> {
        check_input(&feats, batch, self.feat_channels, self.full_dims)?;
        let [_, _, h, w] = feats.dims();
        let lss_out = self.lss.forward(feats, stride, batch)?;
        let x = lss_out.splat_sparse()?;
        crate::profile::mark(Stage::Lss, x.feats());
        let mut stats = vec![
            ("lss.points".to_string(), lss_out.frustum.num_points()),
            ("lss.voxels".to_string(), x.num_active()),
        ];
        let prop = self.propagator.forward(x)?;
        if let Some(l) = prop.levels.last() {
            crate::profile::mark(Stage::Propagator, l.feats());
        }
        stats.extend(prop.stats.iter().cloned());
        let pyr = self.pyramid.forward(&prop.levels)?;
        crate::profile::mark(Stage::Pyramid, pyr.mask_features.feats());
        let n_levels = pyr.levels.len();
        let memory: Vec<MemoryLevel<B>> = if n_levels > 1 {
            (1..n_levels)
                .rev()
                .map(|l| MemoryLevel {
                    tensor: pyr.levels[l].clone(),
                    stride: 1 << l,
                })
                .collect()
        } else {
            vec![MemoryLevel {
                tensor: pyr.levels[0].clone(),
                stride: 1,
            }]
        };
        let head = self.head.forward(&pyr.mask_features, &memory)?;
        crate::profile::mark(Stage::MaskHead, &head.log_scores);
        stats.extend(head.stats.iter().cloned());
        stats.push(("out.sites".to_string(), head.kept_coords.len()));
        let out_dims = pyr.mask_features.spatial_shape();
        let depth_targets = depth_targets(batch, h, w, stride, self.lss.dbound())?;
        let out = ModelOutput {
            coords: head.kept_coords.clone(),
            logits: head.log_scores.clone(),
            out_dims,
            upsample: self.lss_downsample,
            losses: Vec::new(),
            stats,
        };
        let aux = SoAux {
            depth_logits: lss_out.depth_logits,
            depth_targets,
            coarse_logits: head.coarse_logits.clone(),
            coarse_coords: pyr.mask_features.coords().to_vec(),
            head,
            out_dims,
            downsample: self.lss_downsample,
            full_dims: self.full_dims,
            num_classes: self.num_classes,
            weights: SetLossWeights {
                class: self.class_weight,
                mask: self.mask_weight,
                dice: self.dice_weight,
                no_object: self.no_object_weight,
                num_points: self.num_points,
            },
            depth_weight: self.depth_weight,
            coarse_weight: self.coarse_weight,
        };
        Ok(SoOutput { out, aux })
    }
}

impl<B: Backend> SoOutput<B> {
    /// Loss terms (docs/losses.md §5 and §7): for every head prediction `mask_cls` (weight 2, no-object 0.1),
    /// `mask_bce` and `mask_dice` (weight 5) — prefixed `d{i}.` for the auxiliary ones —, `depth`
    /// (BCE, when the batch has LiDAR points) and `coarse_ce` (weighted CE, ignore 255, on the coarse
    /// logits of the level-0 sites).
    ///
    /// `class_weights`: `num_classes` per-class weights (class 0 = empty included).
    pub fn losses(
        &self,
        batch: &Batch<B>,
        class_weights: &[f64],
    ) -> Result<Vec<(LossKey, Tensor<B, 1>)>, ModelError> {
        let a = &self.aux;
        if class_weights.len() != a.num_classes {
            return Err(ModelError::Input(format!(
                "sparseocc.rs: {} class weights for {} classes",
                class_weights.len(),
                a.num_classes
            )));
        }
        let labels = targets_at(batch, a.full_dims, a.downsample)?;
        let mut out = a
            .head
            .set_losses(&labels, a.out_dims, class_weights, &a.weights)?;
        if let Some(t) = &a.depth_targets {
            out.push((
                LossKey::Depth,
                depth_loss(a.depth_logits.clone(), t)?.mul_scalar(a.depth_weight),
            ));
        }
        let [_, dy, dz] = a.out_dims;
        let site_labels: Vec<u8> = a
            .coarse_coords
            .iter()
            .map(|c| {
                labels
                    .get(c[0] as usize)
                    .and_then(|l| l.get((c[1] as usize * dy + c[2] as usize) * dz + c[3] as usize))
                    .copied()
                    .unwrap_or(IGNORE)
            })
            .collect();
        out.push((
            LossKey::CoarseCe,
            cross_entropy_weighted(a.coarse_logits.clone(), &site_labels, class_weights, IGNORE)?
                .mul_scalar(a.coarse_weight),
        ));
        Ok(out)
    }
}
