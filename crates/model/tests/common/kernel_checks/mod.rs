//! The CPU backends take the host kernels: a ResNet-18 forward pass and a DCA block on `NdArray`
//! run the fused host convolution and the DCA host loop, on `Autodiff<NdArray>` the training ops with
//! their own backward pass (counted by `occ_model::kernels::host_kernel_calls`), while the portable
//! paths called directly count nothing.

use burn::prelude::*;
use burn::tensor::backend::AutodiffBackend;
use burn::tensor::Distribution;
use occ_model::encoder::backbone::ResNetConfig;
use occ_model::kernels::conv2d_host::{conv_bn, conv_bn_portable};
use occ_model::kernels::{host_kernel_calls, HostKernelCalls};
use occ_model::sparseocc_pp::dca::{
    DcaConfig, DcaInputs, DeformableCrossAttention, FeatureRows, ViewHits,
};
use occ_model::ModelBackend;

/// The calls counted since `before`.
pub fn since(before: HostKernelCalls) -> HostKernelCalls {
    let now = host_kernel_calls();
    HostKernelCalls {
        conv2d: now.conv2d - before.conv2d,
        conv2d_autodiff: now.conv2d_autodiff - before.conv2d_autodiff,
        dca: now.dca - before.dca,
        dca_autodiff: now.dca_autodiff - before.dca_autodiff,
    }
}

/// Convolutions of a ResNet-18: the stem, two per basic block (8 blocks), three shortcuts.
pub const RESNET18_CONVS: u64 = 1 + 2 * 8 + 3;

/// Two queries, two images: query 0 seen by both, query 1 by one (3 hits).
pub fn hits() -> ViewHits {
    ViewHits {
        num_queries: 2,
        num_images: 2,
        query: vec![0, 1, 0],
        image: vec![0, 0, 1],
        slot: vec![0, 1, 0],
        uv: vec![[5.0, 7.0], [11.0, 3.0], [2.0, 20.0]],
        depth_m: vec![4.0, 6.0, 5.0],
        views_per_query: vec![2, 1],
        max_per_image: 2,
    }
}

fn dca<B: ModelBackend>(device: &B::Device) -> DeformableCrossAttention<B> {
    DcaConfig::new(8, 4)
        .with_num_heads(2)
        .with_num_levels(2)
        .with_num_points(3)
        .init::<B>(device)
}

fn images<B: Backend>(device: &B::Device) -> [Tensor<B, 4>; 2] {
    let d = Distribution::Normal(0.0, 1.0);
    [
        Tensor::random([2, 4, 6, 5], d, device),
        Tensor::random([2, 4, 3, 3], d, device),
    ]
}

/// The inputs of one ungated DCA attention of `query` over `images` (strides 4 and 8).
fn dca_inputs<'a, B: Backend>(
    query: &Tensor<B, 2>,
    hits: &'a ViewHits,
    images: &'a FeatureRows<B>,
) -> DcaInputs<'a, B> {
    DcaInputs {
        query: query.clone(),
        hits,
        feats: images,
        strides: &[4, 8],
        gate: None,
    }
}

/// Inference: what a ResNet-18 forward pass, one `conv_bn` and one DCA attention count on `B`, and
/// that the portable paths count nothing.
pub fn inference_calls<B: ModelBackend>() -> HostKernelCalls {
    let device: B::Device = Default::default();
    let resnet = ResNetConfig::new()
        .with_base_width(8)
        .init::<B>(&device)
        .expect("valid config");
    let x = Tensor::<B, 4>::random([1, 3, 32, 32], Distribution::Normal(0.0, 1.0), &device);
    let dca = dca::<B>(&device);
    let (hits, images) = (hits(), images::<B>(&device));
    let query = Tensor::<B, 2>::random([2, 8], Distribution::Normal(0.0, 1.0), &device);
    let rows = FeatureRows::from_nchw(&images).unwrap();
    let inputs = || dca_inputs(&query, &hits, &rows);

    // The portable paths, called directly: no host kernel.
    let before = host_kernel_calls();
    let conv = &resnet.conv1;
    conv_bn_portable(conv, Some(&resnet.bn1), x.clone(), true);
    dca.aggregate_tensor_ops(inputs()).unwrap();
    assert_eq!(since(before), HostKernelCalls::default());

    let before = host_kernel_calls();
    let stages = resnet.forward(x.clone());
    assert_eq!(stages.len(), 4);
    conv_bn(conv, Some(&resnet.bn1), x, true);
    let got = dca
        .aggregate(query.clone(), &hits, &images, &[4, 8])
        .unwrap();
    let calls = since(before);
    // The backend's attention is the host loop: the same values, bit for bit.
    let host = dca.aggregate_host(inputs()).unwrap();
    assert_eq!(got.into_data(), host.into_data());
    calls
}

/// Training: what a ResNet-18 forward pass and one DCA attention count on `B`, with a backward pass
/// through both, and that the portable paths count nothing.
pub fn training_calls<B: ModelBackend + AutodiffBackend>() -> HostKernelCalls {
    let device: B::Device = Default::default();
    let resnet = ResNetConfig::new()
        .with_base_width(8)
        .init::<B>(&device)
        .expect("valid config");
    let x = Tensor::<B, 4>::random([1, 3, 32, 32], Distribution::Normal(0.0, 1.0), &device)
        .require_grad();
    let dca = dca::<B>(&device);
    let hits = hits();
    let images: Vec<Tensor<B, 4>> = images::<B>(&device)
        .into_iter()
        .map(|t| t.require_grad())
        .collect();
    let query = Tensor::<B, 2>::random([2, 8], Distribution::Normal(0.0, 1.0), &device);
    let rows = FeatureRows::from_nchw(&images).unwrap();
    let inputs = || dca_inputs(&query, &hits, &rows);

    let before = host_kernel_calls();
    conv_bn_portable(&resnet.conv1, Some(&resnet.bn1), x.clone(), true);
    dca.aggregate_tensor_ops(inputs()).unwrap();
    assert_eq!(since(before), HostKernelCalls::default());

    let before = host_kernel_calls();
    let stages = resnet.forward(x.clone());
    let attn = dca.aggregate_gated(inputs()).unwrap();
    let calls = since(before);
    let loss = stages.into_iter().fold(attn.sum(), |acc, s| acc + s.sum());
    let grads = loss.backward();
    assert!(
        x.grad(&grads).is_some(),
        "no gradient through the convolutions"
    );
    for f in &images {
        assert!(f.grad(&grads).is_some(), "no gradient through the DCA op");
    }
    calls
}

/// Inference backend `I` takes the host kernels for every conv2d (the ResNet-18's and the extra
/// one) and the DCA sampling, and training backend `T` the host autodiff ops for both.
pub fn assert_host_kernels_taken<I: ModelBackend, T: ModelBackend + AutodiffBackend>() {
    let expected = HostKernelCalls {
        conv2d: RESNET18_CONVS + 1,
        dca: 1,
        ..Default::default()
    };
    assert_eq!(inference_calls::<I>(), expected);
    let expected = HostKernelCalls {
        conv2d_autodiff: RESNET18_CONVS,
        dca_autodiff: 1,
        ..Default::default()
    };
    assert_eq!(training_calls::<T>(), expected);
}
