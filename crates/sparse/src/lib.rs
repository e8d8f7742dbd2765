//! # occ-sparse
//!
//! Sparse 3D voxel convolution for [burn](https://burn.dev): the sparse tensors, kernel maps and layers that
//! sparse occupancy networks are built from (SubMConv3d, SparseConv3d, SparseConvTranspose3d,
//! SparseInverseConv3d, sparse max pooling, unions, pruning, top-k), with spconv's conventions
//! (docs/reference_models.md §3): coordinates `(batch, x, y, z)`, weights `[Cout, kx, ky, kz, Cin]`, cross-correlation.
//!
//! Structure follows spconv/torchsparse: integer work (coordinate hashing, kernel maps) on the host in
//! [`coords`] and [`kernel_map`], feature compute in [`backend`] (portable burn ops, a fast blocked-GEMM
//! host path for `NdArray`, explicit backward under `Autodiff`). This crate knows nothing about occupancy.

pub mod arrays;
pub mod backend;
pub mod conv;
pub mod coords;
#[cfg(feature = "cube")]
pub mod cube;
#[cfg(feature = "cuda-source")]
pub mod cuda_source;
pub mod error;
pub mod flops;
mod fused;
pub mod host;
pub mod kernel_map;
pub mod norm;
pub mod ops;
pub mod pool;
pub mod rows;
pub mod tensor;

pub use backend::{RowBucket, SparseConvBackend};
pub use conv::{ConvKind, SparseConv3d, SparseConv3dConfig};
pub use coords::{full_grid_coords, Coord, CoordSet};
pub use error::{Result, SparseError};
pub use kernel_map::{ConvGeometry, KernelMap, KernelMapKey, MapKind, MapRule, MapSource, Sites};
pub use pool::{SparseMaxPool3d, SparseMaxPool3dConfig};
pub use rows::{gather_rows, pad_rows, scatter_add_rows, sum_rows, RowPlan};
pub use tensor::SparseTensor;
