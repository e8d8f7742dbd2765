//! ResNet-18/34/50 image backbone with the torchvision module layout (docs/reference_models.md §1; paper
//! Sec. 5.1 uses ResNet-50 / ResNet-101 image backbones, SemanticKITTI runs use a ResNet of this family).
//!
//! Layout, exactly as torchvision's `resnet18/34/50` (the "v1.5" variant for ResNet-50, i.e. the
//! stride of a downsampling Bottleneck sits on its 3x3 convolution):
//!
//! - stem: `conv1` 7x7 stride 2 padding 3 (no bias) → `bn1` → ReLU → `maxpool` 3x3 stride 2 padding 1;
//! - `layer1` .. `layer4` with `[2, 2, 2, 2]` (18) or `[3, 4, 6, 3]` (34, 50) blocks, `planes` =
//!   `base_width · [1, 2, 4, 8]`, first block of layers 2..4 with stride 2;
//! - BasicBlock (18/34): 3x3 conv (stride) → BN → ReLU → 3x3 conv → BN, + identity, ReLU;
//! - Bottleneck (50, expansion 4): 1x1 conv → BN → ReLU → 3x3 conv (stride) → BN → ReLU → 1x1 conv to
//!   `4·planes` → BN, + identity, ReLU;
//! - `downsample` (1x1 conv with the block's stride, no bias → BN) when the stride is not 1 or the
//!   channel count changes.
//!
//! Module field names equal torchvision's state-dict names (`conv1`, `bn1`, `layer1.0.conv1`,
//! `layer2.0.downsample.0`, `layer2.0.downsample.1`, ...) so a torchvision checkpoint loads with
//! [`crate::encoder::weights`] without renaming; the classifier (`avgpool`, `fc`) is not built.
//!
//! `base_width` is the stem width (torchvision: 64); a small value gives a tiny CPU model with the same
//! structure. It is *not* torchvision's `width_per_group`. Stages after the last requested output
//! index are not built (their checkpoint tensors are reported as unused when loading).
//!
//! Batch norm follows burn: batch statistics on an autodiff backend, running statistics otherwise
//! (call `.valid()` on an autodiff module for evaluation-mode normalisation).

use crate::kernels::conv2d_host::conv_bn;
use crate::kernels::ModelBackend;
use burn::config::Config;
use burn::module::{Initializer, Module};
use burn::nn::conv::{Conv2d, Conv2dConfig};
use burn::nn::pool::{MaxPool2d, MaxPool2dConfig};
use burn::nn::{BatchNorm, BatchNormConfig, PaddingConfig2d};
use burn::tensor::activation::relu;
use burn::tensor::backend::Backend;
use burn::tensor::Tensor;

use crate::error::ModelError;

/// Number of residual stages (`layer1` .. `layer4`).
pub const NUM_STAGES: usize = 4;

/// Output stride of stage `i` (0-based: `layer1` → 4, `layer2` → 8, `layer3` → 16, `layer4` → 32).
pub fn stage_stride(stage: usize) -> usize {
    4usize << stage
}

/// Residual block kind.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum BlockKind {
    /// Two 3x3 convolutions, expansion 1 (ResNet-18/34).
    Basic,
    /// 1x1 → 3x3 (stride) → 1x1 convolutions, expansion 4 (ResNet-50, torchvision v1.5).
    Bottleneck,
}

impl BlockKind {
    /// Output channels / `planes`.
    pub fn expansion(self) -> usize {
        match self {
            BlockKind::Basic => 1,
            BlockKind::Bottleneck => 4,
        }
    }
}

/// Configuration of a [`ResNet`].
#[derive(Config, Debug)]
pub struct ResNetConfig {
    /// Depth: 18, 34 or 50.
    #[config(default = 18)]
    pub depth: usize,
    /// Stem width (torchvision: 64); stage `i` has `base_width · 2^i` planes.
    #[config(default = 64)]
    pub base_width: usize,
    /// Which stages to return, 0-based (`0` = `layer1`, stride 4 .. `3` = `layer4`, stride 32);
    /// strictly increasing, non-empty.
    #[config(default = "vec![0, 1, 2, 3]")]
    pub out_indices: Vec<usize>,
    /// Input image channels.
    #[config(default = 3)]
    pub in_channels: usize,
}

