//! Feature pyramid network neck and the complete image encoder (ResNet + FPN; docs/reference_models.md §1):
//! images → multi-scale 2D features for LSS (SparseOcc, paper Sec. 3) and deformable cross attention
//! (SparseOcc++, paper Sec. 4).
//!
//! FPN as in Lin et al. 2017 / mmdet's `FPN` with `start_level = 0`, no extra levels and no norm:
//! lateral 1x1 convolutions (with bias) bring every input level to `out_channels`; top-down, each
//! coarser lateral is upsampled with nearest-neighbour interpolation *to the size of the finer level*
//! (so odd sizes work: source index `⌊dst · in / out⌋`, PyTorch's `mode="nearest"`) and added; a 3x3
//! convolution (padding 1, with bias) is applied to every merged level. Initialisation as mmdet: Xavier
//! uniform weights, zero biases. Field names `lateral_convs.{i}` / `fpn_convs.{i}` (mmdet's keys without
//! the `ConvModule` `.conv` level).

use crate::kernels::conv2d_host::conv_bn;
use crate::kernels::ModelBackend;
use burn::config::Config;
use burn::module::{Initializer, Module};
use burn::nn::conv::{Conv2d, Conv2dConfig};
use burn::nn::PaddingConfig2d;
use burn::tensor::backend::Backend;
use burn::tensor::{Int, Tensor, TensorData};

use crate::encoder::backbone::{ResNet, ResNetConfig};
use crate::error::ModelError;

/// Configuration of an [`Fpn`]; the input channels come from the backbone (see [`FpnConfig::init`]).
#[derive(Config, Debug)]
pub struct FpnConfig {
    /// Channels of every output level.
    #[config(default = 256)]
    pub out_channels: usize,
}

impl FpnConfig {
    /// Builds an FPN over input levels with `in_channels` (finest first).
    pub fn init<B: Backend>(
        &self,
        in_channels: &[usize],
        device: &B::Device,
    ) -> Result<Fpn<B>, ModelError> {
        if in_channels.is_empty() || in_channels.contains(&0) || self.out_channels == 0 {
            return Err(ModelError::Config(format!(
                "FPN needs at least one input level and positive channels (in {in_channels:?}, out {})",
                self.out_channels
            )));
        }
        let c = self.out_channels;
        let lateral_convs = in_channels
            .iter()
            .map(|&cin| conv_with_bias(cin, c, 1, 0, device))
            .collect();
        let fpn_convs = in_channels
            .iter()
            .map(|_| conv_with_bias(c, c, 3, 1, device))
            .collect();
        Ok(Fpn {
            lateral_convs,
            fpn_convs,
            in_channels: in_channels.to_vec(),
            out_channels: c,
        })
    }
}

/// Xavier-uniform weight, zero bias (mmdet FPN `init_cfg`).
fn conv_with_bias<B: Backend>(
    cin: usize,
    cout: usize,
    k: usize,
    pad: usize,
    device: &B::Device,
) -> Conv2d<B> {
    let mut conv = Conv2dConfig::new([cin, cout], [k, k])
        .with_padding(PaddingConfig2d::Explicit(pad, pad, pad, pad))
        .with_bias(true)
        .with_initializer(Initializer::XavierUniform { gain: 1.0 })
        .init(device);
    conv.bias = Some(Initializer::Zeros.init([cout], device));
    conv
}

/// Feature pyramid network (see the module docs). Build with [`FpnConfig::init`].
#[derive(Module, Debug)]
pub struct Fpn<B: Backend> {
    /// 1x1 lateral convolutions, one per input level (finest first).
    pub lateral_convs: Vec<Conv2d<B>>,
    /// 3x3 output convolutions, one per level.
    pub fpn_convs: Vec<Conv2d<B>>,
    /// Expected input channels per level.
    pub in_channels: Vec<usize>,
    /// Output channels of every level.
    pub out_channels: usize,
}

