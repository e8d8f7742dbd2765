//! Software renderer for dense voxel label grids: a perspective view from behind and above the
//! ego, flat-shaded cubes, z-buffer, legend and title.
//!
//! Only faces between a drawn voxel and a not-drawn neighbour (empty class, ignore class, or
//! outside the grid) that face the camera are rasterised: for a driving scene that is a small
//! fraction of the 6 faces per occupied voxel, which is what makes a full 256x256x32 grid fast.
//! Rasterisation runs in parallel over horizontal bands of the image (rayon), each band with its
//! own slice of the z-buffer; per pixel the nearest face wins (ties go to the face found first
//! in C order, so the output is deterministic).

use crate::RgbImage;
use occ_geometry::{CameraView, Mat4, PinholeCamera, VoxelGrid};
use occ_labels::IGNORE;
use rayon::prelude::*;

use crate::canvas::{shade, Canvas};
use crate::font::{draw_text, text_height, text_width};
use crate::palette::{height_color, Palette};
use crate::raster::{AffinePlane, ConvexPoly};
use crate::{canvas_to_image, check_grid, VizError};

/// Options of [`render_voxels`].
#[derive(Debug, Clone, PartialEq)]
pub struct RenderOptions {
    /// Output width in pixels (scene + legend).
    pub width: usize,
    /// Output height in pixels (title + scene).
    pub height: usize,
    /// Class palette (names and colours).
    pub palette: Palette,
    /// Class id that is not drawn (free space).
    pub empty_class: u8,
    /// Class id that is not drawn (unknown / ignored, 255 in all supported datasets).
    pub ignore_class: u8,
    /// Optional title drawn in a strip above the scene.
    pub title: Option<String>,
    /// Draw a legend to the right of the scene: one swatch and name per class present in the
    /// grid, or a height colour bar in height mode.
    pub legend: bool,
    /// Colour voxels by the height of their centre (for occupancy-only grids) instead of class.
    pub color_by_height: bool,
    /// Scene background colour.
    pub background: [u8; 3],
}

impl RenderOptions {
    /// 1280x720, legend on, no title, class colours, empty class = the palette's, ignore = 255.
    pub fn new(palette: Palette) -> Self {
        RenderOptions {
            width: 1280,
            height: 720,
            palette,
            empty_class: palette.default_empty_class(),
            ignore_class: IGNORE,
            title: None,
            legend: true,
            color_by_height: false,
            background: [246, 246, 246],
        }
    }
}

/// Largest output image (pixels) any function of this crate creates.
pub const MAX_PIXELS: usize = 1 << 28;

/// Text scale of titles and legends (5x7 glyphs drawn 2x).
const TEXT_SCALE: usize = 2;
/// Height of the title strip.
const TITLE_H: usize = crate::font::LINE_H * TEXT_SCALE + 12;
const TEXT_COLOR: [u8; 3] = [20, 20, 20];
const LEGEND_BG: [u8; 3] = [255, 255, 255];

/// Where the scene goes inside the output image.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Viewport {
    /// Left column of the scene.
    pub x: usize,
    /// Top row of the scene.
    pub y: usize,
    /// Width of the scene.
    pub width: usize,
    /// Height of the scene.
    pub height: usize,
}

/// The virtual camera of a render: a pinhole camera in *output image* pixels (the scene
/// viewport offset is folded into `cx`, `cy`), placed behind and above the grid and looking
/// forward and down (LiDAR frame: x forward, y left, z up; camera frame: x right, y down,
/// z forward).
#[derive(Debug, Clone, PartialEq)]
pub struct RenderCamera {
    /// Camera centre in the LiDAR frame, metres.
    pub eye_m: [f64; 3],
    /// Rigid transform LiDAR → camera.
    pub cam_from_lidar: Mat4,
    /// Focal length along u, output pixels.
    pub fx: f64,
    /// Focal length along v, output pixels.
    pub fy: f64,
    /// Principal point u (output image pixels, viewport offset included).
    pub cx: f64,
    /// Principal point v (output image pixels, viewport offset included).
    pub cy: f64,
    /// Output image width.
    pub width: usize,
    /// Output image height.
    pub height: usize,
    /// Part of the output that shows the scene.
    pub viewport: Viewport,
}