impl ResNetConfig {
    /// Block kind and number of blocks per stage for this depth.
    pub fn architecture(&self) -> Result<(BlockKind, [usize; NUM_STAGES]), ModelError> {
        match self.depth {
            18 => Ok((BlockKind::Basic, [2, 2, 2, 2])),
            34 => Ok((BlockKind::Basic, [3, 4, 6, 3])),
            50 => Ok((BlockKind::Bottleneck, [3, 4, 6, 3])),
            d => Err(ModelError::Config(format!(
                "ResNet depth {d} is not supported (18, 34 or 50)"
            ))),
        }
    }

    /// Checks depth, widths and `out_indices`.
    pub fn validate(&self) -> Result<(), ModelError> {
        self.architecture()?;
        if self.base_width == 0 || self.in_channels == 0 {
            return Err(ModelError::Config(format!(
                "ResNet base_width ({}) and in_channels ({}) must be positive",
                self.base_width, self.in_channels
            )));
        }
        if self.out_indices.is_empty() {
            return Err(ModelError::Config("ResNet out_indices is empty".into()));
        }
        let increasing = self.out_indices.windows(2).all(|w| w[0] < w[1]);
        let in_range = self.out_indices.iter().all(|&i| i < NUM_STAGES);
        if !increasing || !in_range {
            return Err(ModelError::Config(format!(
                "ResNet out_indices {:?} must be strictly increasing stage indices in 0..{NUM_STAGES}",
                self.out_indices
            )));
        }
        Ok(())
    }

    /// Channels of each returned feature map (in `out_indices` order).
    pub fn out_channels(&self) -> Result<Vec<usize>, ModelError> {
        self.validate()?;
        let (kind, _) = self.architecture()?;
        Ok(self
            .out_indices
            .iter()
            .map(|&i| (self.base_width << i) * kind.expansion())
            .collect())
    }

    /// Output strides of the returned feature maps (in `out_indices` order): 4, 8, 16, 32.
    pub fn strides(&self) -> Vec<usize> {
        self.out_indices.iter().map(|&i| stage_stride(i)).collect()
    }

    /// Builds the backbone with torchvision's initialisation (conv: Kaiming normal, fan-out, ReLU gain;
    /// BN: weight 1, bias 0, running mean 0, running variance 1).
    pub fn init<B: Backend>(&self, device: &B::Device) -> Result<ResNet<B>, ModelError> {
        self.validate()?;
        let (kind, blocks) = self.architecture()?;
        let last = self
            .out_indices
            .iter()
            .copied()
            .max()
            .unwrap_or(NUM_STAGES - 1);
        let w = self.base_width;
        let conv1 = conv(self.in_channels, w, 7, 2, 3, device);
        let bn1 = BatchNormConfig::new(w).init(device);
        let maxpool = MaxPool2dConfig::new([3, 3])
            .with_strides([2, 2])
            .with_padding(PaddingConfig2d::Explicit(1, 1, 1, 1))
            .init();
        let mut inplanes = w;
        let mut layers: Vec<Vec<ResBlock<B>>> = Vec::with_capacity(NUM_STAGES);
        for (stage, &count) in blocks.iter().enumerate() {
            if stage > last {
                layers.push(Vec::new());
                continue;
            }
            let planes = w << stage;
            let stride = if stage == 0 { 1 } else { 2 };
            let mut layer = Vec::with_capacity(count);
            for b in 0..count {
                let s = if b == 0 { stride } else { 1 };
                layer.push(ResBlock::new(kind, inplanes, planes, s, device));
                inplanes = planes * kind.expansion();
            }
            layers.push(layer);
        }
        let mut it = layers.into_iter();
        let mut next = || it.next().unwrap_or_default();
        let (layer1, layer2, layer3, layer4) = (next(), next(), next(), next());
        Ok(ResNet {
            conv1,
            bn1,
            maxpool,
            layer1,
            layer2,
            layer3,
            layer4,
            out_indices: self.out_indices.clone(),
        })
    }
}