impl<B: ModelBackend> Fpn<B> {
    /// `inputs[i]` `[N, in_channels[i], H_i, W_i]` (finest first) → `[N, out_channels, H_i, W_i]` each.
    ///
    /// Errors if the number of levels, batch sizes or channels differ from the configuration.
    pub fn forward(&self, inputs: Vec<Tensor<B, 4>>) -> Result<Vec<Tensor<B, 4>>, ModelError> {
        if inputs.len() != self.in_channels.len() {
            return Err(ModelError::Input(format!(
                "FPN expects {} levels, got {}",
                self.in_channels.len(),
                inputs.len()
            )));
        }
        let n = inputs.first().map(|t| t.dims()[0]).unwrap_or(0);
        for (i, (t, &c)) in inputs.iter().zip(&self.in_channels).enumerate() {
            let d = t.dims();
            if d[1] != c || d[0] != n {
                return Err(ModelError::Input(format!(
                    "FPN level {i}: expected [{n}, {c}, H, W], got {d:?}"
                )));
            }
        }
        Ok(self.forward_levels(inputs))
    }

    /// Forward without input checks (the caller guarantees the level count and channels).
    fn forward_levels(&self, inputs: Vec<Tensor<B, 4>>) -> Vec<Tensor<B, 4>> {
        let mut laterals: Vec<Tensor<B, 4>> = self
            .lateral_convs
            .iter()
            .zip(inputs)
            .map(|(conv, x)| conv_bn(conv, None, x, false))
            .collect();
        for i in (1..laterals.len()).rev() {
            let [_, _, h, w] = laterals[i - 1].dims();
            let up = resize_nearest(laterals[i].clone(), [h, w]);
            laterals[i - 1] = laterals[i - 1].clone() + up;
        }
        self.fpn_convs
            .iter()
            .zip(laterals)
            .map(|(conv, x)| conv_bn(conv, None, x, false))
            .collect()
    }
}

/// Nearest-neighbour resize, source index `⌊dst · in / out⌋` on each axis (PyTorch's
/// `F.interpolate(mode="nearest")`, which mmdet's FPN uses).
///
/// Built from burn ops whose backward autodiff derives (an integer factor, the FPN's usual 2x:
/// reshape, broadcast, reshape, whose backward is a sum; any other size: `select` of rows and
/// columns, whose backward is a scatter-add), not from burn's `interpolate`. Measured with
/// `check-backend` on lavapipe: with burn's `interpolate` in the FPN, the training step's gradients
/// of `lateral_convs.2` and of every backbone stage under it differed from the CPU reference; with
/// this function they agree. burn's nearest backward alone agrees (`burn_interpolate_*` cases,
/// including a channels-last incoming gradient), so the layout that trips it inside the model is
/// not pinned down; burn-cubecl 0.21's kernel indexes its vectorised gradient with element
/// offsets, which is one candidate (docs/gpu.md).
///
/// # Shapes
/// - `x`: `[N, C, H_in, W_in]` → `[N, C, h, w]`
pub fn resize_nearest<B: Backend>(x: Tensor<B, 4>, [h, w]: [usize; 2]) -> Tensor<B, 4> {
    let [n, c, hi, wi] = x.dims();
    if (hi, wi) == (h, w) {
        return x;
    }
    if hi > 0 && wi > 0 && h % hi == 0 && w % wi == 0 {
        let (sh, sw) = (h / hi, w / wi);
        return x
            .reshape([n, c, hi, 1, wi, 1])
            .expand([n, c, hi, sh, wi, sw])
            .reshape([n, c, h, w]);
    }
    let device = x.device();
    let index = |out: usize, inp: usize| {
        let idx: Vec<i64> = (0..out).map(|d| (d * inp / out) as i64).collect();
        Tensor::<B, 1, Int>::from_data(TensorData::new(idx, [out]), &device)
    };
    x.select(2, index(h, hi)).select(3, index(w, wi))
}

/// Image encoder configuration: a [`ResNetConfig`] backbone and an [`FpnConfig`] neck over the
/// backbone's `out_indices` levels.
#[derive(Config, Debug)]
pub struct ImageEncoderConfig {
    /// Backbone.
    pub resnet: ResNetConfig,
    /// Neck.
    pub fpn: FpnConfig,
}