impl RenderCamera {
    /// `img_from_lidar = K · cam_from_lidar` (4x4; row 2 gives the camera depth).
    pub fn img_from_lidar(&self) -> Mat4 {
        let k: Mat4 = [
            [self.fx, 0.0, self.cx, 0.0],
            [0.0, self.fy, self.cy, 0.0],
            [0.0, 0.0, 1.0, 0.0],
            [0.0, 0.0, 0.0, 1.0],
        ];
        let m = &self.cam_from_lidar;
        let mut out = [[0.0; 4]; 4];
        for (r, row) in out.iter_mut().enumerate() {
            for (c, v) in row.iter_mut().enumerate() {
                *v = (0..4).map(|i| k[r][i] * m[i][c]).sum();
            }
        }
        out
    }

    /// Project a LiDAR-frame point to (u, v, depth_m) in output pixels (`None` behind the
    /// camera). The centre of pixel (i, j) is at (u, v) = (i, j), as in `occ_geometry`.
    pub fn project(&self, p_lidar_m: [f64; 3]) -> Option<[f64; 3]> {
        project_with(&self.img_from_lidar(), p_lidar_m)
    }

    /// The same camera as an `occ_geometry::CameraView` (no image augmentation), so that
    /// renders can be checked against the project-wide projection code.
    pub fn camera_view(&self) -> CameraView {
        CameraView::new(
            PinholeCamera {
                fx: self.fx,
                fy: self.fy,
                cx: self.cx,
                cy: self.cy,
                width: self.width,
                height: self.height,
            },
            self.cam_from_lidar,
        )
    }
}

pub(crate) fn identity4() -> Mat4 {
    [
        [1.0, 0.0, 0.0, 0.0],
        [0.0, 1.0, 0.0, 0.0],
        [0.0, 0.0, 1.0, 0.0],
        [0.0, 0.0, 0.0, 1.0],
    ]
}

/// Perspective projection with a 4x4 (or 3x4 padded) `img_from_lidar`: `h = M·[p,1]`,
/// `(u, v) = (h0/h2, h1/h2)`, depth = `h2`. `None` when `h2 <= 1e-9` or not finite.
pub(crate) fn project_with(m: &Mat4, p: [f64; 3]) -> Option<[f64; 3]> {
    let h = |r: usize| m[r][0] * p[0] + m[r][1] * p[1] + m[r][2] * p[2] + m[r][3];
    let (h0, h1, h2) = (h(0), h(1), h(2));
    if h2.is_nan() || h2 <= 1e-9 || !h0.is_finite() || !h1.is_finite() {
        return None;
    }
    Some([h0 / h2, h1 / h2, h2])
}

/// Whether a voxel with class `c` is drawn.
#[inline]
pub(crate) fn drawn(c: u8, empty: u8, ignore: u8) -> bool {
    c != empty && c != ignore
}

/// Classes present (drawn) in `labels`, ascending.
fn present_classes(labels: &[u8], empty: u8, ignore: u8) -> Vec<u8> {
    let mut seen = [false; 256];
    for &c in labels {
        seen[c as usize] = true;
    }
    (0..=255u8)
        .filter(|&c| seen[c as usize] && drawn(c, empty, ignore))
        .collect()
}

/// What the legend shows and how wide it is.
enum Legend {
    None,
    Classes { classes: Vec<u8>, scale: usize },
    HeightBar { z_min_m: f64, z_max_m: f64 },
}

const LEGEND_PAD: usize = 10;
const SWATCH: usize = 16;

