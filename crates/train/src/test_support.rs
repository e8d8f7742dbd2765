//! Shared fixtures of the unit tests of the sample transforms (`mirror`, `shift`).

use crate::dataset::{FrameRef, Sample};
use occ_geometry::{CameraView, Mat4, PinholeCamera, VoxelGrid};
use occ_model::CameraInput;

/// A KITTI-like front camera 0.3 m left of the grid's centre plane (so the mirror is not a
/// symmetry of the rig), looking along +x, on a 20x16x4 grid of 0.5 m.
pub(crate) fn front_camera_sample() -> (Sample, VoxelGrid, CameraView) {
    let grid = VoxelGrid {
        origin_m: [0.0, -4.0, -1.0],
        voxel_size_m: 0.5,
        dims: [20, 16, 4],
    };
    let (w, h) = (40usize, 12usize);
    let camera = PinholeCamera {
        fx: 20.0,
        fy: 20.0,
        cx: 17.3,
        cy: 5.6,
        width: w,
        height: h,
    };
    // cam (x right, y down, z forward) from grid (x forward, y left, z up), camera at y = 0.3.
    let cam_from_lidar: Mat4 = [
        [0.0, -1.0, 0.0, 0.3],
        [0.0, 0.0, -1.0, 0.2],
        [1.0, 0.0, 0.0, 0.0],
        [0.0, 0.0, 0.0, 1.0],
    ];
    let view = CameraView::new(camera, cam_from_lidar);
    let n = grid.dims.iter().product::<usize>();
    let sample = Sample {
        frame: FrameRef {
            sequence: "00".into(),
            frame: "000000".into(),
        },
        chw: (0..3 * w * h).map(|i| i as f32).collect(),
        size: (w, h),
        cameras: vec![CameraInput {
            img_from_lidar: view.img_from_lidar(),
            cam_from_lidar,
        }],
        target: Some((0..n).map(|i| (i % 251) as u8).collect()),
        points: Some(vec![[5.0, 1.25, -0.5], [7.5, -2.0, 0.25]]),
    };
    (sample, grid, view)
}

pub(crate) fn centre(grid: &VoxelGrid, [x, y, z]: [usize; 3]) -> [f64; 3] {
    let s = grid.voxel_size_m;
    [
        grid.origin_m[0] + (x as f64 + 0.5) * s,
        grid.origin_m[1] + (y as f64 + 0.5) * s,
        grid.origin_m[2] + (z as f64 + 0.5) * s,
    ]
}
