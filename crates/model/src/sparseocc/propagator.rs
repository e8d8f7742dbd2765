//! Sparse latent propagator (paper Sec. 3.2, "SparseLatentDiffuser" in the official code; docs/reference_models.md §1).
//!
//! `L` stages; stage `l` works at stride `2^l` of the LSS grid and is
//! 1. a **sparse completion block**: regular (dilating) sparse convolutions, each followed by
//!    BatchNorm + LeakyReLU, which grow the active set: `n_l` layers with kernel `k x k x 1`, then (3D
//!    stages only) `k x 1 x k` and `1 x k x k` (official `CompletionBlock`, `num_layers = [3, 2, 2, 1]`;
//!    the paper describes the minimal one-layer-each version);
//! 2. a **contextual aggregation block**: two parallel submanifold branches summed, so the active set
//!    does not change. 3D stages follow the official `ContxAggreBlock`: `[k x k x 1 -> k x 1 x k]` +
//!    `[1 x k x k -> k x k x 1]`. The last `planar_stages` stages "omit the height dimension" (paper):
//!    two parallel `5 x 5 x 1` submanifold branches. Every convolution is followed by BatchNorm +
//!    LeakyReLU (the paper leaves the placement open; with a norm and activation per branch the two
//!    parallel 5x5x1 branches are not a single linear map);
//! 3. except for the last stage, a **stride-2 downsample**: a regular sparse convolution with kernel 3,
//!    stride 2, padding 1 (+ BN + LeakyReLU), whose output is the next stage's input.
//!
//! The stage outputs before downsampling form the feature pyramid `{V_l}` (official `skip1..4`):
//! channels `channels[l]` at stride `2^l`.
//! Channels: completion keeps the stage's input channels, aggregation maps them to `channels[l]`
//! (official plan 128 -> [128, 256, 512, 1024]).

use crate::error::ModelError;
use burn::prelude::*;
use burn::tensor::activation::leaky_relu;
use occ_sparse::norm::SparseBatchNorm;
use occ_sparse::{ConvKind, SparseConv3d, SparseConv3dConfig, SparseConvBackend, SparseTensor};

/// Configuration of [`SparseLatentPropagator`].
#[derive(Config, Debug)]
pub struct PropagatorConfig {
    /// Input (LSS context) channels.
    pub in_channels: usize,
    /// Output channels of each stage (official `[128, 256, 512, 1024]`); its length is `L`.
    #[config(default = "vec![128, 256, 512, 1024]")]
    pub channels: Vec<usize>,
    /// Number of `k x k x 1` completion layers per stage (official `[3, 2, 2, 1]`).
    #[config(default = "vec![3, 2, 2, 1]")]
    pub completion_layers: Vec<usize>,
    /// How many of the last stages are planar (2D kernels, paper: the last two).
    #[config(default = 2)]
    pub planar_stages: usize,
    /// Orthogonal kernel size `k` (paper: 3).
    #[config(default = 3)]
    pub kernel: usize,
    /// Planar aggregation kernel (paper: 5).
    #[config(default = 5)]
    pub planar_kernel: usize,
    /// LeakyReLU negative slope.
    #[config(default = 0.01)]
    pub negative_slope: f64,
}

impl PropagatorConfig {
    /// Initialises the propagator; errors on empty/mismatched stage lists or even kernels.
    pub fn init<B: Backend>(
        &self,
        device: &B::Device,
    ) -> Result<SparseLatentPropagator<B>, ModelError> {
        let l = self.channels.len();
        if l == 0 || self.completion_layers.len() != l {
            return Err(ModelError::Config(format!(
                "propagator.rs: {} stage channels and {} completion layer counts (need the same, >= 1)",
                l,
                self.completion_layers.len()
            )));
        }
        if self.kernel.is_multiple_of(2) || self.planar_kernel.is_multiple_of(2) {
            return Err(ModelError::Config(format!(
                "propagator.rs: kernels must be odd (kernel {}, planar {})",
                self.kernel, self.planar_kernel
            )));
        }
        if self.in_channels == 0 || self.channels.contains(&0) {
            return Err(ModelError::Config(
                "propagator.rs: channels must be positive".into(),
            ));
        }
        let k = self.kernel;
        let kp = self.planar_kernel;
        let slope = self.negative_slope;
        let mut stages = Vec::with_capacity(l);
        let mut cin = self.in_channels;
        for s in 0..l {
            let planar = s + self.planar_stages >= l;
            let cout = self.channels[s];
            let mut completion = Vec::new();
            for _ in 0..self.completion_layers[s] {
                completion.push(ConvBnAct::new(
                    cin,
                    cin,
                    [k, k, 1],
                    ConvKind::Regular,
                    slope,
                    device,
                ));
            }
            if !planar {
                completion.push(ConvBnAct::new(
                    cin,
                    cin,
                    [k, 1, k],
                    ConvKind::Regular,
                    slope,
                    device,
                ));
                completion.push(ConvBnAct::new(
                    cin,
                    cin,
                    [1, k, k],
                    ConvKind::Regular,
                    slope,
                    device,
                ));
            }
            let sub =
                |ci, co, kern| ConvBnAct::new(ci, co, kern, ConvKind::Submanifold, slope, device);
            let (branch_a, branch_b) = if planar {
                (
                    vec![sub(cin, cout, [kp, kp, 1])],
                    vec![sub(cin, cout, [kp, kp, 1])],
                )
            } else {
                (
                    vec![sub(cin, cout, [k, k, 1]), sub(cout, cout, [k, 1, k])],
                    vec![sub(cin, cout, [1, k, k]), sub(cout, cout, [k, k, 1])],
                )
            };
            let down = (s + 1 < l).then(|| ConvBnAct::new_strided(cout, cout, slope, device));
            stages.push(PropagatorStage {
                completion,
                branch_a,
                branch_b,
                down,
            });
            cin = cout;
        }
        Ok(SparseLatentPropagator { stages })
    }
}