impl Legend {
    fn plan(labels: &[u8], grid: &VoxelGrid, opts: &RenderOptions, avail_h: usize) -> Legend {
        if !opts.legend {
            return Legend::None;
        }
        if opts.color_by_height {
            let z0 = grid.origin_m[2];
            return Legend::HeightBar {
                z_min_m: z0,
                z_max_m: z0 + grid.dims[2] as f64 * grid.voxel_size_m,
            };
        }
        let classes = present_classes(labels, opts.empty_class, opts.ignore_class);
        // Shrink the text if the rows would not fit at 2x. Decided (like the width) from the
        // palette, not from the classes present, so that renders of different label grids
        // (prediction | ground truth) get the same framing.
        let rows = classes.len().max(opts.palette.num_classes()) + 1;
        let scale = if rows * (text_height(TEXT_SCALE).max(SWATCH) + 6) + 2 * LEGEND_PAD <= avail_h
        {
            TEXT_SCALE
        } else {
            1
        };
        Legend::Classes { classes, scale }
    }

    fn label(palette: Palette, c: u8) -> String {
        match palette.name(c) {
            Some(n) => format!("{c} {n}"),
            None => format!("{c} unknown"),
        }
    }

    fn width(&self, palette: Palette) -> usize {
        match self {
            Legend::None => 0,
            Legend::Classes { classes, scale } => {
                let text = (0..palette.num_classes() as u8)
                    .chain(classes.iter().copied())
                    .map(|c| text_width(&Self::label(palette, c), *scale))
                    .chain(std::iter::once(text_width("classes", *scale)))
                    .max()
                    .unwrap_or(0);
                text + SWATCH + 8 + 3 * LEGEND_PAD
            }
            Legend::HeightBar { z_min_m, z_max_m } => {
                let w = [*z_min_m, *z_max_m]
                    .iter()
                    .map(|z| text_width(&format!("{z:.1} m"), TEXT_SCALE))
                    .chain(std::iter::once(text_width("height", TEXT_SCALE)))
                    .max()
                    .unwrap_or(0);
                w + 24 + 8 + 3 * LEGEND_PAD
            }
        }
    }

    fn draw(&self, canvas: &mut Canvas, x0: usize, y0: usize, h: usize, palette: Palette) {
        let w = self.width(palette);
        if w == 0 {
            return;
        }
        canvas.fill_rect(x0 as i64, y0 as i64, w as i64, h as i64, LEGEND_BG);
        canvas.fill_rect(x0 as i64, y0 as i64, 1, h as i64, [200, 200, 200]);
        let x = (x0 + LEGEND_PAD) as i64;
        let mut y = (y0 + LEGEND_PAD) as i64;
        match self {
            Legend::None => {}
            Legend::Classes { classes, scale } => {
                let th = text_height(*scale) as i64;
                let sw = if *scale >= 2 { SWATCH as i64 } else { th + 1 };
                let row_h = th.max(sw) + 6;
                draw_text(canvas, x, y, "classes", *scale, TEXT_COLOR);
                y += row_h;
                for &c in classes {
                    let col = palette.color_or_unknown(c);
                    let cap = (crate::font::GLYPH_H * scale) as i64;
                    canvas.fill_rect(x, y + (cap - sw) / 2, sw, sw, col);
                    canvas.stroke_rect(x, y + (cap - sw) / 2, sw, sw, [60, 60, 60]);
                    let label = Self::label(palette, c);
                    draw_text(canvas, x + sw + 8, y, &label, *scale, TEXT_COLOR);
                    y += row_h;
                }
            }
            Legend::HeightBar { z_min_m, z_max_m } => {
                let th = text_height(TEXT_SCALE) as i64;
                draw_text(canvas, x, y, "height", TEXT_SCALE, TEXT_COLOR);
                y += th + 10;
                let bar_top = y + th / 2;
                let bar_h =
                    (h as i64 - (bar_top - y0 as i64) - 2 * LEGEND_PAD as i64 - th).clamp(20, 360);
                for r in 0..bar_h {
                    // Top of the bar = highest.
                    let t = 1.0 - r as f32 / (bar_h - 1).max(1) as f32;
                    canvas.fill_rect(x, bar_top + r, 24, 1, height_color(t));
                }
                canvas.stroke_rect(x, bar_top, 24, bar_h, [60, 60, 60]);
                let ticks = 5;
                for i in 0..ticks {
                    let f = i as f64 / (ticks - 1) as f64;
                    let z = z_max_m - f * (z_max_m - z_min_m);
                    let ty = bar_top + ((bar_h - 1) as f64 * f).round() as i64;
                    canvas.fill_rect(x + 24, ty, 5, 1, [60, 60, 60]);
                    let cap = (crate::font::GLYPH_H * TEXT_SCALE) as i64;
                    draw_text(
                        canvas,
                        x + 32,
                        ty - cap / 2,
                        &format!("{z:.1} m"),
                        TEXT_SCALE,
                        TEXT_COLOR,
                    );
                }
            }
        }
    }
}