impl ImageEncoderConfig {
    /// Builds backbone and neck.
    pub fn init<B: Backend>(&self, device: &B::Device) -> Result<ImageEncoder<B>, ModelError> {
        let backbone = self.resnet.init(device)?;
        let neck = self.fpn.init(&self.resnet.out_channels()?, device)?;
        Ok(ImageEncoder { backbone, neck })
    }

    /// Output strides (in `out_indices` order), e.g. `[4, 8, 16, 32]`.
    pub fn strides(&self) -> Vec<usize> {
        self.resnet.strides()
    }
}

/// ResNet backbone + FPN neck. Field names `backbone` / `neck` (checkpoint keys `backbone.*`, `neck.*`).
#[derive(Module, Debug)]
pub struct ImageEncoder<B: Backend> {
    /// ResNet (torchvision layout).
    pub backbone: ResNet<B>,
    /// FPN over the backbone outputs.
    pub neck: Fpn<B>,
}

impl<B: ModelBackend> ImageEncoder<B> {
    /// `images` `[N, 3, H, W]` (N = batch × views) → one `[N, out_channels, ⌈H/s⌉, ⌈W/s⌉]` map per
    /// stride `s` in [`Self::strides`] (finest first).
    pub fn forward(&self, images: Tensor<B, 4>) -> Vec<Tensor<B, 4>> {
        self.neck.forward_levels(self.backbone.forward(images))
    }

    /// Output strides of [`Self::forward`] (finest first).
    pub fn strides(&self) -> Vec<usize> {
        self.backbone.strides()
    }

