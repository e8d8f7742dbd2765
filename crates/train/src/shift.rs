//! Translation of a whole training sample in the ground plane (3D translation augmentation).
//!
//! BEVDet's BEV data augmentation (`bda_aug_conf`) and the occupancy networks built on it (FlashOcc,
//! FB-OCC) move the 3D space under a fixed image and fold the inverse motion into the camera
//! transform: the network sees the same picture with the scene at another place in its grid, so it
//! cannot learn "this class sits at this voxel" from the training layouts, only from the image and
//! the camera geometry. Here the motion is a whole number of voxels, so the labels move exactly
//! (no resampling): a sample shifted by `d = (dx, dy)` voxels has
//! - `label'[x + dx, y + dy, z] = label[x, y, z]`, and 255 (ignored) on the strip that enters the grid;
//! - `img_from_lidar' = img_from_lidar · T(−d·s)` and `cam_from_lidar' = cam_from_lidar · T(−d·s)`
//!   (`s` the voxel size in metres), so voxel `(x + dx, y + dy, z)` of the shifted grid projects onto
//!   the pixel of voxel `(x, y, z)` of the original at the same depth;
//! - LiDAR points `p' = p + d·s`.
//!
//! The image is not touched.

use crate::dataset::Sample;
use crate::error::TrainError;
use occ_geometry::{mat4_identity, mat4_mul, VoxelGrid};
use occ_labels::IGNORE;

/// `grid` (flat `[X][Y][Z]`) moved by `(dx, dy)` voxels; voxels that enter are `fill`. `None` when
/// `grid.len()` does not match `dims`.
pub fn shift_grid_xy(grid: &[u8], dims: [usize; 3], d: [i64; 2], fill: u8) -> Option<Vec<u8>> {
    let [nx, ny, nz] = dims;
    if grid.len() != nx * ny * nz {
        return None;
    }
    let mut out = vec![fill; grid.len()];
    for x in 0..nx as i64 {
        let sx = x - d[0];
        if sx < 0 || sx >= nx as i64 {
            continue;
        }
        for y in 0..ny as i64 {
            let sy = y - d[1];
            if sy < 0 || sy >= ny as i64 {
                continue;
            }
            let dst = (x as usize * ny + y as usize) * nz;
            let src = (sx as usize * ny + sy as usize) * nz;
            out[dst..dst + nz].copy_from_slice(&grid[src..src + nz]);
        }
    }
    Some(out)
}

