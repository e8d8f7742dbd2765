//! Pinhole cameras, the 2D image-augmentation affine, and projection of points / voxel centres.
//!
//! Projection chain (docs/formats.md §2.7, SparseOcc `ViewTransformerLSSBEVDepth`):
//! `img_from_lidar = img_aug · img_from_cam · cam_from_lidar`. These are 4x4 matrices acting on
//! `[x, y, z, 1]`; the result `q = img_from_lidar · p` holds `(Z·u, Z·v, Z)` with `Z` the depth
//! along the optical axis, so `u = q0/q2`, `v = q1/q2`. `img_aug` is a 2D affine on pixel
//! coordinates embedded so that it acts on `(Z·u, Z·v, Z)` (see [`mat4_from_img_aug3`]).
//! Pixel coordinates put the centre of pixel column `i` at `u = i` (the KITTI/OpenCV convention
//! of `u = fx·X/Z + cx`).

use crate::grid::VoxelGrid;
use crate::mat::{mat3_identity, mat3_mul, mat4_identity, mat4_mul, transform_point, Mat3, Mat4};
use serde::{Deserialize, Serialize};

/// Smallest depth (metres along the optical axis) accepted as "in front of the camera".
pub const MIN_DEPTH_M: f64 = 1e-6;

/// Intrinsics of an undistorted pinhole camera and the size of its image.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct PinholeCamera {
    pub fx: f64,
    pub fy: f64,
    pub cx: f64,
    pub cy: f64,
    /// Image width in pixels. Inside a [`CameraView`] this is the width of the image that
    /// `img_from_lidar` maps into, i.e. of the augmented image when `img_aug` is not identity.
    pub width: usize,
    /// Image height in pixels (see `width`).
    pub height: usize,
}

impl PinholeCamera {
    /// `K` as a 3x3 matrix.
    pub fn k(&self) -> Mat3 {
        [
            [self.fx, 0.0, self.cx],
            [0.0, self.fy, self.cy],
            [0.0, 0.0, 1.0],
        ]
    }

    /// `img_from_cam`: `[[fx,0,cx,0],[0,fy,cy,0],[0,0,1,0],[0,0,0,1]]`, mapping a camera-frame
    /// point `(X, Y, Z)` to `(fx·X + cx·Z, fy·Y + cy·Z, Z)`.
    pub fn img_from_cam(&self) -> Mat4 {
        [
            [self.fx, 0.0, self.cx, 0.0],
            [0.0, self.fy, self.cy, 0.0],
            [0.0, 0.0, 1.0, 0.0],
            [0.0, 0.0, 0.0, 1.0],
        ]
    }
}

/// Embed a 2D pixel affine `[[a, b, tx], [c, d, ty], [0, 0, 1]]` (acting on `(u, v, 1)`) as the
/// 4x4 `[[a, b, tx, 0], [c, d, ty, 0], [0, 0, 1, 0], [0, 0, 0, 1]]` acting on `(Z·u, Z·v, Z, 1)`.
pub fn mat4_from_img_aug3(a: &Mat3) -> Mat4 {
    [
        [a[0][0], a[0][1], a[0][2], 0.0],
        [a[1][0], a[1][1], a[1][2], 0.0],
        [0.0, 0.0, 1.0, 0.0],
        [0.0, 0.0, 0.0, 1.0],
    ]
}

/// Inverse of [`mat4_from_img_aug3`]: extract the 3x3 pixel affine.
pub fn img_aug3_from_mat4(m: &Mat4) -> Mat3 {
    [
        [m[0][0], m[0][1], m[0][2]],
        [m[1][0], m[1][1], m[1][2]],
        [0.0, 0.0, 1.0],
    ]
}

/// One camera as seen from the LiDAR (or ego) frame, with an optional image augmentation.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct CameraView {
    /// Intrinsics of the raw image; `width`/`height` are those of the image the view maps into
    /// (after augmentation).
    pub camera: PinholeCamera,
    /// Rigid transform LiDAR -> camera (OpenCV axes: x right, y down, z forward).
    pub cam_from_lidar: Mat4,
    /// Post-augmentation pixel affine embedded by [`mat4_from_img_aug3`]; identity if none.
    pub img_aug: Mat4,
}

