//! Lightweight sparse U-Net (SparseOcc++, paper Sec. 4.3 and Sec. 5.4: "four layers, each consisting of
//! one sparse residual block").
//!
//! - Input: a linear map `C_in → c_0` on every site.
//! - Encoder level `i` (`i = 0..4`): one residual block `x + BN(SubM3(ReLU(BN(SubM3(x)))))` followed by
//!   ReLU (SubM 3×3×3 convolutions, batch norm over the active sites, identity shortcut). Between levels
//!   a strided sparse convolution (kernel 3, stride 2, padding 1, as spconv encoders, so odd sizes keep
//!   every voxel: output size `ceil(n/2)`) + BN + ReLU changes the width `c_i → c_{i+1}`.
//! - Decoder: an inverse convolution of each strided convolution (spconv `SparseInverseConv3d`: the
//!   output sites are exactly that convolution's input sites) + BN + ReLU back to `c_i`, and the skip
//!   of that level is ADDED (the sites are identical, so this is a plain sum).
//! - Output: features `[N, c_0]` on exactly the input sites, in the same order.

use crate::error::ModelError;
use burn::nn::{Linear, LinearConfig};
use burn::prelude::*;
use burn::tensor::activation::relu;
use occ_sparse::norm::SparseBatchNorm;
use occ_sparse::{ConvKind, SparseConv3d, SparseConv3dConfig, SparseConvBackend, SparseTensor};

/// Configuration of [`SparseUNet`].
#[derive(Config, Debug)]
pub struct SparseUNetConfig {
    /// Input feature width.
    pub channels_in: usize,
    /// Width of each level (the paper: four levels).
    pub channels: Vec<usize>,
}

impl SparseUNetConfig {
    /// Checks the widths.
    pub fn validate(&self) -> Result<(), ModelError> {
        if self.channels.is_empty() || self.channels.contains(&0) || self.channels_in == 0 {
            return Err(ModelError::Config(format!(
                "U-Net: channels_in {} and level widths {:?} must be positive and non-empty",
                self.channels_in, self.channels
            )));
        }
        Ok(())
    }

    /// Initialises the network.
    pub fn init<B: Backend>(&self, device: &B::Device) -> SparseUNet<B> {
        let c0 = self.channels.first().copied().unwrap_or(1);
        let blocks = self
            .channels
            .iter()
            .map(|&c| SparseResBlock::new(c, device))
            .collect();
        let down = self
            .channels
            .windows(2)
            .map(|w| ConvBnRelu::new(w[0], w[1], ConvKind::Regular, device))
            .collect();
        let up = self
            .channels
            .windows(2)
            .map(|w| ConvBnRelu::new(w[1], w[0], ConvKind::Inverse, device))
            .collect();
        SparseUNet {
            input: LinearConfig::new(self.channels_in, c0).init(device),
            blocks,
            down,
            up,
        }
    }
}

/// SubM 3³ → BN → ReLU → SubM 3³ → BN, plus identity, then ReLU.
#[derive(Module, Debug)]
pub struct SparseResBlock<B: Backend> {
    /// First convolution.
    pub conv1: SparseConv3d<B>,
    /// First norm.
    pub bn1: SparseBatchNorm<B>,
    /// Second convolution.
    pub conv2: SparseConv3d<B>,
    /// Second norm.
    pub bn2: SparseBatchNorm<B>,
}

impl<B: Backend> SparseResBlock<B> {
    /// A block of width `c`.
    pub fn new(c: usize, device: &B::Device) -> Self {
        let conv = || SparseConv3dConfig::new(c, c, [3, 3, 3]).init(device);
        Self {
            conv1: conv(),
            bn1: SparseBatchNorm::new(c, device),
            conv2: conv(),
            bn2: SparseBatchNorm::new(c, device),
        }
    }
}

impl<B: SparseConvBackend> SparseResBlock<B> {
    /// Same sites in and out.
    pub fn forward(&self, x: SparseTensor<B>) -> Result<SparseTensor<B>, ModelError> {
        let y = self
            .bn1
            .forward(self.conv1.forward(x.clone())?)?
            .map_feats(relu)?;
        let y = self.bn2.forward(self.conv2.forward(y)?)?;
        Ok(x.with_feats(relu(x.feats().clone() + y.into_feats()))?)
    }
}

/// Strided (or inverse) sparse convolution k3 s2 p1 → BN → ReLU.
#[derive(Module, Debug)]
pub struct ConvBnRelu<B: Backend> {
    /// The convolution.
    pub conv: SparseConv3d<B>,
    /// The norm.
    pub bn: SparseBatchNorm<B>,
}

impl<B: Backend> ConvBnRelu<B> {
    fn new(cin: usize, cout: usize, kind: ConvKind, device: &B::Device) -> Self {
        Self {
            conv: SparseConv3dConfig::new(cin, cout, [3, 3, 3])
                .with_kind(kind)
                .with_stride([2, 2, 2])
                .with_padding([1, 1, 1])
                .init(device),
            bn: SparseBatchNorm::new(cout, device),
        }
    }
}

impl<B: SparseConvBackend> ConvBnRelu<B> {
    /// Applies the layer.
    pub fn forward(&self, x: SparseTensor<B>) -> Result<SparseTensor<B>, ModelError> {
        Ok(self.bn.forward(self.conv.forward(x)?)?.map_feats(relu)?)
    }
}

/// The sparse U-Net (see the module docs).
#[derive(Module, Debug)]
pub struct SparseUNet<B: Backend> {
    /// Input projection `C_in → c_0`.
    pub input: Linear<B>,
    /// One residual block per level.
    pub blocks: Vec<SparseResBlock<B>>,
    /// Strided convolutions between levels.
    pub down: Vec<ConvBnRelu<B>>,
    /// Inverse convolutions back up.
    pub up: Vec<ConvBnRelu<B>>,
}

impl<B: SparseConvBackend> SparseUNet<B> {
    /// Output width `c_0`.
    pub fn out_channels(&self) -> usize {
        self.input.weight.dims()[1]
    }

    /// # Shapes
    /// - `[N, C_in]` on some sites → `[N, c_0]` on the same sites (same order)
    pub fn forward(&self, x: SparseTensor<B>) -> Result<SparseTensor<B>, ModelError> {
        if x.num_active() == 0 {
            let device = x.device();
            return Ok(x.with_feats(Tensor::zeros([0, self.out_channels()], &device))?);
        }
        let mut x = x.map_feats(|f| crate::profile::linear(&self.input, f))?;
        let levels = self.blocks.len();
        let mut skips = Vec::with_capacity(levels);
        for (i, block) in self.blocks.iter().enumerate() {
            x = block.forward(x)?;
            crate::profile::trace_mark(&format!("unet block {i}"), x.feats());
            if i + 1 < levels {
                skips.push(x.clone());
                x = self.down[i].forward(x)?;
                crate::profile::trace_mark(&format!("unet down {i}"), x.feats());
            }
        }
        for i in (0..levels.saturating_sub(1)).rev() {
            x = self.up[i].forward(x)?;
            let skip = skips
                .pop()
                .ok_or_else(|| ModelError::Config("U-Net: decoder level without a skip".into()))?;
            x = occ_sparse::ops::add(&skip, &x)?;
            crate::profile::trace_mark(&format!("unet up {i}"), x.feats());
        }
        Ok(x)
    }
}