/// Moves `sample` by `d = (dx, dy)` voxels of `grid` in place (see the module documentation): target
/// shifted (255 where it enters), cameras re-folded, LiDAR points moved; the image is unchanged.
/// Shifting by `d` and then by `−d` gives the sample back except on the strips that left the grid.
pub fn shift_sample_xy(
    sample: &mut Sample,
    grid: &VoxelGrid,
    d: [i64; 2],
) -> Result<(), TrainError> {
    let s = grid.voxel_size_m;
    let t_m = [d[0] as f64 * s, d[1] as f64 * s];
    // T(−d·s): a point of the shifted grid frame in the original one.
    let mut lidar_from_shifted = mat4_identity();
    lidar_from_shifted[0][3] = -t_m[0];
    lidar_from_shifted[1][3] = -t_m[1];
    for cam in &mut sample.cameras {
        cam.img_from_lidar = mat4_mul(&cam.img_from_lidar, &lidar_from_shifted);
        cam.cam_from_lidar = mat4_mul(&cam.cam_from_lidar, &lidar_from_shifted);
    }
    sample.map_target("shift", grid.dims, |t| {
        shift_grid_xy(t, grid.dims, d, IGNORE)
    })?;
    if let Some(points) = &mut sample.points {
        for p in points.iter_mut() {
            p[0] += t_m[0] as f32;
            p[1] += t_m[1] as f32;
        }
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::test_support::{self, front_camera_sample};
    use occ_geometry::project_with;

    fn setup() -> (Sample, VoxelGrid) {
        let (sample, grid, _) = front_camera_sample();
        (sample, grid)
    }

    fn centre(grid: &VoxelGrid, [x, y, z]: [i64; 3]) -> [f64; 3] {
        test_support::centre(grid, [x as usize, y as usize, z as usize])
    }

    #[test]
    fn shifted_voxels_keep_their_label_pixel_and_depth() {
        let (orig, grid) = setup();
        let [nx, ny, nz] = grid.dims;
        for d in [[3i64, -2i64], [-4, 5], [0, 1]] {
            let mut m = orig.clone();
            shift_sample_xy(&mut m, &grid, d).unwrap();
            assert_eq!(m.chw, orig.chw);
            let (a, b) = (&orig.cameras[0], &m.cameras[0]);
            let (t0, t1) = (orig.target.as_ref().unwrap(), m.target.as_ref().unwrap());
            let mut entered = 0;
            for x in 0..nx as i64 {
                for y in 0..ny as i64 {
                    for z in 0..nz as i64 {
                        let j = ((x as usize * ny) + y as usize) * nz + z as usize;
                        let (sx, sy) = (x - d[0], y - d[1]);
                        if !(0..nx as i64).contains(&sx) || !(0..ny as i64).contains(&sy) {
                            assert_eq!(t1[j], IGNORE);
                            entered += 1;
                            continue;
                        }
                        let i = ((sx as usize * ny) + sy as usize) * nz + z as usize;
                        assert_eq!(t1[j], t0[i]);
                        let p = project_with(&a.img_from_lidar, centre(&grid, [sx, sy, z]));
                        let q = project_with(&b.img_from_lidar, centre(&grid, [x, y, z]));
                        match (p, q) {
                            (Some(p), Some(q)) => {
                                for k in 0..3 {
                                    assert!((p[k] - q[k]).abs() < 1e-9, "{p:?} {q:?}");
                                }
                            }
                            (None, None) => {}
                            other => panic!("visibility changed under the shift: {other:?}"),
                        }
                        let da = occ_geometry::transform_point(
                            &a.cam_from_lidar,
                            centre(&grid, [sx, sy, z]),
                        );
                        let db = occ_geometry::transform_point(
                            &b.cam_from_lidar,
                            centre(&grid, [x, y, z]),
                        );
                        for k in 0..3 {
                            assert!((da[k] - db[k]).abs() < 1e-9);
                        }
                    }
                }
            }
            let strip =
                nx * ny - (nx - d[0].unsigned_abs() as usize) * (ny - d[1].unsigned_abs() as usize);
            assert_eq!(entered, strip * nz);
            for (p, q) in orig
                .points
                .as_ref()
                .unwrap()
                .iter()
                .zip(m.points.as_ref().unwrap())
            {
                let f = |p: &[f32; 3]| [p[0] as f64, p[1] as f64, p[2] as f64];
                let pa = project_with(&a.img_from_lidar, f(p)).unwrap();
                let pb = project_with(&b.img_from_lidar, f(q)).unwrap();
                for k in 0..3 {
                    assert!((pa[k] - pb[k]).abs() < 1e-4, "{pa:?} {pb:?}");
                }
                assert!((q[0] - p[0] - d[0] as f32 * 0.5).abs() < 1e-6);
            }
        }
    }

    #[test]
    fn shifting_back_restores_the_sample_inside_the_overlap() {
        let (orig, grid) = setup();
        let mut m = orig.clone();
        shift_sample_xy(&mut m, &grid, [2, -3]).unwrap();
        shift_sample_xy(&mut m, &grid, [-2, 3]).unwrap();
        let [nx, ny, nz] = grid.dims;
        let (t0, t1) = (orig.target.as_ref().unwrap(), m.target.as_ref().unwrap());
        for x in 0..nx {
            for y in 0..ny {
                for z in 0..nz {
                    let i = (x * ny + y) * nz + z;
                    let inside = x < nx - 2 && y >= 3;
                    assert_eq!(t1[i], if inside { t0[i] } else { IGNORE }, "{x} {y} {z}");
                }
            }
        }
        for (a, b) in m.cameras.iter().zip(&orig.cameras) {
            for r in 0..4 {
                for c in 0..4 {
                    assert!((a.img_from_lidar[r][c] - b.img_from_lidar[r][c]).abs() < 1e-9);
                }
            }
        }
    }

    #[test]
    fn a_target_that_does_not_match_the_grid_is_an_error() {
        let (mut s, grid) = setup();
        s.target.as_mut().unwrap().pop();
        let e = shift_sample_xy(&mut s, &grid, [1, 1])
            .unwrap_err()
            .to_string();
        assert!(e.contains("00/000000") && e.contains("shift"), "{e}");
    }
}
