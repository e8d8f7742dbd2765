//! Dense baseline: the paper's "all modules disabled" ablation row (docs/paper_notes.md §5): LSS
//! into a DENSE voxel grid → a dense 3D convolutional encoder (`Conv3d 3x3x3`, zero padding 1, + BatchNorm + ReLU per
//! layer) → a linear `1x1x1` head over every voxel. It exists to measure the sparse models against.
//!
//! The dense convolutions run on the gather-GEMM engine of `occ-sparse` with EVERY voxel of the grid
//! active: a 3x3x3 submanifold convolution over a full grid is exactly a dense `Conv3d` with zero
//! padding 1 (neighbours outside the grid are absent, i.e. zero), computed at GEMM speed. burn-ndarray's
//! own `conv3d` is a direct loop (about 0.5 GFLOP/s on the 2-core CPU, 30-60x slower than GEMM), which
//! would make the baseline an unfair peer; `tests/model_f64/so_units.rs` checks the layer against
//! burn's `conv3d`. Weights use the sparse layout `[Cout, kx, ky, kz, Cin]`.
//!
//! Losses: weighted cross-entropy (ignore 255) over all prediction-grid voxels against the
//! downsampled labels ([`crate::targets::downsample_labels_mode`]) and the LSS depth loss.

use crate::batch::Batch;
use crate::error::ModelError;
use crate::kernels::ModelBackend;
use crate::loss::{cross_entropy_weighted, LossKey};
use crate::lss::{depth_loss, depth_targets, Lss, LssConfig};
use crate::output::ModelOutput;
use crate::profile::Stage;
use crate::targets::{check_input, targets_at};
use burn::nn::{Linear, LinearConfig};
use burn::prelude::*;
use burn::tensor::activation::relu;
use occ_labels::IGNORE;
use occ_sparse::norm::SparseBatchNorm;
use occ_sparse::{full_grid_coords, SparseConv3d, SparseConv3dConfig, SparseTensor};

/// Configuration of [`DenseBaseline`].
#[derive(Config, Debug)]
pub struct DenseBaselineConfig {
    /// Number of classes including empty.
    pub num_classes: usize,
    /// Image feature channels.
    pub feat_channels: usize,
    /// Full-resolution grid shape.
    pub full_dims: [usize; 3],
    /// LSS context channels.
    #[config(default = 128)]
    pub lss_channels: usize,
    /// LSS depth-net hidden channels.
    #[config(default = 256)]
    pub lss_mid_channels: usize,
    /// Depth bins `[min, max, step]` (m).
    #[config(default = "[2.0, 58.0, 0.5]")]
    pub dbound: [f64; 3],
    /// LSS grid downsampling (2 = 1/2 resolution).
    #[config(default = 2)]
    pub lss_downsample: usize,
    /// Camera-aware depth net.
    #[config(default = true)]
    pub camera_aware: bool,
    /// Output channels of each dense 3x3x3 encoder layer.
    #[config(default = "vec![128, 128, 128]")]
    pub encoder_channels: Vec<usize>,
    /// Depth loss weight.
    #[config(default = 1.0)]
    pub depth_weight: f64,
}

impl DenseBaselineConfig {
    /// Initialises the model.
    pub fn init<B: Backend>(&self, device: &B::Device) -> Result<DenseBaseline<B>, ModelError> {
        if self.num_classes < 2 || self.full_dims.contains(&0) || self.encoder_channels.contains(&0)
        {
            return Err(ModelError::Config(format!(
                "dense_baseline.rs: num_classes {}, full_dims {:?}, encoder channels {:?}",
                self.num_classes, self.full_dims, self.encoder_channels
            )));
        }
        let lss = LssConfig::new(self.feat_channels, self.lss_channels)
            .with_mid_channels(self.lss_mid_channels)
            .with_dbound(self.dbound)
            .with_downsample(self.lss_downsample)
            .with_camera_aware(self.camera_aware)
            .init(device)?;
        let mut convs = Vec::new();
        let mut norms = Vec::new();
        let mut cin = self.lss_channels;
        for &cout in &self.encoder_channels {
            convs.push(dense_conv_config(cin, cout).init(device));
            norms.push(SparseBatchNorm::new(cout, device));
            cin = cout;
        }
        Ok(DenseBaseline {
            lss,
            convs,
            norms,
            head: LinearConfig::new(cin, self.num_classes).init(device),
            num_classes: self.num_classes,
            feat_channels: self.feat_channels,
            full_dims: self.full_dims,
            lss_downsample: self.lss_downsample,
            depth_weight: self.depth_weight,
        })
    }
}

/// The dense `3x3x3` convolution (zero padding 1, no bias) as a submanifold convolution, which it is
/// on a grid whose every voxel is active.
pub fn dense_conv_config(channels_in: usize, channels_out: usize) -> SparseConv3dConfig {
    SparseConv3dConfig::new(channels_in, channels_out, [3, 3, 3])
}

