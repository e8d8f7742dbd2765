//! Readers and writers of the real dataset formats (docs/formats.md), plus the small
//! `.npy` / file helpers they share.

pub mod io;
pub mod npy;
pub mod nuscenes_occupancy;
pub mod occ3d;
pub mod semantic_kitti;
pub mod voxels;
