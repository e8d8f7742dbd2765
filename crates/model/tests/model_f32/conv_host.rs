//! The fused f32 host convolution of inference (`occ_model::kernels::conv2d_host::conv_bn_host`) against
//! burn's own f32 `Conv2d` -> `BatchNorm` -> `relu` (the f64 cases are in `model_f64/conv_train.rs`).

use burn::backend::NdArray;
use burn::module::{Param, RunningState};
use burn::nn::conv::Conv2dConfig;
use burn::nn::{BatchNormConfig, PaddingConfig2d};
use burn::prelude::*;
use burn::tensor::activation::relu;
use burn::tensor::Distribution;
use occ_model::kernels::conv2d_host::conv_bn_host;

#[test]
fn f32_host_conv_equals_burn_conv_bn_relu() {
    type B = NdArray<f32>;
    let device = Default::default();
    <B as Backend>::seed(&device, 3);
    let conv = Conv2dConfig::new([16, 24], [3, 3])
        .with_padding(PaddingConfig2d::Explicit(1, 1, 1, 1))
        .init::<B>(&device);
    let mut bn = BatchNormConfig::new(24).init::<B>(&device);
    let d = Distribution::Uniform(0.5, 1.5);
    bn.gamma = Param::from_tensor(Tensor::random([24], d, &device));
    bn.beta = Param::from_tensor(Tensor::random(
        [24],
        Distribution::Normal(0.0, 1.0),
        &device,
    ));
    bn.running_mean = RunningState::new(Tensor::random(
        [24],
        Distribution::Normal(0.0, 1.0),
        &device,
    ));
    bn.running_var = RunningState::new(Tensor::random([24], d, &device));
    let x = Tensor::<B, 4>::random([1, 16, 12, 17], Distribution::Normal(0.0, 1.0), &device);
    let want = relu(bn.forward(conv.forward(x.clone())));
    let got = conv_bn_host(&conv, Some(&bn), &x, true).expect("the f32 host path must be taken");
    assert_eq!(got.dims(), want.dims());
    let err: f32 = (got - want).abs().max().into_scalar();
    assert!(err < 1e-4, "f32 max |diff| {err}");
}