/// Layout of an output image: title strip, scene viewport, legend.
fn layout(
    labels: &[u8],
    grid: &VoxelGrid,
    opts: &RenderOptions,
) -> Result<(Viewport, Legend), VizError> {
    if opts.width.saturating_mul(opts.height) > MAX_PIXELS {
        return Err(VizError::InvalidOptions(format!(
            "render size {}x{} exceeds {MAX_PIXELS} pixels",
            opts.width, opts.height
        )));
    }
    let title_h = if opts.title.is_some() { TITLE_H } else { 0 };
    if opts.height < title_h + 32 {
        return Err(VizError::InvalidOptions(format!(
            "render height {} is too small (need at least {})",
            opts.height,
            title_h + 32
        )));
    }
    let legend = Legend::plan(labels, grid, opts, opts.height - title_h);
    let legend_w = legend.width(opts.palette);
    if opts.width < legend_w + 32 {
        return Err(VizError::InvalidOptions(format!(
            "render width {} is too small for the legend ({} px) plus the scene",
            opts.width, legend_w
        )));
    }
    Ok((
        Viewport {
            x: 0,
            y: title_h,
            width: opts.width - legend_w,
            height: opts.height - title_h,
        },
        legend,
    ))
}

/// Build the render camera for `grid` shown in `viewport` of a `width` x `height` image.
///
/// The eye is behind the grid's back face (x = x_min) and above its top, on the grid's y
/// centre line, looking at a point on the grid floor ahead; the focal length and principal
/// point are chosen so that the grid's 8 corners fill the viewport with a small margin.
pub fn fit_camera(
    grid: &VoxelGrid,
    width: usize,
    height: usize,
    viewport: Viewport,
) -> Result<RenderCamera, VizError> {
    check_grid(grid)?;
    let lo = grid.origin_m;
    let size = [
        grid.dims[0] as f64 * grid.voxel_size_m,
        grid.dims[1] as f64 * grid.voxel_size_m,
        grid.dims[2] as f64 * grid.voxel_size_m,
    ];
    let hi = [lo[0] + size[0], lo[1] + size[1], lo[2] + size[2]];
    let span = size[0].max(size[1]);
    let yc = lo[1] + 0.5 * size[1];
    let eye = [lo[0] - 0.15 * span, yc, hi[2] + 0.6 * span];
    let target = [lo[0] + 0.5 * size[0], yc, lo[2]];
    let f = normalize(sub(target, eye));
    let up = [0.0, 0.0, 1.0];
    let right = normalize(cross(f, up));
    let down = cross(f, right);
    let rot = [right, down, f];
    let mut cam_from_lidar = identity4();
    for r in 0..3 {
        cam_from_lidar[r][..3].copy_from_slice(&rot[r]);
        cam_from_lidar[r][3] = -dot(rot[r], eye);
    }
    // Fit the 8 corners into the viewport.
    let mut nx = (f64::INFINITY, f64::NEG_INFINITY);
    let mut ny = (f64::INFINITY, f64::NEG_INFINITY);
    for i in 0..8 {
        let p = [
            if i & 1 == 0 { lo[0] } else { hi[0] },
            if i & 2 == 0 { lo[1] } else { hi[1] },
            if i & 4 == 0 { lo[2] } else { hi[2] },
        ];
        let c: Vec<f64> = (0..3)
            .map(|r| dot(rot[r], p) + cam_from_lidar[r][3])
            .collect();
        if c[2].is_nan() || c[2] <= 1e-6 {
            return Err(VizError::InvalidGrid(format!(
                "grid corner {p:?} is behind the render camera"
            )));
        }
        let (x, y) = (c[0] / c[2], c[1] / c[2]);
        nx = (nx.0.min(x), nx.1.max(x));
        ny = (ny.0.min(y), ny.1.max(y));
    }
    let margin = 0.04;
    let vw = viewport.width as f64 * (1.0 - 2.0 * margin);
    let vh = viewport.height as f64 * (1.0 - 2.0 * margin);
    let focal = (vw / (nx.1 - nx.0)).min(vh / (ny.1 - ny.0));
    if !focal.is_finite() || focal <= 0.0 {
        return Err(VizError::InvalidGrid(format!(
            "grid {:?} with voxel size {} m gives a degenerate view",
            grid.dims, grid.voxel_size_m
        )));
    }
    let cx = viewport.x as f64 + 0.5 * (viewport.width as f64 - 1.0) - focal * 0.5 * (nx.0 + nx.1);
    let cy = viewport.y as f64 + 0.5 * (viewport.height as f64 - 1.0) - focal * 0.5 * (ny.0 + ny.1);
    Ok(RenderCamera {
        eye_m: eye,
        cam_from_lidar,
        fx: focal,
        fy: focal,
        cx,
        cy,
        width,
        height,
        viewport,
    })
}