/// LSS + dense 3D CNN + linear head.
#[derive(Module, Debug)]
pub struct DenseBaseline<B: Backend> {
    /// View transform.
    pub lss: Lss<B>,
    convs: Vec<SparseConv3d<B>>,
    norms: Vec<SparseBatchNorm<B>>,
    head: Linear<B>,
    num_classes: usize,
    feat_channels: usize,
    full_dims: [usize; 3],
    lss_downsample: usize,
    depth_weight: f64,
}

/// What the dense baseline's losses need.
#[derive(Clone, Debug)]
pub struct DenseAux<B: Backend> {
    /// Depth logits `[B*V, D, h, w]`.
    pub depth_logits: Tensor<B, 4>,
    /// Depth target bins per feature pixel (`-1`: none), `None` without points.
    pub depth_targets: Option<Vec<i64>>,
    /// Full-resolution grid.
    pub full_dims: [usize; 3],
    /// Full voxels per prediction voxel.
    pub downsample: usize,
    /// Depth loss weight.
    pub depth_weight: f64,
}

/// Output of [`DenseBaseline::forward`].
#[derive(Clone, Debug)]
pub struct DenseOutput<B: Backend> {
    /// Class logits on EVERY voxel of the prediction grid (sites in `(b, x, y, z)` C order);
    /// `losses` is empty.
    pub out: ModelOutput<B>,
    /// Loss inputs.
    pub aux: DenseAux<B>,
}

impl<B: ModelBackend> DenseBaseline<B> {
    /// Runs the model.
    ///
    /// # Shapes
    /// - feats `[B*V, feat_channels, h, w]` at `stride` -> logits `[B·X·Y·Z, num_classes]` on the
    ///   `full_dims / lss_downsample` grid
    pub fn forward(
        &self,
        feats: Tensor<B, 4>,
        stride: usize,
        batch: &Batch<B>,
    ) -> Result<DenseOutput<B>, ModelError> {
        check_input(&feats, batch, self.feat_channels, self.full_dims)?;
        let [_, _, h, w] = feats.dims();
        let lss_out = self.lss.forward(feats, stride, batch)?;
        let x = lss_out.splat_dense()?;
        crate::profile::mark(Stage::Lss, &x);
        let [b, c, dx, dy, dz] = x.dims();
        let coords = full_grid_coords(b, [dx, dy, dz]);
        let feats = x.permute([0, 2, 3, 4, 1]).reshape([b * dx * dy * dz, c]);
        let mut t = SparseTensor::new(coords, feats, [dx, dy, dz], b)?;
        for (conv, norm) in self.convs.iter().zip(&self.norms) {
            t = norm.forward(conv.forward(t)?)?.map_feats(relu)?;
        }
        crate::profile::mark(Stage::DenseEncoder, t.feats());
        let coords = t.coords().to_vec();
        let logits = crate::profile::linear(&self.head, t.into_feats());
        crate::profile::mark(Stage::Head, &logits);
        let hit = lss_out.frustum.hit_voxels().0.len();
        let out = ModelOutput {
            coords,
            logits,
            out_dims: [dx, dy, dz],
            upsample: self.lss_downsample,
            losses: Vec::new(),
            stats: vec![
                ("lss.points".into(), lss_out.frustum.num_points()),
                ("lss.voxels".into(), hit),
                ("dense.voxels".into(), b * dx * dy * dz),
            ],
        };
        let aux = DenseAux {
            depth_logits: lss_out.depth_logits,
            depth_targets: depth_targets(batch, h, w, stride, self.lss.dbound())?,
            full_dims: self.full_dims,
            downsample: self.lss_downsample,
            depth_weight: self.depth_weight,
        };
        Ok(DenseOutput { out, aux })
    }

    /// Number of classes.
    pub fn num_classes(&self) -> usize {
        self.num_classes
    }
}

impl<B: Backend> DenseOutput<B> {
    /// Loss terms: `ce` (weighted, ignore 255, all voxels) and `depth` (when the batch has points).
    pub fn losses(
        &self,
        batch: &Batch<B>,
        class_weights: &[f64],
    ) -> Result<Vec<(LossKey, Tensor<B, 1>)>, ModelError> {
        let labels = targets_at(batch, self.aux.full_dims, self.aux.downsample)?;
        let flat: Vec<u8> = labels.into_iter().flatten().collect();
        let mut out = vec![(
            LossKey::Ce,
            cross_entropy_weighted(self.out.logits.clone(), &flat, class_weights, IGNORE)?,
        )];
        if let Some(t) = &self.aux.depth_targets {
            out.push((
                LossKey::Depth,
                depth_loss(self.aux.depth_logits.clone(), t)?.mul_scalar(self.aux.depth_weight),
            ));
        }
        Ok(out)
    }
}
