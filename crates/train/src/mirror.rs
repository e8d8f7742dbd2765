//! Lateral mirror of a whole training sample (3D flip augmentation).
//!
//! MonoScene's SemanticKITTI training (`fliplr = 0.5` in `data/semantic_kitti/kitti_dataset.py`)
//! flips the image left-right together with every 3D target along the grid's y axis
//! (`np.flip(label, axis=1)`), so the network sees mirrored streets: buildings on the other side,
//! traffic on the other lane. It cannot learn "this class sits at this lateral position" from the
//! layouts it was trained on, only from the image. BEVDet's BEV augmentation (`flip_dy`) is the same
//! mirror on the BEV grid.
//!
//! Here the mirror is exact for any camera: with `M` the reflection of the grid frame across the
//! grid's centre plane `y = c` and `F` the horizontal flip of the network input (`u' = (W-1) - u`),
//! the mirrored sample's cameras are `img_from_lidar' = F · img_from_lidar · M` and
//! `cam_from_lidar' = cam_from_lidar · M`. A point `p'` of the mirrored scene then lands on the
//! flipped pixel of the original point `M p'` at the same depth, and the mirrored voxel `(x, Y-1-y, z)`
//! on the flipped pixel of voxel `(x, y, z)`. LiDAR points are mirrored with `M`.

use crate::dataset::Sample;
use crate::error::TrainError;
use occ_geometry::{aug_flip_horizontal, flip_grid, mat4_from_img_aug3, mat4_mul, Mat4, VoxelGrid};

/// The reflection of the grid frame across the grid's x-z centre plane `y = c` (metres):
/// `(x, y, z) -> (x, 2c - y, z)`, which maps voxel column `y` onto `Y - 1 - y`.
pub fn mirror_y_of_grid(grid: &VoxelGrid) -> Mat4 {
    let c = grid.origin_m[1] + grid.dims[1] as f64 * grid.voxel_size_m / 2.0;
    [
        [1.0, 0.0, 0.0, 0.0],
        [0.0, -1.0, 0.0, 2.0 * c],
        [0.0, 0.0, 1.0, 0.0],
        [0.0, 0.0, 0.0, 1.0],
    ]
}