/// Bias-free convolution with torchvision's ResNet initialisation
/// (`kaiming_normal_(mode="fan_out", nonlinearity="relu")`).
fn conv<B: Backend>(
    cin: usize,
    cout: usize,
    k: usize,
    stride: usize,
    pad: usize,
    device: &B::Device,
) -> Conv2d<B> {
    Conv2dConfig::new([cin, cout], [k, k])
        .with_stride([stride, stride])
        .with_padding(PaddingConfig2d::Explicit(pad, pad, pad, pad))
        .with_bias(false)
        .with_initializer(Initializer::KaimingNormal {
            gain: std::f64::consts::SQRT_2,
            fan_out_only: true,
        })
        .init(device)
}

/// One residual block (BasicBlock when `conv3`/`bn3` are absent, Bottleneck otherwise); field names are
/// torchvision's.
#[derive(Module, Debug)]
pub struct ResBlock<B: Backend> {
    /// Basic: 3x3 (stride). Bottleneck: 1x1.
    pub conv1: Conv2d<B>,
    /// BN after `conv1`.
    pub bn1: BatchNorm<B>,
    /// 3x3; carries the stride in a Bottleneck.
    pub conv2: Conv2d<B>,
    /// BN after `conv2`.
    pub bn2: BatchNorm<B>,
    /// Bottleneck only: 1x1 expansion to `4·planes`.
    pub conv3: Option<Conv2d<B>>,
    /// Bottleneck only: BN after `conv3`.
    pub bn3: Option<BatchNorm<B>>,
    /// Projection shortcut: (1x1 conv with the block stride, BN), torchvision `downsample.0/1`.
    pub downsample: Option<(Conv2d<B>, BatchNorm<B>)>,
}

impl<B: Backend> ResBlock<B> {
    fn new(
        kind: BlockKind,
        inplanes: usize,
        planes: usize,
        stride: usize,
        device: &B::Device,
    ) -> Self {
        let out = planes * kind.expansion();
        let downsample = (stride != 1 || inplanes != out).then(|| {
            (
                conv(inplanes, out, 1, stride, 0, device),
                BatchNormConfig::new(out).init(device),
            )
        });
        match kind {
            BlockKind::Basic => ResBlock {
                conv1: conv(inplanes, planes, 3, stride, 1, device),
                bn1: BatchNormConfig::new(planes).init(device),
                conv2: conv(planes, planes, 3, 1, 1, device),
                bn2: BatchNormConfig::new(planes).init(device),
                conv3: None,
                bn3: None,
                downsample,
            },
            BlockKind::Bottleneck => ResBlock {
                conv1: conv(inplanes, planes, 1, 1, 0, device),
                bn1: BatchNormConfig::new(planes).init(device),
                conv2: conv(planes, planes, 3, stride, 1, device),
                bn2: BatchNormConfig::new(planes).init(device),
                conv3: Some(conv(planes, out, 1, 1, 0, device)),
                bn3: Some(BatchNormConfig::new(out).init(device)),
                downsample,
            },
        }
    }
}

