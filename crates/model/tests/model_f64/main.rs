//! occ-model integration tests on the f64 NdArray backend (gradient checks, exact references), one
//! binary. burn 0.21 fixes the float dtype of a device type process-wide at the first tensor
//! creation, so f64 and f32 tests live in separate binaries (`model_f32`).

#[path = "../common/kernel_checks/mod.rs"]
mod kernel_checks;
#[path = "../common/pp_common/mod.rs"]
mod pp_common;
#[path = "../common/so_common/mod.rs"]
mod so_common;

mod conv_train;
mod host_kernels;
mod pp_dca;
mod pp_model;
mod pp_targets;
mod pp_unet;
mod so_units;
