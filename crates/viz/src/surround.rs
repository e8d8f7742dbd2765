//! Surround-camera frames: the LiDAR points and the occupied voxels of a grid projected into every
//! camera of a rig, the cameras laid out in a grid of panels beside a bird's-eye view of the grid
//! with each camera's frustum.
//!
//! Everything is in one frame, the label grid's ("grid"): each camera is a [`CameraView`] whose
//! `cam_from_lidar` maps grid coordinates to that camera at its own timestamp (for nuScenes the
//! ego motion between the LiDAR and camera timestamps is already in it, see
//! `occ_train::dataset::SurroundDataset::frame_views`), and the points are in the grid frame.
//!
//! Pixel convention (as in `occ_geometry::camera`): the centre of pixel column `i` is at `u = i`,
//! so a point projected to `(u, v)` lies on pixel `(round(u), round(v))` ([`ProjectedPoint::pixel`]).

use crate::canvas::{shade, Canvas};
use crate::font::{draw_text, text_width};
use crate::overlay::{overlay_canvas, OverlayOptions};
use crate::palette::depth_color;
use crate::panels::{panel_grid, side_by_side};
use crate::render::drawn;
use crate::{canvas_to_image, check_grid, check_labels, image_to_canvas, RgbImage, VizError};
use occ_geometry::{
    mat4_inverse, mat4_mul, project_with, transform_point, CameraView, Mat4, VoxelGrid,
};
use rayon::prelude::*;

/// A point projected into an image.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct ProjectedPoint {
    /// Index of the point in the input slice.
    pub index: usize,
    /// Column coordinate (pixel centres at integers).
    pub u: f64,
    /// Row coordinate.
    pub v: f64,
    /// Depth along the optical axis (m).
    pub depth: f64,
}

impl ProjectedPoint {
    /// The pixel `(x, y)` the point lies on: `(round(u), round(v))`.
    pub fn pixel(&self) -> (usize, usize) {
        (self.u.round() as usize, self.v.round() as usize)
    }
}

/// The points (grid frame, metres) that `img_from_grid` puts in front of the camera (depth above
/// `near_m`) and on a pixel of a `width` x `height` image, in input order.
pub fn project_points(
    points: &[[f32; 3]],
    img_from_grid: &Mat4,
    width: usize,
    height: usize,
    near_m: f64,
) -> Vec<ProjectedPoint> {
    let (w, h) = (width as f64 - 0.5, height as f64 - 0.5);
    points
        .iter()
        .enumerate()
        .filter_map(|(index, p)| {
            let [u, v, depth] = project_with(img_from_grid, p.map(f64::from))?;
            (depth > near_m && u >= -0.5 && v >= -0.5 && u < w && v < h).then_some(ProjectedPoint {
                index,
                u,
                v,
                depth,
            })
        })
        .collect()
}

/// One camera of a surround frame.
#[derive(Clone, Copy, Debug)]
pub struct SurroundCamera<'a> {
    /// Panel label (the channel, e.g. `CAM_FRONT`).
    pub name: &'a str,
    /// The camera image, of the size of `view.camera`.
    pub image: &'a RgbImage,
    /// Grid frame -> this camera's pixels.
    pub view: &'a CameraView,
}

/// A class grid to draw over the cameras and in the bird's-eye view.
#[derive(Clone, Copy, Debug)]
pub struct SurroundGrid<'a> {
    /// One class id per voxel, C order `[x][y][z]`.
    pub labels: &'a [u8],
    /// Palette, empty/ignore classes, opacity and depth limits of the camera overlay.
    pub overlay: &'a OverlayOptions,
}

/// Options of [`render_surround`].
#[derive(Clone, Debug, PartialEq)]
pub struct SurroundOptions {
    /// Width of each camera panel in the output (the images are scaled to it, aspect kept).
    pub panel_width: usize,
    /// Columns of the camera grid; `None`: 3 for up to nine cameras (rows of at most three,
    /// e.g. 3x2 for six, 2x2 for four), about square beyond.
    pub columns: Option<usize>,
    /// Radius of a drawn LiDAR point in pixels of the image drawn into (the panel, for
    /// [`render_surround`]); 0 draws one pixel.
    pub point_radius: usize,
    /// Depth (m) at the far end of the point colour ramp (near red .. far violet).
    pub max_depth_m: f64,
    /// Points nearer than this (m along the optical axis) are not drawn.
    pub near_m: f64,
    /// Draw the LiDAR points.
    pub draw_points: bool,
    /// Longer side of the bird's-eye panel in pixels; `None`: the height of the camera grid.
    pub bev_size: Option<usize>,
    /// Length (m) of the frustum edges in the bird's-eye view.
    pub frustum_range_m: f64,
    /// Label of the camera grid (e.g. the scene and sample).
    pub title: String,
}

