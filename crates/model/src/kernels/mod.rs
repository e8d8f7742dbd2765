//! CPU fast paths: host loops over burn-ndarray's buffers for the operations whose generic burn graph
//! is far slower on the CPU (the image-side convolutions, the DCA sampling). They compute what the
//! portable path computes (tests compare the two) and are chosen at run time for the NdArray backends
//! only; every other backend runs the portable burn graph.
//!
//! - [`conv2d_host`]: image 2D convolutions with their inference BatchNorm folded in (im2col + GEMM).
//! - `dca_host`: the DCA sampling step and its backward pass as host loops.
//! - `host_data`: zero-copy access to the NdArray backend's tensors for the two above.

pub mod conv2d_host;
pub(crate) mod dca_host;
pub(crate) mod host_data;