/// The camera [`render_voxels`] uses for these labels, grid and options (the legend width
/// depends on the classes present).
pub fn render_camera(
    labels: &[u8],
    grid: &VoxelGrid,
    opts: &RenderOptions,
) -> Result<RenderCamera, VizError> {
    check_grid(grid)?;
    let (vp, _) = layout(labels, grid, opts)?;
    fit_camera(grid, opts.width, opts.height, vp)
}

/// Face directions: 0 -x, 1 +x, 2 -y, 3 +y, 4 -z, 5 +z.
const DIRS: [[i64; 3]; 6] = [
    [-1, 0, 0],
    [1, 0, 0],
    [0, -1, 0],
    [0, 1, 0],
    [0, 0, -1],
    [0, 0, 1],
];

/// Light direction (towards the light) in the LiDAR frame: from above, slightly behind-left of
/// the ego, so that tops, camera-facing fronts and sides get distinct shades.
const LIGHT: [f64; 3] = [-0.5, 0.25, 1.0];
const AMBIENT: f64 = 0.42;

/// Lambert factor per face direction.
fn face_shades() -> [f32; 6] {
    let l = normalize(LIGHT);
    let mut s = [0.0f32; 6];
    for (d, dir) in DIRS.iter().enumerate() {
        let n = [dir[0] as f64, dir[1] as f64, dir[2] as f64];
        s[d] = (AMBIENT + (1.0 - AMBIENT) * dot(n, l).max(0.0)) as f32;
    }
    s
}

/// A projected, shaded face ready for scan conversion.
/// Kept compact (52 bytes): a worst-case grid has millions of exposed faces. The edge
/// functions and the depth plane are rebuilt in each band that the face touches.
struct Quad {
    pts: [[f32; 2]; 4],
    inv_depth: [f32; 4],
    color: [u8; 3],
}

/// Homogeneous projection of lattice point (i, j, k) is `base + i*ax + j*ay + k*az`.
struct Lattice {
    base: [f64; 3],
    ax: [f64; 3],
    ay: [f64; 3],
    az: [f64; 3],
}

impl Lattice {
    fn new(m: &Mat4, grid: &VoxelGrid) -> Lattice {
        let o = grid.origin_m;
        let s = grid.voxel_size_m;
        let mut l = Lattice {
            base: [0.0; 3],
            ax: [0.0; 3],
            ay: [0.0; 3],
            az: [0.0; 3],
        };
        for (r, row) in m.iter().take(3).enumerate() {
            l.base[r] = row[0] * o[0] + row[1] * o[1] + row[2] * o[2] + row[3];
            l.ax[r] = row[0] * s;
            l.ay[r] = row[1] * s;
            l.az[r] = row[2] * s;
        }
        l
    }

