//! The model's compute kernels behind the backend extension trait [`ModelBackend`] (in `backend.rs`,
//! done like occ-sparse's `SparseConvBackend`): portable burn ops by default, CPU fast paths (host
//! loops over burn-ndarray's buffers) for the operations whose generic burn graph is far slower on
//! the CPU. The fast paths compute what the portable path computes (tests compare the two); the
//! `NdArray` and `Autodiff<NdArray>` backends override the defaults with them, every other backend
//! (CUDA) runs the portable burn graph.
//!
//! - [`conv2d_host`]: image 2D convolutions with their inference BatchNorm folded in (im2col + GEMM),
//!   and the convolution as one autodiff op for CPU training.
//! - [`dca`]: the DCA sampling op's inputs ([`DcaSample`], [`ViewHits`]) and its portable form.
//! - `dca_host`: the DCA sampling step and its backward pass as host loops.
//! - `dca_cube` (features `cuda` / `wgpu`): the same step and its backward as `#[cube]` kernels for
//!   the cubecl backends, registered as burn-fusion custom ops.
//! - `rows_host`: linear layers (bias and ReLU fused), LayerNorm and softmax as row-wise host loops
//!   for inference.
//! - [`host_data`]: zero-copy access to the NdArray backend's tensors for the host kernels.
//!
//! [`host_kernel_calls`] counts, per thread, how often each host kernel ran (tests use it to check
//! that the CPU backends take the fast paths).

mod backend;
#[cfg(feature = "cube")]
pub mod conv2d_cube;
pub mod conv2d_host;
pub mod dca;
#[cfg(feature = "cube")]
pub mod dca_cube;
pub(crate) mod dca_host;
pub mod host_data;
pub(crate) mod rows_host;

pub use backend::{linear_bucketed, rows_bucketed, ModelBackend, LAYER_NORM_EPSILON};
pub use dca::{DcaSample, FeatureRows, ViewHits};

use std::cell::Cell;

/// How many times each host kernel ran on the current thread (see [`host_kernel_calls`]).
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct HostKernelCalls {
    /// Fused inference convolutions ([`conv2d_host::conv_bn_host`]).
    pub conv2d: u64,
    /// Training convolution ops ([`conv2d_host::conv_autodiff`]).
    pub conv2d_autodiff: u64,
    /// DCA sampling host loops (inference).
    pub dca: u64,
    /// DCA sampling autodiff ops (training).
    pub dca_autodiff: u64,
}

thread_local! {
    static CALLS: Cell<HostKernelCalls> = const {
        Cell::new(HostKernelCalls {
            conv2d: 0,
            conv2d_autodiff: 0,
            dca: 0,
            dca_autodiff: 0,
        })
    };
}

/// The host kernel calls made on this thread so far (a running count; compare two readings).
pub fn host_kernel_calls() -> HostKernelCalls {
    CALLS.with(Cell::get)
}

/// Adds one call to the counts.
pub(crate) fn count(f: impl FnOnce(&mut HostKernelCalls)) {
    CALLS.with(|c| {
        let mut v = c.get();
        f(&mut v);
        c.set(v);
    });
}
