//! The f64 CPU backends take the host kernels (see `common/kernel_checks`), and so does a whole
//! SparseOccPP forward pass: its DCA blocks run the host loop on `NdArray<f64>` and the host
//! autodiff op on `Autodiff<NdArray<f64>>`.

use crate::kernel_checks::{assert_host_kernels_taken, since};
use crate::pp_common::*;
use occ_model::kernels::{host_kernel_calls, HostKernelCalls};
use occ_model::sparseocc_pp::{SparseOccPP, SparseOccPPConfig};

#[test]
fn cpu_backends_take_the_host_kernels_f64() {
    assert_host_kernels_taken::<NB, AD>();
}

fn sparseocc_pp_calls<B: occ_model::ModelBackend>() -> HostKernelCalls {
    let cfg = SparseOccPPConfig::new(6, 8, FEAT_C, FULL_DIMS)
        .with_num_feature_levels(2)
        .with_dca_heads(2)
        .with_dca_points(2)
        .with_s_max_planar(4)
        .with_s_max_vertical(2);
    let device = Default::default();
    let model: SparseOccPP<B> = cfg.try_init(&device).expect("valid config");
    let batch = batch::<B>(1, 3, &device);
    let feats = features::<B>(1, 4, &device);
    let before = host_kernel_calls();
    model.forward(&feats, &STRIDES, &batch).expect("forward");
    since(before)
}

#[test]
fn sparseocc_pp_runs_dca_through_the_host_kernels() {
    let inference = sparseocc_pp_calls::<NB>();
    assert!(inference.dca >= 3, "{inference:?}");
    assert_eq!(inference.dca_autodiff, 0, "{inference:?}");
    let training = sparseocc_pp_calls::<AD>();
    assert!(training.dca_autodiff >= 3, "{training:?}");
    assert_eq!(training.dca, 0, "{training:?}");
}