    /// (u, v, depth) of lattice point (i, j, k), `None` if not in front of the camera.
    #[inline]
    fn project(&self, i: f64, j: f64, k: f64, near: f64) -> Option<[f64; 3]> {
        let h = |r: usize| self.base[r] + i * self.ax[r] + j * self.ay[r] + k * self.az[r];
        let w = h(2);
        if w <= near {
            return None;
        }
        Some([h(0) / w, h(1) / w, w])
    }
}

/// Corners (lattice offsets) of face `d` of the unit voxel, in order around the face.
fn face_corners(d: usize) -> [[f64; 3]; 4] {
    match d {
        0 => [[0., 0., 0.], [0., 1., 0.], [0., 1., 1.], [0., 0., 1.]],
        1 => [[1., 0., 0.], [1., 1., 0.], [1., 1., 1.], [1., 0., 1.]],
        2 => [[0., 0., 0.], [1., 0., 0.], [1., 0., 1.], [0., 0., 1.]],
        3 => [[0., 1., 0.], [1., 1., 0.], [1., 1., 1.], [0., 1., 1.]],
        4 => [[0., 0., 0.], [1., 0., 0.], [1., 1., 0.], [0., 1., 0.]],
        _ => [[0., 0., 1.], [1., 0., 1.], [1., 1., 1.], [0., 1., 1.]],
    }
}

/// Render `labels` (one class per voxel, C order [x][y][z], `grid.num_voxels()` long) as
/// shaded cubes seen from behind and above the ego.
///
/// Voxels of `opts.empty_class` and `opts.ignore_class` are not drawn. Colours come from
/// `opts.palette`, or from the voxel centre height when `opts.color_by_height`.
pub fn render_voxels(
    labels: &[u8],
    grid: &VoxelGrid,
    opts: &RenderOptions,
) -> Result<RgbImage, VizError> {
    Ok(canvas_to_image(render_canvas(labels, grid, opts)?))
}

pub(crate) fn render_canvas(
    labels: &[u8],
    grid: &VoxelGrid,
    opts: &RenderOptions,
) -> Result<Canvas, VizError> {
    check_grid(grid)?;
    crate::check_labels(labels, grid)?;
    let (vp, legend) = layout(labels, grid, opts)?;
    let cam = fit_camera(grid, opts.width, opts.height, vp)?;
    let scene = rasterize(labels, grid, &cam.img_from_lidar(), cam.eye_m, vp, opts);
    let mut out = Canvas::new(opts.width, opts.height, LEGEND_BG);
    if let Some(t) = &opts.title {
        out.fill_rect(0, 0, opts.width as i64, TITLE_H as i64, [235, 235, 235]);
        let ty = (TITLE_H - text_height(TEXT_SCALE)) / 2;
        draw_text(&mut out, 10, ty as i64, t, TEXT_SCALE, TEXT_COLOR);
    }
    out.blit(&scene, vp.x as i64, vp.y as i64);
    legend.draw(&mut out, vp.x + vp.width, vp.y, vp.height, opts.palette);
    Ok(out)
}

/// Render `labels` as seen by a given camera `view` (e.g. the dataset's camera, to compare with
/// the photo). The output has the view's image size; the title and legend options are not
/// used (compose with [`crate::side_by_side`] instead). Faces with a corner behind the camera
/// are skipped.
pub fn render_voxels_from_view(
    labels: &[u8],
    grid: &VoxelGrid,
    view: &CameraView,
    opts: &RenderOptions,
) -> Result<RgbImage, VizError> {
    check_grid(grid)?;
    crate::check_labels(labels, grid)?;
    let (w, h) = (view.camera.width, view.camera.height);
    if w == 0 || h == 0 || w.saturating_mul(h) > MAX_PIXELS {
        return Err(VizError::InvalidOptions(format!(
            "camera image size {w}x{h} is not renderable"
        )));
    }
    let m = view.img_from_lidar();
    let lidar_from_cam = occ_geometry::mat4_inverse(&view.cam_from_lidar)
        .filter(|m| m.iter().flatten().all(|v| v.is_finite()))
        .ok_or_else(|| VizError::InvalidOptions("cam_from_lidar is not invertible".into()))?;
    if m.iter().flatten().any(|v| !v.is_finite()) {
        return Err(VizError::InvalidOptions(
            "img_from_lidar has a non-finite entry".into(),
        ));
    }
    let eye = [
        lidar_from_cam[0][3],
        lidar_from_cam[1][3],
        lidar_from_cam[2][3],
    ];
    let vp = Viewport {
        x: 0,
        y: 0,
        width: w,
        height: h,
    };
    Ok(canvas_to_image(rasterize(labels, grid, &m, eye, vp, opts)))
}

