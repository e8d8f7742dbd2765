//! Options of SparseOcc++ that are NOT in the paper, kept apart from its components. Every one is off
//! in the paper configs (`configs/`) and switched on by its own field of
//! [`crate::sparseocc_pp::SparseOccPPConfig`]; BENCHMARKS.md records what each was measured to give.
//!
//! | module | what it adds | kind |
//! |---|---|---|
//! | [`depth_gate`] | a predicted depth map gates every DCA sample by how well its voxel matches the surface its pixel shows | option |
//! | [`sem2d`] | an auxiliary per-pixel semantic head on the image features, supervised by projected labels | option |
//! | [`subvoxel`] | class logits for the 8 full-resolution children of every 1/2-resolution output voxel | option |
//! | [`depth_oracle`] | the true depth at every DCA sample (reads the LiDAR scan) | DIAGNOSTIC, not camera-only |
//! | [`scan_oracle`] | the scan's hit / free shares of every anchor and voxel (reads the LiDAR scan) | DIAGNOSTIC, not camera-only |

pub mod depth_gate;
pub mod depth_oracle;
pub mod scan_oracle;
pub mod sem2d;
pub mod subvoxel;
