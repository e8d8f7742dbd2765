//! occ-geometry: cameras, voxel grids, projections, augmentation transforms, and the
//! scene-completion-field (SCF) geometry of SparseOcc++ (paper Sec. 4.2, Algorithms 1 and 2).
//!
//! Conventions (docs/formats.md §1): voxel index `(x, y, z)`, flat arrays in C order with z fastest,
//! transforms named `b_from_a`, units in names.

pub mod camera;
pub mod grid;
pub mod mat;
pub mod scf;

pub use camera::{
    apply_aug3, aug_crop, aug_flip_horizontal, aug_identity, aug_resize, aug_rotate,
    img_aug3_from_mat4, mat4_from_img_aug3, project_voxel_centers, project_with, CameraView,
    ImageAug, PinholeCamera, VoxelProjection, MIN_DEPTH_M,
};
pub use grid::{flip_grid, VoxelGrid};
pub use mat::{
    mat3_det, mat3_identity, mat3_inverse, mat3_mul, mat4_from_quat_translation, mat4_identity,
    mat4_inverse, mat4_mul, quat_from_mat4, transform_point, Mat3, Mat4,
};