impl Default for SurroundOptions {
    fn default() -> Self {
        SurroundOptions {
            panel_width: 800,
            columns: None,
            point_radius: 1,
            max_depth_m: 60.0,
            near_m: 0.5,
            draw_points: true,
            bev_size: None,
            frustum_range_m: 30.0,
            title: "cameras".into(),
        }
    }
}

/// A rendered surround frame.
#[derive(Clone, Debug)]
pub struct SurroundRender {
    /// The whole picture: camera panels | bird's-eye view.
    pub image: RgbImage,
    /// LiDAR points drawn in each camera (input order of the cameras).
    pub points_per_camera: Vec<usize>,
}

/// The panel order of a rig: the six nuScenes cameras as they sit on the car (front-left, front,
/// front-right / back-left, back, back-right), any other rig in its own order.
pub fn display_order<S: AsRef<str>>(channels: &[S]) -> Vec<usize> {
    const LAYOUT: [&str; 6] = [
        "CAM_FRONT_LEFT",
        "CAM_FRONT",
        "CAM_FRONT_RIGHT",
        "CAM_BACK_LEFT",
        "CAM_BACK",
        "CAM_BACK_RIGHT",
    ];
    let names: Vec<&str> = channels.iter().map(|c| c.as_ref()).collect();
    let mut sorted = names.clone();
    sorted.sort_unstable();
    let mut six = LAYOUT.to_vec();
    six.sort_unstable();
    if sorted == six {
        LAYOUT
            .iter()
            .map(|l| names.iter().position(|n| n == l).unwrap_or(0))
            .collect()
    } else {
        (0..names.len()).collect()
    }
}

/// Columns of the camera grid for `n` cameras (see [`SurroundOptions::columns`]).
pub fn default_columns(n: usize) -> usize {
    if n <= 9 {
        let rows = n.div_ceil(3).max(1);
        n.div_ceil(rows).max(1)
    } else {
        let rows = (n as f64).sqrt().ceil() as usize;
        n.div_ceil(rows)
    }
}

/// Draw `pts` (from [`project_points`]) into `canvas`, far first so near points end on top, each a
/// disc of `radius` coloured by depth over `[0, max_depth_m]`.
fn draw_projected(canvas: &mut Canvas, pts: &[ProjectedPoint], radius: usize, max_depth_m: f64) {
    let mut order: Vec<&ProjectedPoint> = pts.iter().collect();
    order.sort_by(|a, b| b.depth.total_cmp(&a.depth).then(a.index.cmp(&b.index)));
    for p in order {
        let (x, y) = p.pixel();
        let c = depth_color((p.depth / max_depth_m) as f32);
        canvas.fill_disc(x as i64, y as i64, radius, c);
    }
}

/// One camera image at full resolution with the grid's voxels (nearest first, semi-transparent)
/// and the LiDAR points (coloured by depth) drawn over it; returns the image and the number of
/// points drawn.
pub fn annotate_camera(
    cam: &SurroundCamera<'_>,
    points: &[[f32; 3]],
    grid: &VoxelGrid,
    labels: Option<&SurroundGrid<'_>>,
    opts: &SurroundOptions,
) -> Result<(RgbImage, usize), VizError> {
    let k = cam.view.camera;
    if (cam.image.width, cam.image.height) != (k.width, k.height) {
        return Err(VizError::InvalidImage(format!(
            "{}: image is {}x{} but its camera is {}x{}",
            cam.name, cam.image.width, cam.image.height, k.width, k.height
        )));
    }
    let mut canvas = image_to_canvas(cam.image)?;
    let m = cam.view.img_from_lidar();
    if let Some(g) = labels {
        let mut o = g.overlay.clone();
        o.nearest_only = true;
        overlay_canvas(&mut canvas, g.labels, grid, &m, &o)?;
    }
    let mut n = 0;
    if opts.draw_points {
        let pts = project_points(points, &m, k.width, k.height, opts.near_m);
        draw_projected(&mut canvas, &pts, opts.point_radius, opts.max_depth_m);
        n = pts.len();
    }
    Ok((canvas_to_image(canvas), n))
}

