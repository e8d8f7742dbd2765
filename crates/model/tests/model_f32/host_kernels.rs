//! The production CPU backends (`NdArray<f32>` for inference, `Autodiff<NdArray<f32>>` for
//! training) take the host kernels (see `common/kernel_checks`).

use crate::kernel_checks::assert_host_kernels_taken;

#[test]
fn cpu_backends_take_the_host_kernels_f32() {
    type B = burn::backend::NdArray<f32>;
    assert_host_kernels_taken::<B, burn::backend::Autodiff<B>>();
}