impl<B: ModelBackend> ResBlock<B> {
    /// `[N, inplanes, H, W]` → `[N, planes·expansion, H/stride, W/stride]` (ceil for odd sizes).
    pub fn forward(&self, x: Tensor<B, 4>) -> Tensor<B, 4> {
        let identity = match &self.downsample {
            Some((conv, bn)) => conv_bn(conv, Some(bn), x.clone(), false),
            None => x.clone(),
        };
        let out = conv_bn(&self.conv1, Some(&self.bn1), x, true);
        let bottleneck = self.conv3.is_some() && self.bn3.is_some();
        // The Bottleneck's ReLU between bn2 and conv3 is fused into the conv2 step.
        let out = conv_bn(&self.conv2, Some(&self.bn2), out, bottleneck);
        let out = match (&self.conv3, &self.bn3) {
            (Some(conv3), Some(bn3)) => conv_bn(conv3, Some(bn3), out, false),
            _ => out,
        };
        relu(out + identity)
    }
}

/// The stem of `resnet`: `maxpool(relu(bn1(conv1(images))))`, the input of `layer1`.
///
/// # Shapes
/// - `images`: `[N, in_channels, H, W]` → `[N, base_width, ⌈H/4⌉, ⌈W/4⌉]`
pub fn stem_forward<B: ModelBackend>(resnet: &ResNet<B>, images: Tensor<B, 4>) -> Tensor<B, 4> {
    resnet
        .maxpool
        .forward(conv_bn(&resnet.conv1, Some(&resnet.bn1), images, true))
}

/// ResNet backbone (torchvision layout, no classifier). Build with [`ResNetConfig::init`].
#[derive(Module, Debug)]
pub struct ResNet<B: Backend> {
    /// Stem 7x7 stride-2 convolution.
    pub conv1: Conv2d<B>,
    /// Stem BN.
    pub bn1: BatchNorm<B>,
    /// Stem 3x3 stride-2 max pooling (padding 1).
    pub maxpool: MaxPool2d,
    /// Stage 1 (stride 4).
    pub layer1: Vec<ResBlock<B>>,
    /// Stage 2 (stride 8).
    pub layer2: Vec<ResBlock<B>>,
    /// Stage 3 (stride 16); empty when not needed by `out_indices`.
    pub layer3: Vec<ResBlock<B>>,
    /// Stage 4 (stride 32); empty when not needed by `out_indices`.
    pub layer4: Vec<ResBlock<B>>,
    /// Returned stages (0-based), strictly increasing.
    pub out_indices: Vec<usize>,
}

impl<B: ModelBackend> ResNet<B> {
    /// `images` `[N, in_channels, H, W]` → one feature map per `out_indices` entry, stage `i` of shape
    /// `[N, C_i, ⌈H/2^(i+2)⌉, ⌈W/2^(i+2)⌉]` (exact torchvision arithmetic for odd sizes).
    pub fn forward(&self, images: Tensor<B, 4>) -> Vec<Tensor<B, 4>> {
        let mut x = stem_forward(self, images);
        let last = self.out_indices.iter().copied().max().unwrap_or(0);
        let mut outs = Vec::with_capacity(self.out_indices.len());
        for (stage, layer) in self.stages().into_iter().enumerate() {
            if stage > last {
                break;
            }
            for block in layer {
                x = block.forward(x);
            }
            if self.out_indices.contains(&stage) {
                outs.push(x.clone());
            }
        }
        outs
    }

    /// Output strides of the returned maps (in `out_indices` order).
    pub fn strides(&self) -> Vec<usize> {
        self.out_indices.iter().map(|&i| stage_stride(i)).collect()
    }

    /// Channels of the returned maps (in `out_indices` order), read from the built layers.
    pub fn out_channels(&self) -> Vec<usize> {
        let stages = self.stages();
        self.out_indices
            .iter()
            .filter_map(|&i| stages.get(i).and_then(|l| l.last()))
            .map(|b| match &b.bn3 {
                Some(bn3) => bn3.gamma.dims()[0],
                None => b.bn2.gamma.dims()[0],
            })
            .collect()
    }

