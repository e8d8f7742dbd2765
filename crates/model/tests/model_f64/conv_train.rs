//! The image-side convolution of CPU training (`occ_model::conv2d_host::conv_autodiff`: im2col + GEMM
//! forward, GEMM + col2im backward) against burn's `Conv2d` on `Autodiff<NdArray<f64>>`. In this
//! f64-only binary the op is always taken (burn 0.21 fixes a device's float dtype at the first tensor
//! of the process, so it cannot live beside f32 tests).

use burn::nn::conv::Conv2dConfig;
use burn::nn::PaddingConfig2d;
use burn::prelude::*;
use burn::tensor::Distribution;
use occ_model::conv2d_host::conv_autodiff;

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

/// On `Autodiff<NdArray>` (training) the convolution is one op with its own backward; output and
/// the gradients of the input, weight and bias equal burn's `Conv2d` (direct loops) on every case.
#[test]
fn training_conv_op_equals_burn_conv_with_gradients() {
    type A = burn::backend::Autodiff<burn::backend::NdArray<f64>>;
    let device = Default::default();
    <A as Backend>::seed(&device, 11);
    let cases: [Case; 6] = [
        (3, 8, 7, 2, 1, [3, 3, 3, 3], false, 23, 30),
        (6, 5, 3, 1, 1, [1, 1, 1, 1], true, 9, 11),
        (6, 5, 3, 2, 1, [1, 1, 1, 1], false, 10, 13),
        (4, 7, 1, 1, 1, [0, 0, 0, 0], true, 5, 6),
        (4, 7, 1, 2, 1, [0, 0, 0, 0], false, 7, 9),
        (3, 4, 3, 1, 2, [2, 1, 0, 3], true, 8, 9),
    ];
    for (cin, cout, k, s, d, [t, l, b, r], bias, h, w) in cases {
        let conv = Conv2dConfig::new([cin, cout], [k, k])
            .with_stride([s, s])
            .with_dilation([d, d])
            .with_padding(PaddingConfig2d::Explicit(t, l, b, r))
            .with_bias(bias)
            .init::<A>(&device);
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
