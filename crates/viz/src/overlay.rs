//! Camera overlay: occupied voxels projected onto the camera image.
//!
//! Each drawn voxel that is exposed to a not-drawn neighbour (interior voxels are hidden by
//! their neighbours anyway) is projected with `img_from_lidar`; its footprint is the convex
//! hull of its 8 projected corners, i.e. the exact silhouette of the projected cube. Voxels are
//! painted far to near (painter's algorithm; ties in depth broken by voxel index) with alpha
//! blending, so near structure ends on top. Voxels with any corner closer than `near_m` to the
//! camera plane are skipped.

use crate::RgbImage;
use occ_geometry::{Mat4, VoxelGrid};
use occ_labels::IGNORE;
use rayon::prelude::*;

use crate::canvas::{blend, shade, Canvas};
use crate::palette::{height_color, Palette};
use crate::raster::{convex_hull, ConvexPoly};
use crate::render::{drawn, RenderOptions};
use crate::{canvas_to_image, check_grid, check_labels, image_to_canvas, VizError};

/// Options of [`overlay_on_image`].
#[derive(Debug, Clone, PartialEq)]
pub struct OverlayOptions {
    /// Class palette.
    pub palette: Palette,
    /// Class id that is not drawn (free space).
    pub empty_class: u8,
    /// Class id that is not drawn (ignored/unknown).
    pub ignore_class: u8,
    /// Colour by voxel centre height instead of by class.
    pub color_by_height: bool,
    /// Opacity of each voxel footprint in [0, 1].
    pub alpha: f32,
    /// Voxels with a corner nearer than this (camera depth, metres) are skipped.
    pub near_m: f64,
    /// Voxels whose centre is farther than this (camera depth, metres) are skipped.
    pub max_depth_m: f64,
    /// Darken the border (0.75 px) of footprints at least 8 px across, so that individual
    /// voxels stay visible where they overlap.
    pub outline: bool,
    /// Paint each pixel once, with the nearest voxel that covers it (voxels sorted nearest
    /// first, a pixel already painted is kept), so the image stays visible through one
    /// semi-transparent layer; otherwise far to near, every footprint blended over the last.
    pub nearest_only: bool,
}

impl OverlayOptions {
    /// Palette defaults (empty class from the palette, ignore 255), alpha 0.5, near 0.5 m,
    /// no far limit.
    pub fn new(palette: Palette) -> Self {
        OverlayOptions {
            palette,
            empty_class: palette.default_empty_class(),
            ignore_class: IGNORE,
            color_by_height: false,
            alpha: 0.5,
            near_m: 0.5,
            max_depth_m: f64::INFINITY,
            outline: true,
            nearest_only: false,
        }
    }

    /// The class/colour settings of a [`RenderOptions`], other fields default.
    pub fn from_render(r: &RenderOptions) -> Self {
        OverlayOptions {
            empty_class: r.empty_class,
            ignore_class: r.ignore_class,
            color_by_height: r.color_by_height,
            ..OverlayOptions::new(r.palette)
        }
    }
}

/// One voxel footprint to paint.
struct Splat {
    depth: f64,
    index: usize,
    poly: ConvexPoly,
    color: [u8; 3],
    outline: bool,
}

/// Overlay the drawn voxels of `labels` on `img`, projecting with `img_from_lidar` (a 4x4
/// matrix: a 3x4 `P·Tr` padded with a last row `[0, 0, 0, 1]`; row 2 must give the depth,
/// as it does for `K·[R|t]`). Returns a new image of the same size.
pub fn overlay_on_image(
    img: &RgbImage,
    labels: &[u8],
    grid: &VoxelGrid,
    img_from_lidar: &Mat4,
    opts: &OverlayOptions,
) -> Result<RgbImage, VizError> {
    let mut canvas = image_to_canvas(img)?;
    overlay_canvas(&mut canvas, labels, grid, img_from_lidar, opts)?;
    Ok(canvas_to_image(canvas))
}