impl CameraView {
    /// A view without augmentation.
    pub fn new(camera: PinholeCamera, cam_from_lidar: Mat4) -> Self {
        CameraView {
            camera,
            cam_from_lidar,
            img_aug: mat4_identity(),
        }
    }

    /// This view after an image augmentation: `img_aug` becomes `aug · img_aug` and the
    /// image size becomes the augmented size.
    pub fn augmented(&self, aug: &ImageAug) -> Self {
        let mut v = *self;
        v.img_aug = mat4_mul(&aug.matrix4(), &self.img_aug);
        v.camera.width = aug.out_width;
        v.camera.height = aug.out_height;
        v
    }

    /// `img_aug · img_from_cam · cam_from_lidar`.
    pub fn img_from_lidar(&self) -> Mat4 {
        mat4_mul(
            &self.img_aug,
            &mat4_mul(&self.camera.img_from_cam(), &self.cam_from_lidar),
        )
    }

    /// Project a LiDAR-frame point to `(u, v, depth_m)` in the (augmented) image; `None` if the
    /// depth is not above [`MIN_DEPTH_M`] or not finite.
    pub fn project_point(&self, p_lidar_m: [f64; 3]) -> Option<[f64; 3]> {
        project_with(&self.img_from_lidar(), p_lidar_m)
    }

    /// `0 <= u < width`, `0 <= v < height` of the (augmented) image and `depth > 0`.
    pub fn in_view(&self, uvd: [f64; 3]) -> bool {
        uvd[2] > 0.0
            && uvd[0] >= 0.0
            && uvd[1] >= 0.0
            && uvd[0] < self.camera.width as f64
            && uvd[1] < self.camera.height as f64
    }
}

/// Project with a precomputed `img_from_lidar`: `(q0/q2, q1/q2, q2)`, `None` if `q2 <= MIN_DEPTH_M`.
pub fn project_with(img_from_lidar: &Mat4, p: [f64; 3]) -> Option<[f64; 3]> {
    let q = transform_point(img_from_lidar, p);
    if q[2].is_nan() || q[2] <= MIN_DEPTH_M || !q[0].is_finite() || !q[1].is_finite() {
        return None;
    }
    Some([q[0] / q[2], q[1] / q[2], q[2]])
}

/// Result of projecting every voxel centre of a grid into one view (flat C order).
#[derive(Clone, Debug, PartialEq)]
pub struct VoxelProjection {
    /// `(u, v, depth_m)` per voxel; `u`, `v` are NaN when the centre is behind the camera.
    pub uvd: Vec<[f32; 3]>,
    /// [`CameraView::in_view`] of each projected centre.
    pub in_view: Vec<bool>,
}

/// Project all voxel centres of `grid` into `view` (the voxel-to-pixel map used by MonoScene's
/// FLoSP and by SparseOcc++ DCA reference points).
pub fn project_voxel_centers(grid: &VoxelGrid, view: &CameraView) -> VoxelProjection {
    let m = view.img_from_lidar();
    let n = grid.num_voxels();
    let mut uvd = Vec::with_capacity(n);
    let mut in_view = Vec::with_capacity(n);
    for lin in 0..n {
        let c = grid.voxel_center_m(grid.ijk_of(lin));
        match project_with(&m, c) {
            Some(p) => {
                in_view.push(view.in_view(p));
                uvd.push([p[0] as f32, p[1] as f32, p[2] as f32]);
            }
            None => {
                let d = transform_point(&m, c)[2];
                in_view.push(false);
                uvd.push([f32::NAN, f32::NAN, d as f32]);
            }
        }
    }
    VoxelProjection { uvd, in_view }
}