/// Sparse convolution + BatchNorm + LeakyReLU.
#[derive(Module, Debug)]
pub struct ConvBnAct<B: Backend> {
    conv: SparseConv3d<B>,
    bn: SparseBatchNorm<B>,
    slope: f64,
}

impl<B: Backend> ConvBnAct<B> {
    fn new(
        cin: usize,
        cout: usize,
        kernel: [usize; 3],
        kind: ConvKind,
        slope: f64,
        device: &B::Device,
    ) -> Self {
        // "Same" padding for the regular (dilating) stride-1 convolutions, as the official
        // CompletionBlock (pad (1,1,0) for k(3,3,1), ...); ignored by submanifold layers.
        let padding = kernel.map(|k| k / 2);
        Self {
            conv: SparseConv3dConfig::new(cin, cout, kernel)
                .with_kind(kind)
                .with_padding(padding)
                .init(device),
            bn: SparseBatchNorm::new(cout, device),
            slope,
        }
    }

    fn new_strided(cin: usize, cout: usize, slope: f64, device: &B::Device) -> Self {
        Self {
            conv: SparseConv3dConfig::new(cin, cout, [3, 3, 3])
                .with_kind(ConvKind::Regular)
                .with_stride([2, 2, 2])
                .with_padding([1, 1, 1])
                .init(device),
            bn: SparseBatchNorm::new(cout, device),
            slope,
        }
    }
}

impl<B: SparseConvBackend> ConvBnAct<B> {
    /// conv -> BN -> LeakyReLU.
    pub fn forward(&self, x: SparseTensor<B>) -> Result<SparseTensor<B>, ModelError> {
        let y = self.bn.forward(self.conv.forward(x)?)?;
        let slope = self.slope;
        Ok(y.map_feats(|f| leaky_relu(f, slope))?)
    }
}

/// One stage: completion, aggregation, optional downsample.
#[derive(Module, Debug)]
pub struct PropagatorStage<B: Backend> {
    completion: Vec<ConvBnAct<B>>,
    branch_a: Vec<ConvBnAct<B>>,
    branch_b: Vec<ConvBnAct<B>>,
    down: Option<ConvBnAct<B>>,
}

impl<B: SparseConvBackend> PropagatorStage<B> {
    /// The sparse completion block alone (grows the active set).
    pub fn complete(&self, x: SparseTensor<B>) -> Result<SparseTensor<B>, ModelError> {
        self.completion.iter().try_fold(x, |x, l| l.forward(x))
    }

    /// The contextual aggregation block alone (keeps the active set).
    pub fn aggregate(&self, x: SparseTensor<B>) -> Result<SparseTensor<B>, ModelError> {
        let a = self
            .branch_a
            .iter()
            .try_fold(x.clone(), |x, l| l.forward(x))?;
        let b = self.branch_b.iter().try_fold(x, |x, l| l.forward(x))?;
        Ok(occ_sparse::ops::add(&a, &b)?)
    }
}

/// The sparse latent propagator (see the module documentation).
#[derive(Module, Debug)]
pub struct SparseLatentPropagator<B: Backend> {
    /// The `L` stages.
    pub stages: Vec<PropagatorStage<B>>,
}

/// Output of [`SparseLatentPropagator::forward`].
#[derive(Clone, Debug)]
pub struct PropagatorOutput<B: Backend> {
    /// Stage outputs before downsampling; level `l` has stride `2^l` on the LSS grid.
    pub levels: Vec<SparseTensor<B>>,
    /// Active sites after each completion block and each stage (`prop.l{l}.completed`, `.level`).
    pub stats: Vec<(String, usize)>,
}

impl<B: SparseConvBackend> SparseLatentPropagator<B> {
    /// Runs the `L` stages.
    ///
    /// # Shapes
    /// - input: `N` sites x `in_channels` on the LSS grid
    /// - output level `l`: `N_l` sites x `channels[l]` on the grid downsampled `l` times
    pub fn forward(&self, x: SparseTensor<B>) -> Result<PropagatorOutput<B>, ModelError> {
        let mut levels = Vec::with_capacity(self.stages.len());
        let mut stats = Vec::new();
        let mut x = x;
        for (l, stage) in self.stages.iter().enumerate() {
            let completed = stage.complete(x)?;
            stats.push((format!("prop.l{l}.completed"), completed.num_active()));
            let level = stage.aggregate(completed)?;
            stats.push((format!("prop.l{l}.level"), level.num_active()));
            x = match &stage.down {
                Some(down) => down.forward(level.clone())?,
                None => level.clone(),
            };
            levels.push(level);
        }
        Ok(PropagatorOutput { levels, stats })
    }
}