const BEV_BG: [u8; 3] = [24, 24, 28];
const BEV_LINES: [u8; 3] = [48, 48, 56];
/// Frustum colours, one per camera (cycled).
const FRUSTUM_COLORS: [[u8; 3]; 8] = [
    [255, 90, 90],
    [255, 200, 60],
    [90, 230, 90],
    [80, 200, 255],
    [200, 120, 255],
    [255, 130, 220],
    [240, 240, 240],
    [160, 255, 200],
];

/// The bird's-eye view of `grid`: forward (+x) up, left (+y) to the left; each column shows its
/// highest drawn voxel (class colour, darker when lower), the points as small dots coloured by
/// their distance from the grid origin when `draw_points`, each camera's horizontal field of
/// view as a triangle of `frustum_range_m` with its name (from the raw intrinsics and image size;
/// `img_aug` is not used), and a 10 m lattice; `size` pixels along the grid's longer side.
pub fn bev_panel(
    grid: &VoxelGrid,
    labels: Option<&SurroundGrid<'_>>,
    points: &[[f32; 3]],
    cameras: &[(&str, &CameraView)],
    size: usize,
    opts: &SurroundOptions,
) -> Result<RgbImage, VizError> {
    check_grid(grid)?;
    let [nx, ny, nz] = grid.dims;
    if size == 0 || size > 16384 {
        return Err(VizError::InvalidOptions(format!(
            "bird's-eye size {size} is outside 1..=16384"
        )));
    }
    let scale = size as f64 / nx.max(ny) as f64; // pixels per voxel
    let (w, h) = (
        ((ny as f64 * scale).round() as usize).max(1),
        ((nx as f64 * scale).round() as usize).max(1),
    );
    let s = grid.voxel_size_m;
    let o = grid.origin_m;
    // Grid-frame (x, y) metres -> BEV pixel (col, row).
    let to_px = |x: f64, y: f64| -> [f64; 2] {
        [
            (o[1] + ny as f64 * s - y) / s * scale - 0.5,
            (o[0] + nx as f64 * s - x) / s * scale - 0.5,
        ]
    };
    let mut canvas = Canvas::new(w, h, BEV_BG);
    // 10 m lattice through the origin of the frame.
    let step = 10.0;
    let (x0, x1) = (o[0], o[0] + nx as f64 * s);
    let (y0, y1) = (o[1], o[1] + ny as f64 * s);
    let mut gx = (x0 / step).ceil() * step;
    while gx <= x1 {
        canvas.draw_line(to_px(gx, y0), to_px(gx, y1), BEV_LINES, 1);
        gx += step;
    }
    let mut gy = (y0 / step).ceil() * step;
    while gy <= y1 {
        canvas.draw_line(to_px(x0, gy), to_px(x1, gy), BEV_LINES, 1);
        gy += step;
    }
    if let Some(g) = labels {
        check_labels(g.labels, grid)?;
        let lut = g.overlay.palette.lut();
        let (empty, ignore) = (g.overlay.empty_class, g.overlay.ignore_class);
        // The highest drawn voxel of every column.
        let top: Vec<Option<(u8, usize)>> = (0..nx * ny)
            .into_par_iter()
            .map(|col| {
                let base = col * nz;
                (0..nz)
                    .rev()
                    .find(|&k| drawn(g.labels[base + k], empty, ignore))
                    .map(|k| (g.labels[base + k], k))
            })
            .collect();
        for (r, row) in canvas.data.chunks_mut(w * 3).enumerate() {
            let i = nx - 1 - ((r as f64 + 0.5) / scale).floor().min(nx as f64 - 1.0) as usize;
            for c in 0..w {
                let j = ny - 1 - ((c as f64 + 0.5) / scale).floor().min(ny as f64 - 1.0) as usize;
                if let Some((cls, k)) = top[i * ny + j] {
                    let color = if g.overlay.color_by_height {
                        crate::palette::height_color((k as f32 + 0.5) / nz as f32)
                    } else {
                        shade(lut[cls as usize], 0.55 + 0.45 * (k + 1) as f32 / nz as f32)
                    };
                    row[c * 3..c * 3 + 3].copy_from_slice(&color);
                }
            }
        }
    }
    if opts.draw_points {
        for p in points {
            let (x, y) = (p[0] as f64, p[1] as f64);
            if x < x0 || x >= x1 || y < y0 || y >= y1 {
                continue;
            }
            let q = to_px(x, y);
            let range = (x * x + y * y).sqrt();
            canvas.set(
                q[0].round() as usize,
                q[1].round() as usize,
                depth_color((range / opts.max_depth_m) as f32),
            );
        }
    }
    let thick = (size / 450).max(1);
    for (n, (name, view)) in cameras.iter().enumerate() {
        let Some(grid_from_cam) = mat4_inverse(&view.cam_from_lidar) else {
            return Err(VizError::InvalidOptions(format!(
                "{name}: cam_from_grid is singular"
            )));
        };
        let k = view.camera;
        let c = transform_point(&grid_from_cam, [0.0, 0.0, 0.0]);
        // Horizontal directions of the rays through the left and right image edges (principal
        // row) and the optical axis.
        let dir = |u: f64| -> Option<[f64; 2]> {
            let p = transform_point(&grid_from_cam, [(u - k.cx) / k.fx, 0.0, 1.0]);
            let d = [p[0] - c[0], p[1] - c[1]];
            let n = (d[0] * d[0] + d[1] * d[1]).sqrt();
            (n > 1e-6).then(|| [d[0] / n, d[1] / n])
        };
        let (Some(dl), Some(dr), Some(dc)) = (dir(-0.5), dir(k.width as f64 - 0.5), dir(k.cx))
        else {
            continue; // looking straight up or down: no horizontal field of view
        };
        let r = opts.frustum_range_m;
        let color = FRUSTUM_COLORS[n % FRUSTUM_COLORS.len()];
        let pc = to_px(c[0], c[1]);
        let pl = to_px(c[0] + r * dl[0], c[1] + r * dl[1]);
        let pr = to_px(c[0] + r * dr[0], c[1] + r * dr[1]);
        canvas.draw_line(pc, pl, color, thick);
        canvas.draw_line(pc, pr, color, thick);
        canvas.draw_line(pl, pr, color, thick);
        let label = name.strip_prefix("CAM_").unwrap_or(name);
        let t = to_px(c[0] + 0.75 * r * dc[0], c[1] + 0.75 * r * dc[1]);
        let tw = text_width(label, 1) as f64;
        draw_text(
            &mut canvas,
            (t[0] - tw / 2.0).round() as i64,
            (t[1] - 3.0).round() as i64,
            label,
            1,
            color,
        );
    }
    // The ego (grid-frame origin).
    let e = to_px(0.0, 0.0);
    canvas.fill_rect(
        e[0].round() as i64 - 2,
        e[1].round() as i64 - 4,
        5,
        9,
        [255, 255, 255],
    );
    // Depth colour bar of the points.
    if opts.draw_points {
        let (bx, by, bw) = (8i64, h as i64 - 22, 120usize.min(w.saturating_sub(16)));
        for x in 0..bw {
            let c = depth_color(x as f32 / bw.max(1) as f32);
            canvas.fill_rect(bx + x as i64, by, 1, 6, c);
        }
        let txt = format!("0 .. {:.0} m", opts.max_depth_m);
        draw_text(&mut canvas, bx, by + 9, &txt, 1, [220, 220, 220]);
    }
    Ok(canvas_to_image(canvas))
}

