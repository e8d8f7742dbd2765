//! Shared fixtures of the SparseOcc / dense-baseline tests: a tiny hand-built scene seen by one or
//! two pinhole cameras.
#![allow(dead_code)]

use burn::prelude::*;
use burn::tensor::TensorData;
use occ_geometry::{mat4_mul, Mat4, VoxelGrid};
use occ_model::{Batch, CameraInput};
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;

pub fn rng(seed: u64) -> ChaCha8Rng {
    ChaCha8Rng::seed_from_u64(seed)
}

/// Input image size (H, W).
pub const IMG_H: usize = 32;
pub const IMG_W: usize = 64;

/// The tiny grid: 32x32x8 voxels of 0.2 m, x in [0, 6.4], y in [-3.2, 3.2], z in [-0.8, 0.8].
pub fn tiny_grid() -> VoxelGrid {
    VoxelGrid {
        origin_m: [0.0, -3.2, -0.8],
        voxel_size_m: 0.2,
        dims: [32, 32, 8],
    }
}

/// A camera at `centre_m` (LiDAR frame) looking along +x rotated by `yaw_rad` about z; fx = fy = 32,
/// principal point at the image centre. Camera axes: x right, y down, z forward.
pub fn camera(centre_m: [f64; 3], yaw_rad: f64) -> CameraInput {
    let (s, c) = yaw_rad.sin_cos();
    // Rows: camera x = -left, camera y = -up, camera z = forward (in LiDAR coordinates).
    let fwd = [c, s, 0.0];
    let left = [-s, c, 0.0];
    let up = [0.0, 0.0, 1.0];
    let rows = [left.map(|v| -v), up.map(|v| -v), fwd];
    let mut cam_from_lidar: Mat4 = [[0.0; 4]; 4];
    for r in 0..3 {
        for k in 0..3 {
            cam_from_lidar[r][k] = rows[r][k];
        }
        cam_from_lidar[r][3] = -(0..3).map(|k| rows[r][k] * centre_m[k]).sum::<f64>();
    }
    cam_from_lidar[3][3] = 1.0;
    let img_from_cam: Mat4 = [
        [32.0, 0.0, (IMG_W as f64 - 1.0) / 2.0, 0.0],
        [0.0, 32.0, (IMG_H as f64 - 1.0) / 2.0, 0.0],
        [0.0, 0.0, 1.0, 0.0],
        [0.0, 0.0, 0.0, 1.0],
    ];
    CameraInput {
        img_from_lidar: mat4_mul(&img_from_cam, &cam_from_lidar),
        cam_from_lidar,
    }
}

/// The hand-built scene labels on [`tiny_grid`] (flat C order): ground (class 1) on the bottom layer,
/// a "car" box (class 2) and a "building" box (class 3), everything else empty; a few ignore voxels.
pub fn scene_labels() -> Vec<u8> {
    let g = tiny_grid();
    let [dx, dy, dz] = g.dims;
    let mut l = vec![0u8; dx * dy * dz];
    for x in 0..dx {
        for y in 0..dy {
            for z in 0..dz {
                let v = if z == 0 {
                    1
                } else if (10..20).contains(&x) && (8..16).contains(&y) && z < 5 {
                    2
                } else if (20..30).contains(&x) && (18..28).contains(&y) {
                    3
                } else {
                    0
                };
                l[(x * dy + y) * dz + z] = v;
            }
        }
    }
    // A few ignore voxels.
    l[(31 * dy + 31) * dz + 7] = 255;
    l[(31 * dy) * dz + 7] = 255;
    l
}

/// LiDAR points: the centres of the occupied voxels.
pub fn scene_points(labels: &[u8]) -> Vec<[f32; 3]> {
    let g = tiny_grid();
    (0..labels.len())
        .filter(|&i| labels[i] != 0 && labels[i] != 255)
        .map(|i| {
            let c = g.voxel_center_m(g.ijk_of(i));
            [c[0] as f32, c[1] as f32, c[2] as f32]
        })
        .collect()
}

/// A batch of `b` items with the given cameras per item, zero images, targets and points.
pub fn batch<B: Backend>(cams: Vec<Vec<CameraInput>>, with_targets: bool) -> Batch<B> {
    let b = cams.len();
    let v = cams[0].len();
    let labels = scene_labels();
    let pts = scene_points(&labels);
    Batch {
        images: Tensor::zeros([b, v, 3, IMG_H, IMG_W], &Default::default()),
        cameras: cams,
        grid: tiny_grid(),
        target: with_targets.then(|| vec![labels.clone(); b]),
        points: with_targets.then(|| vec![pts.clone(); b]),
    }
}

/// A fixed random tensor with entries in [-1, 1).
pub fn random_tensor<B: Backend, const D: usize>(
    r: &mut ChaCha8Rng,
    shape: [usize; D],
) -> Tensor<B, D> {
    let n: usize = shape.iter().product();
    let v: Vec<f32> = (0..n).map(|_| r.random_range(-1.0f32..1.0)).collect();
    Tensor::from_data(TensorData::new(v, shape), &Default::default())
}

pub fn to_vec_f64<B: Backend, const D: usize>(t: Tensor<B, D>) -> Vec<f64> {
    t.into_data().convert::<f64>().to_vec::<f64>().unwrap()
}

static SEED_LOCK: std::sync::Mutex<()> = std::sync::Mutex::new(());

/// Seeds burn's (process-global) backend RNG and holds a lock so that tests drawing parameter
/// initialisations (lazily, at first use) do not interleave. Keep the guard alive for the whole test.
pub fn seeded<B: Backend>(seed: u64) -> std::sync::MutexGuard<'static, ()> {
    let guard = SEED_LOCK.lock().unwrap_or_else(|e| e.into_inner());
    B::seed(&Default::default(), seed);
    guard
}

/// The input of the overfitting tests: the scene seen by one camera at (-0.5, 0, 0) m with yaw 0
/// ([`camera`]), its labels as targets, and random image features
/// `[1, 8, IMG_H / stride, IMG_W / stride]` drawn with seed `feature_seed`.
pub fn one_camera_frame<B: Backend>(feature_seed: u64, stride: usize) -> (Batch<B>, Tensor<B, 4>) {
    let mut r = rng(feature_seed);
    let batch = batch::<B>(vec![vec![camera([-0.5, 0.0, 0.0], 0.0)]], true);
    let feats = random_tensor::<B, 4>(&mut r, [1, 8, IMG_H / stride, IMG_W / stride]);
    (batch, feats)
}
