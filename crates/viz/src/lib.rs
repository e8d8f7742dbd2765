//! occ-viz: headless visualization of voxel label grids — no display, no GPU, no font files.
//!
//! - [`render_voxels`]: perspective render of a dense label grid (shaded cubes, z-buffer,
//!   legend, title), camera behind and above the ego.
//! - [`overlay_on_image`]: drawn voxels projected onto a camera image with `img_from_lidar`,
//!   depth-sorted and alpha-blended.
//! - [`side_by_side`]: labelled panels of equal height (image | prediction | ground truth);
//!   [`panel_grid`]: labelled panels in rows and columns.
//! - [`render_surround`]: a surround-camera frame: every camera of a rig with the LiDAR points
//!   (coloured by depth, [`project_points`]) and the voxels of a grid drawn over it, in a grid of
//!   panels beside a bird's-eye view with the camera frusta ([`bev_panel`]).
//! - [`write_ply`]: drawn voxels as a coloured PLY point cloud.
//! - [`Palette`]: SemanticKITTI (20 classes), Occ3D-nuScenes (18 incl. free) and
//!   nuScenes-Occupancy (17 incl. empty) names and colours; [`height_color`] ramp for
//!   occupancy-only grids.
//!
//! Label grids are `u8` per voxel in C order `[x][y][z]` (z fastest), `grid.num_voxels()` long
//! (docs/formats.md §1). Images are `occ_data::image::RgbImage` (re-exported as [`RgbImage`]); write
//! them with `occ_data::image::write_png`. An optional `rerun` streaming feature is not
//! implemented.

mod canvas;
mod font;
mod overlay;
mod palette;
mod panels;
pub mod plot;
mod ply;
mod raster;
mod render;
mod surround;

use std::fs::File;
use std::path::{Path, PathBuf};

pub use occ_data::image::RgbImage;
use occ_geometry::VoxelGrid;

pub use overlay::{overlay_on_image, OverlayOptions};
pub use palette::{depth_color, height_color, Palette, UNKNOWN_CLASS_RGB};
pub use panels::{panel_grid, side_by_side, LABEL_STRIP_H, PANEL_GAP};
pub use ply::{write_ply, PlyFormat, PlyOptions};
pub use render::{
    fit_camera, render_camera, render_voxels, render_voxels_from_view, RenderCamera, RenderOptions,
    Viewport, MAX_PIXELS,
};
pub use surround::{
    annotate_camera, bev_panel, default_columns, display_order, project_points, render_surround,
    ProjectedPoint, SurroundCamera, SurroundGrid, SurroundOptions, SurroundRender,
};

use canvas::Canvas;

/// Errors of this crate. Each names the file or the input that is wrong.
#[derive(Debug, thiserror::Error)]
pub enum VizError {
    /// The label array does not match the grid.
    #[error("label array has {got} voxels but the grid {dims:?} has {expected}")]
    LabelSize {
        /// `grid.num_voxels()`.
        expected: usize,
        /// `labels.len()`.
        got: usize,
        /// Grid dims.
        dims: [usize; 3],
    },
    /// The grid cannot be rendered (zero dims, bad voxel size or origin).
    #[error("invalid voxel grid: {0}")]
    InvalidGrid(String),
    /// An option or matrix is out of range.
    #[error("invalid visualization option: {0}")]
    InvalidOptions(String),
    /// An image given as input is inconsistent.
    #[error("invalid image: {0}")]
    InvalidImage(String),
    /// Writing or renaming an output file failed.
    #[error("cannot write {path}: {source}")]
    Io {
        /// The output path.
        path: PathBuf,
        /// The cause.
        #[source]
        source: std::io::Error,
    },
}

pub(crate) fn check_grid(grid: &VoxelGrid) -> Result<(), VizError> {
    if grid.dims.contains(&0) {
        return Err(VizError::InvalidGrid(format!(
            "dims {:?} contain a zero",
            grid.dims
        )));
    }
    if !(grid.voxel_size_m.is_finite() && grid.voxel_size_m > 0.0) {
        return Err(VizError::InvalidGrid(format!(
            "voxel size {} m is not a positive number",
            grid.voxel_size_m
        )));
    }
    if grid.origin_m.iter().any(|v| !v.is_finite()) {
        return Err(VizError::InvalidGrid(format!(
            "origin {:?} m is not finite",
            grid.origin_m
        )));
    }
    let n = grid.dims.iter().try_fold(1usize, |a, &d| a.checked_mul(d));
    if n.is_none_or(|n| n > u32::MAX as usize) {
        return Err(VizError::InvalidGrid(format!(
            "dims {:?} are too large",
            grid.dims
        )));
    }
    Ok(())
}

pub(crate) fn check_labels(labels: &[u8], grid: &VoxelGrid) -> Result<(), VizError> {
    let expected = grid.dims[0] * grid.dims[1] * grid.dims[2];
    if labels.len() != expected {
        return Err(VizError::LabelSize {
            expected,
            got: labels.len(),
            dims: grid.dims,
        });
    }
    Ok(())
}

pub(crate) fn canvas_to_image(c: Canvas) -> RgbImage {
    RgbImage {
        width: c.width,
        height: c.height,
        data: c.data,
    }
}

pub(crate) fn image_to_canvas(img: &RgbImage) -> Result<Canvas, VizError> {
    let (w, h) = (img.width, img.height);
    if w.checked_mul(h).and_then(|n| n.checked_mul(3)) != Some(img.data.len()) {
        return Err(VizError::InvalidImage(format!(
            "{}x{} RGB image has {} bytes, expected {}",
            w,
            h,
            img.data.len(),
            w.saturating_mul(h).saturating_mul(3)
        )));
    }
    Ok(Canvas {
        width: w,
        height: h,
        data: img.data.clone(),
    })
}

/// Create `path` through a fresh temporary file in the same folder, renamed into place only after
/// `write` succeeded (the temporary file is removed on failure): the project's one atomic writer,
/// [`occ_data::formats::io::write_atomic_io`].
pub(crate) fn write_atomically(
    path: &Path,
    write: impl FnOnce(&mut File) -> std::io::Result<()>,
) -> Result<(), VizError> {
    occ_data::formats::io::write_atomic_io(path, write).map_err(|source| VizError::Io {
        path: path.to_path_buf(),
        source,
    })
}

/// Draw `text` into `img` with the built-in 5x7 bitmap font (`A-Z a-z 0-9` and common
/// punctuation; other characters show as `?`), top-left corner at (`x`, `y`), each font pixel a
/// `scale` x `scale` block, clipped to the image. Returns the text width in pixels.
pub fn draw_text(
    img: &mut RgbImage,
    x: i64,
    y: i64,
    text: &str,
    scale: usize,
    color: [u8; 3],
) -> Result<usize, VizError> {
    let mut canvas = image_to_canvas(img)?;
    font::draw_text(&mut canvas, x, y, text, scale, color);
    img.data = canvas.data;
    Ok(font::text_width(text, scale))
}