/// Mirrors `sample` in place across the centre plane of `grid` (see the module documentation):
/// images flipped left-right, cameras re-folded, target reversed along y, LiDAR points mirrored.
/// Applying it twice gives the sample back.
pub fn mirror_sample_y(sample: &mut Sample, grid: &VoxelGrid) -> Result<(), TrainError> {
    let (w, h) = sample.size;
    let views = sample.cameras.len();
    if w == 0 || sample.chw.len() != views * 3 * w * h {
        return Err(TrainError::Data(format!(
            "frame {}/{}: mirror: {} image values for {views} views of {w}x{h}",
            sample.frame.sequence,
            sample.frame.frame,
            sample.chw.len()
        )));
    }
    let m = mirror_y_of_grid(grid);
    let f = mat4_from_img_aug3(&aug_flip_horizontal(w));
    for cam in &mut sample.cameras {
        cam.img_from_lidar = mat4_mul(&f, &mat4_mul(&cam.img_from_lidar, &m));
        cam.cam_from_lidar = mat4_mul(&cam.cam_from_lidar, &m);
    }
    for row in sample.chw.chunks_mut(w) {
        row.reverse();
    }
    sample.map_target("mirror", grid.dims, |t| {
        flip_grid(t, grid.dims, [false, true, false])
    })?;
    if let Some(points) = &mut sample.points {
        let two_c = m[1][3] as f32;
        for p in points.iter_mut() {
            p[1] = two_c - p[1];
        }
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::test_support::{centre, front_camera_sample as setup};
    use occ_geometry::project_with;

    #[test]
    fn mirrored_voxels_and_points_land_on_the_flipped_pixels() {
        let (orig, grid, _) = setup();
        let mut m = orig.clone();
        mirror_sample_y(&mut m, &grid).unwrap();
        let (w, h) = orig.size;
        let [_, ny, nz] = grid.dims;
        let (a, b) = (&orig.cameras[0], &m.cameras[0]);
        let mut seen = 0;
        for x in 0..grid.dims[0] {
            for y in 0..ny {
                for z in 0..nz {
                    let i = (x * ny + y) * nz + z;
                    let j = (x * ny + (ny - 1 - y)) * nz + z;
                    // the label moved to the mirrored column
                    assert_eq!(
                        m.target.as_ref().unwrap()[j],
                        orig.target.as_ref().unwrap()[i]
                    );
                    let p = project_with(&a.img_from_lidar, centre(&grid, [x, y, z]));
                    let q = project_with(&b.img_from_lidar, centre(&grid, [x, ny - 1 - y, z]));
                    match (p, q) {
                        (Some(p), Some(q)) => {
                            assert!((q[0] - ((w - 1) as f64 - p[0])).abs() < 1e-9, "{p:?} {q:?}");
                            assert!((q[1] - p[1]).abs() < 1e-9 && (q[2] - p[2]).abs() < 1e-9);
                            // same depth through cam_from_lidar
                            let da = occ_geometry::transform_point(
                                &a.cam_from_lidar,
                                centre(&grid, [x, y, z]),
                            )[2];
                            let db = occ_geometry::transform_point(
                                &b.cam_from_lidar,
                                centre(&grid, [x, ny - 1 - y, z]),
                            )[2];
                            assert!((da - db).abs() < 1e-9);
                            // the image value at an in-view integer pixel moved with it
                            let (u, v) = (p[0].round(), p[1].round());
                            if (0.0..w as f64).contains(&u) && (0.0..h as f64).contains(&v) {
                                let (u, v) = (u as usize, v as usize);
                                for c in 0..3 {
                                    assert_eq!(
                                        m.chw[(c * h + v) * w + (w - 1 - u)],
                                        orig.chw[(c * h + v) * w + u]
                                    );
                                }
                                seen += 1;
                            }
                        }
                        (None, None) => {}
                        other => panic!("visibility changed under the mirror: {other:?}"),
                    }
                }
            }
        }
        assert!(seen > 100, "only {seen} voxels in view");
        for (p, q) in orig.points.unwrap().iter().zip(m.points.as_ref().unwrap()) {
            let f = |p: &[f32; 3]| [p[0] as f64, p[1] as f64, p[2] as f64];
            let pa = project_with(&a.img_from_lidar, f(p)).unwrap();
            let pb = project_with(&b.img_from_lidar, f(q)).unwrap();
            assert!((pb[0] - ((w - 1) as f64 - pa[0])).abs() < 1e-5);
            assert!((pb[1] - pa[1]).abs() < 1e-5 && (pb[2] - pa[2]).abs() < 1e-5);
        }
    }

    #[test]
    fn mirroring_twice_is_the_identity() {
        let (orig, grid, _) = setup();
        let mut m = orig.clone();
        mirror_sample_y(&mut m, &grid).unwrap();
        assert_ne!(m.target, orig.target);
        mirror_sample_y(&mut m, &grid).unwrap();
        assert_eq!(m.chw, orig.chw);
        assert_eq!(m.target, orig.target);
        assert_eq!(m.points, orig.points);
        for (a, b) in m.cameras.iter().zip(&orig.cameras) {
            for r in 0..4 {
                for c in 0..4 {
                    assert!((a.img_from_lidar[r][c] - b.img_from_lidar[r][c]).abs() < 1e-9);
                    assert!((a.cam_from_lidar[r][c] - b.cam_from_lidar[r][c]).abs() < 1e-12);
                }
            }
        }
    }

    #[test]
    fn a_sample_whose_image_does_not_match_its_size_is_an_error() {
        let (mut s, grid, _) = setup();
        s.chw.pop();
        let e = mirror_sample_y(&mut s, &grid).unwrap_err().to_string();
        assert!(e.contains("00/000000") && e.contains("mirror"), "{e}");
    }
}
