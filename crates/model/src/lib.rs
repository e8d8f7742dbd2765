//! # occ-model
//!
//! SparseOcc (paper Sec. 3), SparseOcc++ (paper Sec. 4) and the dense baseline, in burn. One file per
//! stage, each `XConfig::init(&device) -> X` with a documented `forward`.
//!
//! Shared vocabulary: [`batch::Batch`] (images, cameras, targets) goes in, [`output::ModelOutput`]
//! (sparse voxel logits, losses, per-stage statistics) comes out.

pub mod anchors;
pub mod backbone;
pub mod batch;
pub mod conv2d_host;
pub mod dca;
mod dca_host;
pub mod dense_baseline;
pub mod depth_gate;
pub mod depth_oracle;
pub mod error;
pub mod fpn;
mod host_data;
pub mod hungarian;
pub mod loss;
pub mod lss;
pub mod mask_head;
pub mod network;
pub mod occnet;
pub mod output;
pub mod profile;
pub mod propagation;
pub mod propagator;
pub mod pyramid;
pub mod sample;
pub mod scan_oracle;
pub mod scf_head;
pub mod sem2d;
pub mod sparseocc;
pub mod sparseocc_pp;
pub mod subvoxel;
pub mod unet;
pub mod weights;

pub use batch::{Batch, CameraInput};
pub use error::ModelError;
pub use network::OccNetwork;
pub use occnet::{load_checked, ModelKind, OccNet, OccNetConfig};
pub use output::ModelOutput;