/// Rasterise the exposed, camera-facing faces of the drawn voxels with projection `m` (output
/// image pixels) and camera centre `eye` into a canvas of the viewport's size (pixel (x, y) of
/// the canvas is pixel (vp.x + x, vp.y + y) of the output image).
fn rasterize(
    labels: &[u8],
    grid: &VoxelGrid,
    m: &Mat4,
    eye: [f64; 3],
    vp: Viewport,
    opts: &RenderOptions,
) -> Canvas {
    let lattice = Lattice::new(m, grid);
    let [nx, ny, nz] = grid.dims;
    let (empty, ignore) = (opts.empty_class, opts.ignore_class);
    let shades = face_shades();
    let lut = opts.palette.lut();
    let o = grid.origin_m;
    let s = grid.voxel_size_m;
    // Face d of voxel (i, j, k) faces the camera iff the eye is on its outer side.
    let eye_idx = [
        (eye[0] - o[0]) / s,
        (eye[1] - o[1]) / s,
        (eye[2] - o[2]) / s,
    ];
    let faces_camera = |d: usize, i: usize, j: usize, k: usize| -> bool {
        let (axis, positive) = (d / 2, d % 2 == 1);
        let idx = [i, j, k][axis] as f64;
        if positive {
            eye_idx[axis] > idx + 1.0
        } else {
            eye_idx[axis] < idx
        }
    };
    let near = 1e-3;

    // Collect visible exposed faces, in parallel over x slices (order kept: C order).
    let quads: Vec<Quad> = (0..nx)
        .into_par_iter()
        .flat_map_iter(|i| {
            let mut out = Vec::new();
            for j in 0..ny {
                for k in 0..nz {
                    let c = labels[(i * ny + j) * nz + k];
                    if !drawn(c, empty, ignore) {
                        continue;
                    }
                    let base = if opts.color_by_height {
                        height_color((k as f32 + 0.5) / nz as f32)
                    } else {
                        lut[c as usize]
                    };
                    for (d, dir) in DIRS.iter().enumerate() {
                        if !faces_camera(d, i, j, k) {
                            continue;
                        }
                        let (ni, nj, nk) =
                            (i as i64 + dir[0], j as i64 + dir[1], k as i64 + dir[2]);
                        let inside = ni >= 0
                            && nj >= 0
                            && nk >= 0
                            && (ni as usize) < nx
                            && (nj as usize) < ny
                            && (nk as usize) < nz;
                        if inside {
                            let nc = labels[((ni as usize) * ny + nj as usize) * nz + nk as usize];
                            if drawn(nc, empty, ignore) {
                                continue;
                            }
                        }
                        let mut pts = [[0.0f32; 2]; 4];
                        let mut invd = [0.0f32; 4];
                        let mut ok = true;
                        for (q, off) in face_corners(d).iter().enumerate() {
                            match lattice.project(
                                i as f64 + off[0],
                                j as f64 + off[1],
                                k as f64 + off[2],
                                near,
                            ) {
                                Some(p) => {
                                    pts[q] =
                                        [(p[0] - vp.x as f64) as f32, (p[1] - vp.y as f64) as f32];
                                    invd[q] = (1.0 / p[2]) as f32;
                                }
                                None => ok = false,
                            }
                        }
                        if !ok {
                            continue;
                        }
                        let (mut x0, mut x1, mut y0, mut y1) =
                            (f32::MAX, f32::MIN, f32::MAX, f32::MIN);
                        for p in &pts {
                            x0 = x0.min(p[0]);
                            x1 = x1.max(p[0]);
                            y0 = y0.min(p[1]);
                            y1 = y1.max(p[1]);
                        }
                        // Off-screen, or too thin to contain a pixel centre.
                        if x1 < 0.0
                            || y1 < 0.0
                            || x0 > vp.width as f32
                            || y0 > vp.height as f32
                            || (x0 - 1e-4).ceil() > (x1 + 1e-4).floor()
                            || (y0 - 1e-4).ceil() > (y1 + 1e-4).floor()
                        {
                            continue;
                        }
                        out.push(Quad {
                            pts,
                            inv_depth: invd,
                            color: shade(base, shades[d]),
                        });
                    }
                }
            }
            out
        })
        .collect();

    // Bin faces into bands of rows (face indices stay in C order within a band).
    let mut scene = Canvas::new(vp.width, vp.height, opts.background);
    let width = vp.width;
    if width == 0 || vp.height == 0 {
        return scene;
    }
    let band_rows = (vp.height / (4 * rayon::current_num_threads().max(1))).clamp(8, 64);
    let n_bands = vp.height.div_ceil(band_rows);
    let mut bins: Vec<Vec<u32>> = vec![Vec::new(); n_bands];
    for (qi, q) in quads.iter().enumerate() {
        let (y0, y1) = q
            .pts
            .iter()
            .fold((f32::MAX, f32::MIN), |(a, b), p| (a.min(p[1]), b.max(p[1])));
        let b0 = (y0.max(0.0) as usize / band_rows).min(n_bands - 1);
        let b1 = (y1.max(0.0) as usize / band_rows).min(n_bands - 1);
        for bin in &mut bins[b0..=b1] {
            bin.push(qi as u32);
        }
    }
    scene
        .data
        .par_chunks_mut(band_rows * width * 3)
        .zip(bins.par_iter())
        .enumerate()
        .for_each(|(b, (chunk, bin))| {
            let row0 = b * band_rows;
            let rows = chunk.len() / (width * 3);
            let row1 = row0 + rows;
            let mut zbuf = vec![0.0f32; rows * width];
            for &qi in bin {
                let q = &quads[qi as usize];
                let Some(poly) = ConvexPoly::new(&q.pts) else {
                    continue;
                };
                let Some(plane) = AffinePlane::fit(&q.pts, &q.inv_depth) else {
                    continue;
                };
                let outline = poly.min_edge_len() >= 7.0;
                let outline_color = shade(q.color, 0.72);
                poly.for_each_pixel(row0, row1, width, |x, y, dist| {
                    let z = plane.at(x as f32, y as f32);
                    let zi = (y - row0) * width + x;
                    if z > zbuf[zi] {
                        zbuf[zi] = z;
                        let col = if outline && dist < 0.8 {
                            outline_color
                        } else {
                            q.color
                        };
                        chunk[zi * 3..zi * 3 + 3].copy_from_slice(&col);
                    }
                });
            }
        });
    scene
}

fn sub(a: [f64; 3], b: [f64; 3]) -> [f64; 3] {
    [a[0] - b[0], a[1] - b[1], a[2] - b[2]]
}
fn dot(a: [f64; 3], b: [f64; 3]) -> f64 {
    a[0] * b[0] + a[1] * b[1] + a[2] * b[2]
}
fn cross(a: [f64; 3], b: [f64; 3]) -> [f64; 3] {
    [
        a[1] * b[2] - a[2] * b[1],
        a[2] * b[0] - a[0] * b[2],
        a[0] * b[1] - a[1] * b[0],
    ]
}
fn normalize(a: [f64; 3]) -> [f64; 3] {
    let n = dot(a, a).sqrt();
    [a[0] / n, a[1] / n, a[2] / n]
}