    fn stages(&self) -> [&Vec<ResBlock<B>>; NUM_STAGES] {
        [&self.layer1, &self.layer2, &self.layer3, &self.layer4]
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use burn::backend::NdArray;

    type Be = NdArray<f32>;

    fn shapes(depth: usize, width: usize, out: Vec<usize>, hw: [usize; 2]) -> Vec<[usize; 4]> {
        let device = Default::default();
        let cfg = ResNetConfig::new()
            .with_depth(depth)
            .with_base_width(width)
            .with_out_indices(out);
        let net: ResNet<Be> = cfg.init(&device).expect("valid config");
        let x = Tensor::<Be, 4>::zeros([2, 3, hw[0], hw[1]], &device);
        let outs = net.forward(x);
        assert_eq!(net.out_channels(), cfg.out_channels().unwrap());
        assert_eq!(net.strides(), cfg.strides());
        outs.iter().map(|t| t.dims()).collect()
    }

    #[test]
    fn output_shapes_and_strides_18_34_50() {
        // 64x96: stride s → [64/s, 96/s].
        for (depth, exp) in [(18, 1), (34, 1), (50, 4)] {
            let got = shapes(depth, 2, vec![0, 1, 2, 3], [64, 96]);
            let want: Vec<[usize; 4]> = (0..4)
                .map(|i| [2, (2 << i) * exp, 64 / (4 << i), 96 / (4 << i)])
                .collect();
            assert_eq!(got, want, "depth {depth}");
        }
        // Odd size 70x90 (torchvision arithmetic): 35x45 → pool 18x23 → 9x12 → 5x6 → 3x3.
        let got = shapes(18, 2, vec![1, 3], [70, 90]);
        assert_eq!(got, vec![[2, 4, 9, 12], [2, 16, 3, 3]]);
    }

    #[test]
    fn block_counts_and_unbuilt_stages() {
        let device = Default::default();
        let net: ResNet<Be> = ResNetConfig::new()
            .with_depth(34)
            .with_base_width(2)
            .with_out_indices(vec![1])
            .init(&device)
            .unwrap();
        assert_eq!(
            [
                net.layer1.len(),
                net.layer2.len(),
                net.layer3.len(),
                net.layer4.len()
            ],
            [3, 4, 0, 0]
        );
        assert_eq!(net.strides(), vec![8]);
        let net: ResNet<Be> = ResNetConfig::new()
            .with_depth(50)
            .with_base_width(2)
            .init(&device)
            .unwrap();
        let counts = [
            net.layer1.len(),
            net.layer2.len(),
            net.layer3.len(),
            net.layer4.len(),
        ];
        assert_eq!(counts, [3, 4, 6, 3]);
        // Bottleneck v1.5: the stride sits on conv2 (3x3), layer1.0 has a stride-1 projection 2 → 8.
        assert_eq!(net.layer2[0].conv2.stride, [2, 2]);
        assert_eq!(net.layer2[0].conv1.stride, [1, 1]);
        let ds = net.layer1[0].downsample.as_ref().expect("projection");
        assert_eq!(ds.0.weight.dims(), [8, 2, 1, 1]);
        assert_eq!(ds.0.stride, [1, 1]);
        assert!(net.layer1[1].downsample.is_none());
        // ResNet-18 layer1 has no projection (64 → 64 at stride 1).
        let net: ResNet<Be> = ResNetConfig::new()
            .with_base_width(2)
            .init(&device)
            .unwrap();
        assert!(net.layer1[0].downsample.is_none());
        assert!(net.layer2[0].downsample.is_some());
        assert_eq!(net.layer2[0].conv1.stride, [2, 2]);
    }

    #[test]
    fn invalid_configs_are_errors() {
        let device = Default::default();
        let bad = [
            ResNetConfig::new().with_depth(101),
            ResNetConfig::new().with_base_width(0),
            ResNetConfig::new().with_out_indices(vec![]),
            ResNetConfig::new().with_out_indices(vec![2, 1]),
            ResNetConfig::new().with_out_indices(vec![4]),
        ];
        for cfg in bad {
            let r: Result<ResNet<Be>, _> = cfg.init(&device);
            assert!(matches!(r, Err(ModelError::Config(_))), "{cfg:?}");
        }
    }
}
