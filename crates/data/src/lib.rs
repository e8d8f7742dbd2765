//! occ-data: dataset formats, label remaps and downsampling, synthetic scenes.
//!
//! - [`formats`]: SemanticKITTI, nuScenes-Occupancy, Occ3D readers and writers (docs/formats.md).
//! - [`labels`]: learning maps and the MonoScene label downsampling rule.
//! - [`image`]: PNG I/O and the camera-image augmentation pipeline.
//! - [`prepare`]: dataset layout check and label preprocessing (`sparseocc prepare`).

pub mod error;
pub mod formats;
pub mod image;
pub mod labels;
pub mod prepare;
pub mod synthetic;

pub use error::DataError;
