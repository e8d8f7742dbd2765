//! The image-side convolutions of `occ_model::kernels::conv2d_host` against burn's own ops on the f64 NdArray
//! backend: the fused inference path (`conv_bn_host`: im2col + GEMM with the batch norm folded in)
//! against `Conv2d` -> `BatchNorm` -> `relu`, and the training op (`conv_autodiff`: im2col + GEMM
//! forward, GEMM + col2im backward) against `Conv2d` on `Autodiff<NdArray<f64>>`. In this f64-only
//! binary both host paths are always taken (burn 0.21 fixes a device's float dtype at the first
//! tensor of the process, so they cannot be tested beside f32 tests: there they fall back to burn).

use burn::backend::NdArray;
use burn::module::{Param, RunningState};
use burn::nn::conv::{Conv2d, Conv2dConfig};
use burn::nn::{BatchNorm, BatchNormConfig, PaddingConfig2d};
use burn::prelude::*;
use burn::tensor::activation::relu;
use burn::tensor::Distribution;
use occ_model::kernels::conv2d_host::{conv_autodiff, conv_bn_host};

/// (cin, cout, k, stride, dilation, padding (t, l, b, r), bias, h, w)
type Case = (
    usize,
    usize,
    usize,
    usize,
    usize,
    [usize; 4],
    bool,
    usize,
    usize,
);

const CASES: [Case; 7] = [
    (3, 8, 7, 2, 1, [3, 3, 3, 3], false, 23, 30), // ResNet stem, odd sizes
    (6, 5, 3, 1, 1, [1, 1, 1, 1], true, 9, 11),   // FPN 3x3 with bias
    (6, 5, 3, 2, 1, [1, 1, 1, 1], false, 10, 13), // strided 3x3
    (4, 7, 1, 1, 1, [0, 0, 0, 0], true, 5, 6),    // pointwise (no im2col)
    (4, 7, 1, 2, 1, [0, 0, 0, 0], false, 7, 9),   // strided 1x1 shortcut
    (3, 4, 3, 1, 2, [2, 1, 0, 3], false, 8, 9),   // dilated, asymmetric padding
    (3, 4, 3, 1, 2, [2, 1, 0, 3], true, 8, 9),    // the same with bias
];

fn conv<Be: Backend>(
    (cin, cout, k, s, d, [t, l, b, r], bias, _, _): Case,
    device: &Be::Device,
) -> Conv2d<Be> {
    Conv2dConfig::new([cin, cout], [k, k])
        .with_stride([s, s])
        .with_dilation([d, d])
        .with_padding(PaddingConfig2d::Explicit(t, l, b, r))
        .with_bias(bias)
        .init::<Be>(device)
}

fn random_bn(c: usize, device: &burn::backend::ndarray::NdArrayDevice) -> BatchNorm<NdArray<f64>> {
    let mut bn = BatchNormConfig::new(c).init::<NdArray<f64>>(device);
    let d = Distribution::Uniform(0.5, 1.5);
    bn.gamma = Param::from_tensor(Tensor::random([c], d, device));
    bn.beta = Param::from_tensor(Tensor::random([c], Distribution::Normal(0.0, 1.0), device));
    bn.running_mean =
        RunningState::new(Tensor::random([c], Distribution::Normal(0.0, 1.0), device));
    bn.running_var = RunningState::new(Tensor::random([c], d, device));
    bn
}

/// Inference (`NdArray<f64>`): the fused host convolution equals burn's `Conv2d` -> `BatchNorm`
/// (inference statistics) -> `relu`, and without BN and ReLU the plain `Conv2d`, on every case.
#[test]
fn fused_host_conv_equals_burn_conv_bn_relu() {
    type B = NdArray<f64>;
    let device = Default::default();
    <B as Backend>::seed(&device, 7);
    for case in CASES {
        let (cin, cout, k, s, d, _, _, h, w) = case;
        let conv = conv::<B>(case, &device);
        let bn = random_bn(cout, &device);
        let x = Tensor::<B, 4>::random([2, cin, h, w], Distribution::Normal(0.0, 1.0), &device);
        let want = relu(bn.forward(conv.forward(x.clone())));
        let got = conv_bn_host(&conv, Some(&bn), &x, true).expect("the host path must be taken");
        assert_eq!(got.dims(), want.dims(), "case k{k} s{s} d{d}");
        let err: f64 = (got - want).abs().max().into_scalar();
        assert!(err < 1e-10, "case k{k} s{s} d{d}: max |diff| {err}");
        let got = conv_bn_host(&conv, None, &x, false).expect("the host path must be taken");
        let err: f64 = (got - conv.forward(x)).abs().max().into_scalar();
        assert!(err < 1e-10, "plain case k{k} s{s} d{d}: max |diff| {err}");
    }
}

/// On `Autodiff<NdArray>` (training) the convolution is one op with its own backward; output and
/// the gradients of the input, weight and bias equal burn's `Conv2d` (direct loops) on every case.
#[test]
fn training_conv_op_equals_burn_conv_with_gradients() {
    type A = burn::backend::Autodiff<burn::backend::NdArray<f64>>;
    let device = Default::default();
    <A as Backend>::seed(&device, 11);
    for case in CASES {
        let (cin, _, k, s, d, _, _, h, w) = case;
        let conv = conv::<A>(case, &device);
        let x0 = Tensor::<A, 4>::random([2, cin, h, w], Distribution::Normal(0.0, 1.0), &device);
        let mut results = Vec::new();
        for ours in [true, false] {
            let x = x0.clone().detach().require_grad();
            let y = if ours {
                conv_autodiff(&conv, x.clone()).expect("the training op must be taken")
            } else {
                conv.forward(x.clone())
            };
            let r = Tensor::<A, 4>::from_data(
                TensorData::new(
                    (0..y.shape().num_elements())
                        .map(|i| ((i * 37 % 101) as f64 - 50.0) / 25.0)
                        .collect::<Vec<_>>(),
                    y.dims(),
                ),
                &device,
            );
            let grads = (y.clone() * r).sum().backward();
            let v = |t: Tensor<burn::backend::NdArray<f64>, 4>| -> Vec<f64> {
                t.into_data().to_vec().unwrap()
            };
            let mut got = vec![
                v(y.inner()),
                v(x.grad(&grads).unwrap()),
                v(conv.weight.val().grad(&grads).unwrap()),
            ];
            if let Some(b) = &conv.bias {
                got.push(b.val().grad(&grads).unwrap().into_data().to_vec().unwrap());
            }
            results.push(got);
        }
        for (i, (a, b)) in results[0].iter().zip(&results[1]).enumerate() {
            assert_eq!(a.len(), b.len());
            let err = a
                .iter()
                .zip(b)
                .map(|(x, y)| (x - y).abs())
                .fold(0.0, f64::max);
            assert!(
                err < 1e-9,
                "case k{k} s{s} d{d}, tensor {i}: max |diff| {err}"
            );
        }
    }
}