/// Image-augmentation parameters of the BEVDet/OccFormer/SparseOcc pipeline (docs/formats.md §2.8,
/// `loading_kitti_imgs.py` `img_transform`), applied in this order to the raw image:
/// resize by `resize`, crop the window starting at `(crop_x0, crop_y0)` of size
/// `out_width x out_height` (pixels outside the resized image are zero), optional horizontal
/// flip, then rotation by `rotate_deg` about the centre of the output image (positive =
/// counter-clockwise on screen, as PIL's `Image.rotate`).
///
/// With pixel centres at integer coordinates (see the module doc) the per-step pixel maps are
/// `u' = r·u`, `u' = u - x0`, `u' = (W-1) - u`, and rotation about `((W-1)/2, (H-1)/2)`.
/// BEVDet writes the flip as `W - u` and rotates about `(W/2, H/2)` with the same matrices;
/// those differ from these by at most one pixel. Here the image resampling in
/// `occ_data::image` inverts exactly this matrix, so image and matrix agree to the pixel.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct ImageAug {
    /// Scale factor applied to the raw image.
    pub resize: f64,
    /// Left edge of the crop window in the resized image (may be negative = padding).
    pub crop_x0: f64,
    /// Top edge of the crop window in the resized image.
    pub crop_y0: f64,
    /// Width of the output image.
    pub out_width: usize,
    /// Height of the output image.
    pub out_height: usize,
    /// Horizontal flip.
    pub flip: bool,
    /// Rotation in degrees (counter-clockwise on screen).
    pub rotate_deg: f64,
}

impl ImageAug {
    /// No augmentation for an image of the given size.
    pub fn identity(width: usize, height: usize) -> Self {
        ImageAug {
            resize: 1.0,
            crop_x0: 0.0,
            crop_y0: 0.0,
            out_width: width,
            out_height: height,
            flip: false,
            rotate_deg: 0.0,
        }
    }

    /// SparseOcc/OccFormer KITTI test-time transform (docs/formats.md §2.8): `r = out_w / W`,
    /// resized size `(int(W·r), int(H·r))`, bottom crop `(0, newH - out_h, out_w, newH)`,
    /// no flip, no rotation.
    pub fn kitti_test(
        src_width: usize,
        src_height: usize,
        out_width: usize,
        out_height: usize,
    ) -> Self {
        let r = out_width as f64 / src_width.max(1) as f64;
        let new_h = (src_height as f64 * r) as i64; // python int(): truncation
        let crop_y0 = (new_h - out_height as i64).max(0) as f64;
        ImageAug {
            resize: r,
            crop_x0: 0.0,
            crop_y0,
            out_width,
            out_height,
            flip: false,
            rotate_deg: 0.0,
        }
    }

    /// Resized image size `(int(W·r), int(H·r))`.
    pub fn resized_dims(&self, src_width: usize, src_height: usize) -> (usize, usize) {
        (
            (src_width as f64 * self.resize) as usize,
            (src_height as f64 * self.resize) as usize,
        )
    }

    /// The composed 3x3 pixel affine `rotate · flip · crop · resize` (raw pixel -> output pixel).
    pub fn matrix3(&self) -> Mat3 {
        let mut m = aug_resize(self.resize);
        m = mat3_mul(&aug_crop(self.crop_x0, self.crop_y0), &m);
        if self.flip {
            m = mat3_mul(&aug_flip_horizontal(self.out_width), &m);
        }
        if self.rotate_deg != 0.0 {
            m = mat3_mul(
                &aug_rotate(self.rotate_deg, self.out_width, self.out_height),
                &m,
            );
        }
        m
    }

    /// [`ImageAug::matrix3`] embedded as a 4x4 `img_aug` (see [`mat4_from_img_aug3`]).
    pub fn matrix4(&self) -> Mat4 {
        mat4_from_img_aug3(&self.matrix3())
    }
}

/// Pixel affine of a resize by `r`: `u' = r·u`, `v' = r·v`.
pub fn aug_resize(r: f64) -> Mat3 {
    [[r, 0.0, 0.0], [0.0, r, 0.0], [0.0, 0.0, 1.0]]
}

/// Pixel affine of a crop whose top-left corner is `(x0, y0)`: `u' = u - x0`, `v' = v - y0`.
pub fn aug_crop(x0: f64, y0: f64) -> Mat3 {
    [[1.0, 0.0, -x0], [0.0, 1.0, -y0], [0.0, 0.0, 1.0]]
}

/// Pixel affine of a horizontal flip of an image `width` pixels wide: `u' = (width - 1) - u`.
pub fn aug_flip_horizontal(width: usize) -> Mat3 {
    [
        [-1.0, 0.0, width as f64 - 1.0],
        [0.0, 1.0, 0.0],
        [0.0, 0.0, 1.0],
    ]
}

