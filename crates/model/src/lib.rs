//! # occ-model
//!
//! SparseOcc (paper Sec. 3), SparseOcc++ (paper Sec. 4) and the dense baseline, in burn. One file per
//! stage, each `XConfig::init(&device) -> X` with a documented `forward`.
//!
//! Shared vocabulary: [`batch::Batch`] (images, cameras, targets) goes in, [`output::ModelOutput`]
//! (sparse voxel logits, losses, per-stage statistics) comes out.

pub mod batch;
pub mod error;
pub mod network;
pub mod output;

pub use batch::{Batch, CameraInput};
pub use error::ModelError;
pub use network::OccNetwork;
pub use output::ModelOutput;