/// The whole surround picture: every camera scaled to `panel_width` with the points and voxels
/// drawn over it (see [`annotate_camera`]) and laid out in the grid of
/// [`display_order`] / [`default_columns`], beside the [`bev_panel`] (as tall as the camera grid
/// unless `bev_size` says otherwise).
pub fn render_surround(
    cameras: &[SurroundCamera<'_>],
    points: &[[f32; 3]],
    grid: &VoxelGrid,
    labels: Option<&SurroundGrid<'_>>,
    opts: &SurroundOptions,
) -> Result<SurroundRender, VizError> {
    if cameras.is_empty() {
        return Err(VizError::InvalidOptions("no cameras to render".into()));
    }
    if opts.panel_width == 0 || opts.max_depth_m.is_nan() || opts.max_depth_m <= 0.0 {
        return Err(VizError::InvalidOptions(format!(
            "panel width {} and point depth range {} m must be positive",
            opts.panel_width, opts.max_depth_m
        )));
    }
    check_grid(grid)?;
    if let Some(g) = labels {
        check_labels(g.labels, grid)?;
    }
    // Each camera is drawn at the size of its panel: the image scaled first (bilinear, pixel
    // centres aligned), the view scaled with it, so voxels and points are drawn sharp and at a
    // quarter of the cost of a full-resolution 1600x900 image; the count of points is that of the
    // full-resolution image.
    let panels: Vec<(RgbImage, usize)> = cameras
        .par_iter()
        .map(|cam| -> Result<(RgbImage, usize), VizError> {
            let k = cam.view.camera;
            if (cam.image.width, cam.image.height) != (k.width, k.height) || k.width == 0 {
                return Err(VizError::InvalidImage(format!(
                    "{}: image is {}x{} but its camera is {}x{}",
                    cam.name, cam.image.width, cam.image.height, k.width, k.height
                )));
            }
            let pw = opts.panel_width;
            let ph = ((k.height as f64 * pw as f64 / k.width as f64).round() as usize).max(1);
            let small = canvas_to_image(image_to_canvas(cam.image)?.resized(pw, ph));
            let (sx, sy) = (pw as f64 / k.width as f64, ph as f64 / k.height as f64);
            let panel_from_img: Mat4 = [
                [sx, 0.0, 0.5 * sx - 0.5, 0.0],
                [0.0, sy, 0.5 * sy - 0.5, 0.0],
                [0.0, 0.0, 1.0, 0.0],
                [0.0, 0.0, 0.0, 1.0],
            ];
            let mut view = *cam.view;
            view.img_aug = mat4_mul(&panel_from_img, &view.img_aug);
            view.camera.width = pw;
            view.camera.height = ph;
            let panel_cam = SurroundCamera {
                name: cam.name,
                image: &small,
                view: &view,
            };
            let (img, _) = annotate_camera(&panel_cam, points, grid, labels, opts)?;
            let n = if opts.draw_points {
                project_points(
                    points,
                    &cam.view.img_from_lidar(),
                    k.width,
                    k.height,
                    opts.near_m,
                )
                .len()
            } else {
                0
            };
            Ok((img, n))
        })
        .collect::<Result<_, _>>()?;
    let names: Vec<&str> = cameras.iter().map(|c| c.name).collect();
    let order = display_order(&names);
    let titles: Vec<String> = order
        .iter()
        .map(|&i| {
            if opts.draw_points {
                format!("{}  {} pts", names[i], panels[i].1)
            } else {
                names[i].to_string()
            }
        })
        .collect();
    let refs: Vec<(&str, &RgbImage)> = order
        .iter()
        .zip(&titles)
        .map(|(&i, t)| (t.as_str(), &panels[i].0))
        .collect();
    let columns = opts
        .columns
        .unwrap_or_else(|| default_columns(cameras.len()));
    let cam_grid = panel_grid(&refs, columns)?;
    let views: Vec<(&str, &CameraView)> = cameras.iter().map(|c| (c.name, c.view)).collect();
    let size = opts.bev_size.unwrap_or(cam_grid.height);
    let bev = bev_panel(grid, labels, points, &views, size, opts)?;
    let image = side_by_side(&[(opts.title.as_str(), &cam_grid), ("top view", &bev)])?;
    Ok(SurroundRender {
        image,
        points_per_camera: panels.iter().map(|p| p.1).collect(),
    })
}

#[cfg(test)]
mod tests {
    use super::*;
    use occ_geometry::PinholeCamera;

    fn camera(yaw_deg: f64) -> CameraView {
        // Camera at the origin looking along the grid's +x rotated by yaw (x right, y down,
        // z forward).
        let (s, c) = yaw_deg.to_radians().sin_cos();
        let grid_from_cam: Mat4 = [
            [s, 0.0, c, 0.0],
            [-c, 0.0, s, 0.0],
            [0.0, -1.0, 0.0, 1.0],
            [0.0, 0.0, 0.0, 1.0],
        ];
        let k = PinholeCamera {
            fx: 50.0,
            fy: 50.0,
            cx: 40.0,
            cy: 30.0,
            width: 80,
            height: 60,
        };
        CameraView::new(k, mat4_inverse(&grid_from_cam).unwrap())
    }

    #[test]
    fn points_project_to_their_rounded_pixel_and_off_image_points_are_dropped() {
        let v = camera(0.0);
        let m = v.img_from_lidar();
        // 10 m ahead on the optical axis at the camera's height -> the principal point.
        let pts = [
            [10.0, 0.0, 1.0],
            [10.0, 1.0, 1.0],  // left of centre: u = 40 - 5
            [-10.0, 0.0, 1.0], // behind
            [10.0, -9.0, 1.0], // far right, off the image
            [0.2, 0.0, 1.0],   // nearer than near_m
        ];
        let p = project_points(&pts, &m, 80, 60, 0.5);
        assert_eq!(p.len(), 2);
        assert_eq!((p[0].index, p[0].pixel()), (0, (40, 30)));
        assert!((p[0].depth - 10.0).abs() < 1e-12);
        assert_eq!((p[1].index, p[1].pixel()), (1, (35, 30)));
        // The pixel is the rounded position: u = 39.6 -> 40, 39.4 -> 39; -0.5 <= u < w - 0.5.
        let q = project_points(&[[10.0, 0.08, 1.0], [10.0, 0.12, 1.0]], &m, 80, 60, 0.5);
        assert_eq!(q[0].pixel(), (40, 30));
        assert_eq!(q[1].pixel(), (39, 30));
        // u = -1 is off the image, u = -0.25 on pixel 0.
        let edge = project_points(&[[10.0, 8.2, 1.0], [10.0, 8.05, 1.0]], &m, 80, 60, 0.5);
        assert_eq!(edge.len(), 1);
        assert_eq!(edge[0].pixel(), (0, 30));
    }

    #[test]
    fn annotated_camera_shows_points_on_top_of_voxels_in_depth_colour() {
        let v = camera(0.0);
        let grid = VoxelGrid {
            origin_m: [0.0, -4.0, -1.0],
            voxel_size_m: 1.0,
            dims: [20, 8, 4],
        };
        let mut labels = vec![17u8; grid.num_voxels()];
        // A wall of class 4 (car, Occ3D) at x = 10 m.
        for j in 0..8 {
            for k in 0..4 {
                labels[(10 * 8 + j) * 4 + k] = 4;
            }
        }
        let img = RgbImage::new(80, 60);
        let cam = SurroundCamera {
            name: "CAM_FRONT",
            image: &img,
            view: &v,
        };
        let ov = OverlayOptions::new(crate::Palette::Occ3d);
        let g = SurroundGrid {
            labels: &labels,
            overlay: &ov,
        };
        let opts = SurroundOptions {
            point_radius: 0,
            ..Default::default()
        };
        let pts = [[10.0f32, 0.0, 1.0]];
        let (out, n) = annotate_camera(&cam, &pts, &grid, Some(&g), &opts).unwrap();
        assert_eq!(n, 1);
        let px = |x: usize, y: usize| {
            let i = (y * 80 + x) * 3;
            [out.data[i], out.data[i + 1], out.data[i + 2]]
        };
        assert_eq!(px(40, 30), depth_color((10.0 / 60.0) as f32));
        // Beside the point: the wall, blended once (alpha 0.5) over black.
        let car = crate::Palette::Occ3d.color(4).unwrap();
        let want = crate::canvas::blend([0, 0, 0], car, 0.5);
        let dark = crate::canvas::blend([0, 0, 0], shade(car, 0.55), 0.5);
        assert!(px(45, 25) == want || px(45, 25) == dark, "{:?}", px(45, 25));
        // Wrong image size is an error naming the camera.
        let small = RgbImage::new(10, 10);
        let bad = SurroundCamera {
            name: "CAM_X",
            image: &small,
            view: &v,
        };
        let e = annotate_camera(&bad, &pts, &grid, None, &opts).unwrap_err();
        assert!(e.to_string().contains("CAM_X"), "{e}");
    }

    #[test]
    fn render_surround_draws_each_camera_at_panel_scale() {
        let v = camera(0.0);
        let grid = VoxelGrid {
            origin_m: [0.0, -4.0, -1.0],
            voxel_size_m: 1.0,
            dims: [20, 8, 4],
        };
        let img = RgbImage::new(80, 60);
        let cams = [SurroundCamera {
            name: "CAM_FRONT",
            image: &img,
            view: &v,
        }];
        let opts = SurroundOptions {
            panel_width: 40,
            point_radius: 0,
            ..Default::default()
        };
        let pts = [[10.0f32, 0.0, 1.0], [-5.0, 0.0, 1.0]];
        let r = render_surround(&cams, &pts, &grid, None, &opts).unwrap();
        assert_eq!(r.points_per_camera, vec![1]);
        // Full-resolution pixel (40, 30) is panel position (0.5 * 40 - 0.25, 0.5 * 30 - 0.25)
        // = (19.75, 14.75) -> pixel (20, 15); the panel sits below two label strips.
        use crate::panels::{LABEL_STRIP_H, PANEL_GAP};
        let (x, y) = (2 * PANEL_GAP + 20, 2 * (PANEL_GAP + LABEL_STRIP_H) + 15);
        let i = (y * r.image.width + x) * 3;
        assert_eq!(
            &r.image.data[i..i + 3],
            &depth_color((10.0 / 60.0) as f32)[..]
        );
        let j = i - 3 * 2;
        assert_eq!(&r.image.data[j..j + 3], &[0, 0, 0][..]);
        assert!(render_surround(&[], &pts, &grid, None, &opts).is_err());
    }

    #[test]
    fn display_order_and_columns() {
        // The readers' (BEVDet's) camera order.
        let bevdet = occ_data::formats::nuscenes_occupancy::CAMERA_CHANNELS;
        assert_eq!(display_order(&bevdet), vec![2, 0, 1, 4, 3, 5]);
        assert_eq!(display_order(&["B", "A", "C"]), vec![0, 1, 2]);
        assert_eq!(display_order(&bevdet[..5]), vec![0, 1, 2, 3, 4]);
        let cols: Vec<usize> = (1..=12).map(default_columns).collect();
        assert_eq!(cols, vec![1, 2, 3, 2, 3, 3, 3, 3, 3, 3, 3, 3]);
    }

    #[test]
    fn bev_draws_columns_frusta_and_rejects_bad_input() {
        let grid = VoxelGrid {
            origin_m: [-10.0, -10.0, -1.0],
            voxel_size_m: 1.0,
            dims: [20, 20, 4],
        };
        let mut labels = vec![17u8; grid.num_voxels()];
        // One voxel column at x in [5, 6), y in [-8, -7) (ahead, to the right), class 11.
        labels[(15 * 20 + 2) * 4] = 11;
        let ov = OverlayOptions::new(crate::Palette::Occ3d);
        let g = SurroundGrid {
            labels: &labels,
            overlay: &ov,
        };
        let opts = SurroundOptions {
            draw_points: false,
            frustum_range_m: 8.0,
            ..Default::default()
        };
        let front = camera(0.0);
        let bev = bev_panel(&grid, Some(&g), &[], &[("CAM_FRONT", &front)], 200, &opts).unwrap();
        assert_eq!((bev.width, bev.height), (200, 200));
        let px = |x: usize, y: usize| {
            let i = (y * 200 + x) * 3;
            [bev.data[i], bev.data[i + 1], bev.data[i + 2]]
        };
        // Row = (10 - x) * 10 px, col = (10 - y) * 10 px: the column's centre at (x 5.5, y -7.5).
        let cls = shade(crate::Palette::Occ3d.color(11).unwrap(), 0.55 + 0.45 / 4.0);
        assert_eq!(px(175, 45), cls);
        // The frustum's far edge joins the edge rays' ends 8 m out (half angle atan(40.5/50),
        // 6.2 m ahead: row 37.5), in its colour.
        assert!((35..=40).any(|r| px(100, r) == FRUSTUM_COLORS[0]));
        // Beside the frustum, ahead and to the left, only background and lattice.
        assert!(px(20, 30) == BEV_BG || px(20, 30) == BEV_LINES);
        // Behind the camera nothing is drawn but the lattice.
        assert!(px(100, 150) == BEV_BG || px(100, 150) == BEV_LINES);
        let short = vec![0u8; 3];
        let bad = SurroundGrid {
            labels: &short,
            overlay: &ov,
        };
        assert!(bev_panel(&grid, Some(&bad), &[], &[], 200, &opts).is_err());
        assert!(bev_panel(&grid, None, &[], &[], 0, &opts).is_err());
    }
}