/// Pixel affine of a rotation by `deg` (counter-clockwise on screen, y pointing down) about the
/// image centre `((width-1)/2, (height-1)/2)`: `p' = A (p - c) + c` with
/// `A = [[cos, sin], [-sin, cos]]` (BEVDet `get_rot`).
pub fn aug_rotate(deg: f64, width: usize, height: usize) -> Mat3 {
    let (s, c) = deg.to_radians().sin_cos();
    let cx = (width as f64 - 1.0) / 2.0;
    let cy = (height as f64 - 1.0) / 2.0;
    let a = [[c, s], [-s, c]];
    let tx = cx - (a[0][0] * cx + a[0][1] * cy);
    let ty = cy - (a[1][0] * cx + a[1][1] * cy);
    [
        [a[0][0], a[0][1], tx],
        [a[1][0], a[1][1], ty],
        [0.0, 0.0, 1.0],
    ]
}

/// Apply a 3x3 pixel affine to `(u, v)`.
pub fn apply_aug3(m: &Mat3, uv: [f64; 2]) -> [f64; 2] {
    [
        m[0][0] * uv[0] + m[0][1] * uv[1] + m[0][2],
        m[1][0] * uv[0] + m[1][1] * uv[1] + m[1][2],
    ]
}

/// Identity pixel affine.
pub fn aug_identity() -> Mat3 {
    mat3_identity()
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::mat::{mat3_inverse, mat4_from_quat_translation};
    use rand::{Rng, SeedableRng};
    use rand_chacha::ChaCha8Rng;

    fn kitti_like_view() -> CameraView {
        let camera = PinholeCamera {
            fx: 718.856,
            fy: 718.856,
            cx: 607.1928,
            cy: 185.2157,
            width: 1241,
            height: 376,
        };
        // lidar x forward, y left, z up -> camera x right, y down, z forward
        let cam_from_lidar = [
            [0.0, -1.0, 0.0, 0.0],
            [0.0, 0.0, -1.0, -0.08],
            [1.0, 0.0, 0.0, -0.27],
            [0.0, 0.0, 0.0, 1.0],
        ];
        CameraView::new(camera, cam_from_lidar)
    }

    #[test]
    fn projection_matches_pinhole_formula() {
        let v = kitti_like_view();
        let mut rng = ChaCha8Rng::seed_from_u64(5);
        for _ in 0..1000 {
            let p = [
                rng.random_range(-10.0..50.0),
                rng.random_range(-20.0..20.0),
                rng.random_range(-3.0..3.0),
            ];
            let c = transform_point(&v.cam_from_lidar, p);
            let got = v.project_point(p);
            if c[2] <= MIN_DEPTH_M {
                assert!(got.is_none());
                continue;
            }
            let g = got.unwrap();
            let u = v.camera.fx * c[0] / c[2] + v.camera.cx;
            let vv = v.camera.fy * c[1] / c[2] + v.camera.cy;
            assert!(
                (g[0] - u).abs() < 1e-9 && (g[1] - vv).abs() < 1e-9 && (g[2] - c[2]).abs() < 1e-12
            );
            let inside = u >= 0.0 && vv >= 0.0 && u < 1241.0 && vv < 376.0;
            assert_eq!(v.in_view(g), inside);
        }
        // a point straight ahead lands at the principal point
        let g = v.project_point([10.27, 0.0, -0.08]).unwrap();
        assert!((g[0] - 607.1928).abs() < 1e-9 && (g[1] - 185.2157).abs() < 1e-9);
    }

    #[test]
    fn augmentation_matrix_equals_stepwise_pixel_maps() {
        let mut rng = ChaCha8Rng::seed_from_u64(6);
        for _ in 0..200 {
            let aug = ImageAug {
                resize: rng.random_range(0.9..1.2),
                crop_x0: rng.random_range(0.0..60.0f64).floor(),
                crop_y0: rng.random_range(0.0..10.0f64).floor(),
                out_width: 1280,
                out_height: 384,
                flip: rng.random_bool(0.5),
                rotate_deg: rng.random_range(-5.4..5.4),
            };
            let m = aug.matrix3();
            let uv = [rng.random_range(0.0..1241.0), rng.random_range(0.0..376.0)];
            // step by step
            let mut p = [uv[0] * aug.resize, uv[1] * aug.resize];
            p = [p[0] - aug.crop_x0, p[1] - aug.crop_y0];
            if aug.flip {
                p[0] = 1279.0 - p[0];
            }
            let (s, c) = aug.rotate_deg.to_radians().sin_cos();
            let (cx, cy) = (639.5, 191.5);
            let (dx, dy) = (p[0] - cx, p[1] - cy);
            p = [c * dx + s * dy + cx, -s * dx + c * dy + cy];
            let q = apply_aug3(&m, uv);
            assert!((q[0] - p[0]).abs() < 1e-9 && (q[1] - p[1]).abs() < 1e-9);
            // the 4x4 embedding gives the same pixel through the projection chain
            let mut view = kitti_like_view();
            view = view.augmented(&aug);
            let base = kitti_like_view();
            let pt = [
                20.0,
                rng.random_range(-5.0..5.0),
                rng.random_range(-1.0..1.0),
            ];
            let raw = base.project_point(pt).unwrap();
            let augp = view.project_point(pt).unwrap();
            let want = apply_aug3(&m, [raw[0], raw[1]]);
            assert!((augp[0] - want[0]).abs() < 1e-8 && (augp[1] - want[1]).abs() < 1e-8);
            assert!((augp[2] - raw[2]).abs() < 1e-12);
            assert_eq!(view.camera.width, 1280);
            assert!(mat3_inverse(&m).is_some());
        }
    }

    #[test]
    fn rotation_is_counter_clockwise_on_screen() {
        // a point right of the centre moves up (v decreases) for a positive angle
        let m = aug_rotate(90.0, 101, 101);
        let q = apply_aug3(&m, [60.0, 50.0]);
        assert!(
            (q[0] - 50.0).abs() < 1e-9 && (q[1] - 40.0).abs() < 1e-9,
            "{q:?}"
        );
        // flip is an involution on pixel centres
        let f = aug_flip_horizontal(10);
        assert_eq!(apply_aug3(&f, apply_aug3(&f, [3.0, 2.0])), [3.0, 2.0]);
        assert_eq!(apply_aug3(&f, [0.0, 0.0]), [9.0, 0.0]);
    }

    #[test]
    fn kitti_test_transform_matches_facts() {
        // docs/formats.md §2.8: for 1226x370 the crop is rows 2..386.
        let a = ImageAug::kitti_test(1226, 370, 1280, 384);
        assert_eq!(a.resized_dims(1226, 370), (1280, 386));
        assert_eq!(a.crop_y0, 2.0);
        // Python: int(1241 * (1280 / 1241)) == int(1279.9999999999998) == 1279: the last output
        // column is padding, exactly as in the reference pipeline.
        let b = ImageAug::kitti_test(1241, 376, 1280, 384);
        assert_eq!(b.resized_dims(1241, 376), (1279, 387));
        assert_eq!(b.crop_y0, 3.0);
    }

    #[test]
    fn voxel_projection_agrees_with_point_projection() {
        let g = VoxelGrid {
            origin_m: [0.0, -25.6, -2.2],
            voxel_size_m: 1.6,
            dims: [32, 32, 4],
        };
        let mut v = kitti_like_view();
        v.cam_from_lidar = mat4_mul(
            &mat4_from_quat_translation([0.999, 0.01, -0.02, 0.03], [0.0; 3]).unwrap(),
            &v.cam_from_lidar,
        );
        let proj = project_voxel_centers(&g, &v);
        assert_eq!(proj.uvd.len(), g.num_voxels());
        let mut n_in = 0;
        for lin in 0..g.num_voxels() {
            let c = g.voxel_center_m(g.ijk_of(lin));
            match v.project_point(c) {
                Some(p) => {
                    assert!((proj.uvd[lin][0] as f64 - p[0]).abs() <= 1e-5 * p[0].abs().max(1.0));
                    assert_eq!(proj.in_view[lin], v.in_view(p));
                }
                None => assert!(!proj.in_view[lin] && proj.uvd[lin][0].is_nan()),
            }
            n_in += proj.in_view[lin] as usize;
        }
        assert!(n_in > 0 && n_in < g.num_voxels());
    }
}