pub(crate) fn overlay_canvas(
    canvas: &mut Canvas,
    labels: &[u8],
    grid: &VoxelGrid,
    img_from_lidar: &Mat4,
    opts: &OverlayOptions,
) -> Result<(), VizError> {
    check_grid(grid)?;
    check_labels(labels, grid)?;
    if img_from_lidar.iter().flatten().any(|v| !v.is_finite()) {
        return Err(VizError::InvalidOptions(
            "img_from_lidar has a non-finite entry".to_string(),
        ));
    }
    if !(opts.near_m.is_finite() && opts.near_m >= 0.0) || opts.max_depth_m.is_nan() {
        return Err(VizError::InvalidOptions(format!(
            "overlay depth range near {} m .. max {} m is invalid",
            opts.near_m, opts.max_depth_m
        )));
    }
    if !(0.0..=1.0).contains(&opts.alpha) {
        return Err(VizError::InvalidOptions(format!(
            "overlay alpha {} is outside [0, 1]",
            opts.alpha
        )));
    }
    let [nx, ny, nz] = grid.dims;
    let (w, h) = (canvas.width, canvas.height);
    let (empty, ignore) = (opts.empty_class, opts.ignore_class);
    let lut = opts.palette.lut();
    let m = img_from_lidar;
    let o = grid.origin_m;
    let s = grid.voxel_size_m;
    let hom = |p: [f64; 3], r: usize| m[r][0] * p[0] + m[r][1] * p[1] + m[r][2] * p[2] + m[r][3];
    let is_drawn = |i: i64, j: i64, k: i64| -> bool {
        if i < 0 || j < 0 || k < 0 || i as usize >= nx || j as usize >= ny || k as usize >= nz {
            return false;
        }
        drawn(
            labels[((i as usize) * ny + j as usize) * nz + k as usize],
            empty,
            ignore,
        )
    };

    let mut splats: Vec<Splat> = (0..nx)
        .into_par_iter()
        .flat_map_iter(|i| {
            let mut out = Vec::new();
            for j in 0..ny {
                for k in 0..nz {
                    let index = (i * ny + j) * nz + k;
                    let c = labels[index];
                    if !drawn(c, empty, ignore) {
                        continue;
                    }
                    let (ii, jj, kk) = (i as i64, j as i64, k as i64);
                    let interior = is_drawn(ii - 1, jj, kk)
                        && is_drawn(ii + 1, jj, kk)
                        && is_drawn(ii, jj - 1, kk)
                        && is_drawn(ii, jj + 1, kk)
                        && is_drawn(ii, jj, kk - 1)
                        && is_drawn(ii, jj, kk + 1);
                    if interior {
                        continue;
                    }
                    let centre = [
                        o[0] + (i as f64 + 0.5) * s,
                        o[1] + (j as f64 + 0.5) * s,
                        o[2] + (k as f64 + 0.5) * s,
                    ];
                    let depth = hom(centre, 2);
                    if depth.is_nan() || depth > opts.max_depth_m {
                        continue;
                    }
                    let mut pts = [[0.0f32; 2]; 8];
                    let mut ok = true;
                    for (q, pt) in pts.iter_mut().enumerate() {
                        let p = [
                            o[0] + (i + (q & 1)) as f64 * s,
                            o[1] + (j + ((q >> 1) & 1)) as f64 * s,
                            o[2] + (k + ((q >> 2) & 1)) as f64 * s,
                        ];
                        let d = hom(p, 2);
                        if d.is_nan() || d <= opts.near_m {
                            ok = false;
                            break;
                        }
                        *pt = [(hom(p, 0) / d) as f32, (hom(p, 1) / d) as f32];
                    }
                    if !ok {
                        continue;
                    }
                    let hull = convex_hull(&pts);
                    let Some(poly) = ConvexPoly::new(&hull) else {
                        continue;
                    };
                    if poly.x_max < 0.0
                        || poly.y_max < 0.0
                        || poly.x_min > w as f32
                        || poly.y_min > h as f32
                    {
                        continue;
                    }
                    let color = if opts.color_by_height {
                        height_color((k as f32 + 0.5) / nz as f32)
                    } else {
                        lut[c as usize]
                    };
                    let outline = opts.outline
                        && (poly.x_max - poly.x_min).min(poly.y_max - poly.y_min) >= 8.0;
                    out.push(Splat {
                        depth,
                        index,
                        poly,
                        color,
                        outline,
                    });
                }
            }
            out
        })
        .collect();
    // Far first (near first for `nearest_only`); equal depths in voxel order (deterministic).
    if opts.nearest_only {
        splats.par_sort_unstable_by(|a, b| a.depth.total_cmp(&b.depth).then(a.index.cmp(&b.index)));
    } else {
        splats.par_sort_unstable_by(|a, b| b.depth.total_cmp(&a.depth).then(a.index.cmp(&b.index)));
    }
    let nearest_only = opts.nearest_only;

    if w == 0 || h == 0 {
        return Ok(());
    }
    let band_rows = (h / (4 * rayon::current_num_threads().max(1))).clamp(8, 64);
    let alpha = opts.alpha;
    canvas
        .data
        .par_chunks_mut(band_rows * w * 3)
        .enumerate()
        .for_each(|(b, chunk)| {
            let row0 = b * band_rows;
            let row1 = row0 + chunk.len() / (w * 3);
            let mut painted = vec![false; if nearest_only { chunk.len() / 3 } else { 0 }];
            for sp in &splats {
                if sp.poly.y_max < row0 as f32 || sp.poly.y_min > row1 as f32 {
                    continue;
                }
                let edge_color = shade(sp.color, 0.55);
                sp.poly.for_each_pixel(row0, row1, w, |x, y, dist| {
                    let p = (y - row0) * w + x;
                    if nearest_only {
                        if painted[p] {
                            return;
                        }
                        painted[p] = true;
                    }
                    let i = p * 3;
                    let dst = [chunk[i], chunk[i + 1], chunk[i + 2]];
                    let c = if sp.outline && dist < 0.75 {
                        edge_color
                    } else {
                        sp.color
                    };
                    chunk[i..i + 3].copy_from_slice(&blend(dst, c, alpha));
                });
            }
        });
    Ok(())
}