    /// Channels of every output level.
    pub fn out_channels(&self) -> usize {
        self.neck.out_channels
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use burn::backend::NdArray;
    use burn::module::Param;
    use burn::tensor::TensorData;

    type Be = NdArray<f32>;

    #[test]
    fn encoder_shapes_and_strides() {
        let device = Default::default();
        for depth in [18, 34, 50] {
            let cfg = ImageEncoderConfig::new(
                ResNetConfig::new()
                    .with_depth(depth)
                    .with_base_width(2)
                    .with_out_indices(vec![1, 2, 3]),
                FpnConfig::new().with_out_channels(6),
            );
            let enc: ImageEncoder<Be> = cfg.init(&device).unwrap();
            assert_eq!(enc.strides(), vec![8, 16, 32]);
            assert_eq!(cfg.strides(), vec![8, 16, 32]);
            assert_eq!(enc.out_channels(), 6);
            let outs = enc.forward(Tensor::zeros([2, 3, 70, 90], &device));
            let dims: Vec<[usize; 4]> = outs.iter().map(|t| t.dims()).collect();
            assert_eq!(
                dims,
                vec![[2, 6, 9, 12], [2, 6, 5, 6], [2, 6, 3, 3]],
                "depth {depth}"
            );
        }
    }

    /// Identity laterals / output convs reduce the FPN to its top-down nearest-upsample-and-add
    /// pathway, checked against a direct evaluation of `out[l](y, x) = Σ_{k≥l} in_k(y_k, x_k)` with
    /// `y_{k+1} = ⌊y_k · H_{k+1} / H_k⌋`.
    #[test]
    fn top_down_pathway_matches_brute_force() {
        let device = Default::default();
        let sizes = [[9usize, 12usize], [5, 6], [3, 3]];
        let mut fpn: Fpn<Be> = FpnConfig::new()
            .with_out_channels(1)
            .init(&[1, 1, 1], &device)
            .unwrap();
        let one = |k: usize| {
            let mut w = vec![0.0f32; k * k];
            w[k * k / 2] = 1.0;
            Tensor::<Be, 4>::from_data(TensorData::new(w, [1, 1, k, k]), &device)
        };
        for c in fpn.lateral_convs.iter_mut() {
            c.weight = Param::from_tensor(one(1));
        }
        for c in fpn.fpn_convs.iter_mut() {
            c.weight = Param::from_tensor(one(3));
        }
        let levels: Vec<Vec<f32>> = sizes
            .iter()
            .enumerate()
            .map(|(l, [h, w])| {
                (0..h * w)
                    .map(|i| (i as f32) * 0.37 + l as f32 * 100.0)
                    .collect()
            })
            .collect();
        let inputs = levels
            .iter()
            .zip(&sizes)
            .map(|(v, &[h, w])| {
                Tensor::from_data(TensorData::new(v.clone(), [1, 1, h, w]), &device)
            })
            .collect();
        let outs = fpn.forward(inputs).unwrap();
        for (l, out) in outs.iter().enumerate() {
            let got = out.to_data().to_vec::<f32>().unwrap();
            let [h, w] = sizes[l];
            for y in 0..h {
                for x in 0..w {
                    let (mut yk, mut xk, mut want) = (y, x, 0.0f32);
                    for k in l..sizes.len() {
                        if k > l {
                            yk = yk * sizes[k][0] / sizes[k - 1][0];
                            xk = xk * sizes[k][1] / sizes[k - 1][1];
                        }
                        want += levels[k][yk * sizes[k][1] + xk];
                    }
                    let g = got[y * w + x];
                    assert!(
                        (g - want).abs() < 1e-3,
                        "level {l} ({y},{x}): {g} vs {want}"
                    );
                }
            }
        }
    }

    /// [`resize_nearest`] against burn's `interpolate(Nearest)` on NdArray (correct on the CPU),
    /// forward and the gradient of `Σ y ⊙ r`, at an integer factor, an odd size, a downsampling and
    /// unequal factors per axis.
    #[test]
    fn resize_nearest_matches_burn_interpolate_forward_and_backward() {
        use burn::backend::Autodiff;
        use burn::tensor::module::interpolate;
        use burn::tensor::ops::{InterpolateMode, InterpolateOptions};
        type Ad = Autodiff<Be>;
        let device = Default::default();
        let seq = |n: usize, a: f32| -> Vec<f32> {
            (0..n)
                .map(|i| ((i as f32 * a).sin() * 3.0).round() / 4.0)
                .collect()
        };
        for (src, dst) in [
            ([4usize, 13usize], [8usize, 26usize]),
            ([5, 7], [9, 13]),
            ([6, 8], [3, 5]),
            ([3, 4], [9, 6]),
            ([3, 4], [3, 4]),
        ] {
            let run = |ours: bool| {
                let x = Tensor::<Ad, 4>::from_data(
                    TensorData::new(seq(2 * 3 * src[0] * src[1], 0.7), [2, 3, src[0], src[1]]),
                    &device,
                )
                .require_grad();
                let y = if ours {
                    resize_nearest(x.clone(), dst)
                } else {
                    interpolate(
                        x.clone(),
                        dst,
                        InterpolateOptions::new(InterpolateMode::Nearest),
                    )
                };
                let r = Tensor::<Ad, 4>::from_data(
                    TensorData::new(seq(2 * 3 * dst[0] * dst[1], 1.3), [2, 3, dst[0], dst[1]]),
                    &device,
                );
                let grads = (y.clone() * r).sum().backward();
                let dx = x.grad(&grads).unwrap();
                (
                    y.into_data().to_vec::<f32>().unwrap(),
                    dx.into_data().to_vec::<f32>().unwrap(),
                )
            };
            let (y, dx) = run(true);
            let (y_ref, dx_ref) = run(false);
            assert_eq!(y, y_ref, "forward {src:?} -> {dst:?}");
            for (a, b) in dx.iter().zip(&dx_ref) {
                assert!(
                    (a - b).abs() < 1e-5,
                    "backward {src:?} -> {dst:?}: {a} vs {b}"
                );
            }
        }
    }

    #[test]
    fn fpn_input_errors() {
        let device = Default::default();
        let fpn: Fpn<Be> = FpnConfig::new()
            .with_out_channels(4)
            .init(&[2, 4], &device)
            .unwrap();
        let a = Tensor::<Be, 4>::zeros([1, 2, 8, 8], &device);
        let b = Tensor::<Be, 4>::zeros([1, 3, 4, 4], &device);
        assert!(matches!(
            fpn.forward(vec![a.clone()]),
            Err(ModelError::Input(_))
        ));
        assert!(matches!(fpn.forward(vec![a, b]), Err(ModelError::Input(_))));
        let r: Result<Fpn<Be>, _> = FpnConfig::new().init(&[], &device);
        assert!(matches!(r, Err(ModelError::Config(_))));
    }
}
