//! occ-model integration tests on the f32 NdArray backend (PyTorch reference outputs, overfitting),
//! one binary (see `model_f64/main.rs` for why the dtypes are split).

#[path = "../common/kernel_checks/mod.rs"]
mod kernel_checks;
#[path = "../common/so_common/mod.rs"]
mod so_common;

mod conv_host;
mod host_kernels;
mod image_encoder;
mod pp_overfit;
mod pth_cases;
mod so_overfit;
