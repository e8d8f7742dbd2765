//! The panel images `viz`, `infer` and `demo` write: the camera image with the voxels drawn over it,
//! the prediction and the ground truth, side by side.

use crate::labels_io::LabelGrid;
use anyhow::{Context, Result};
use occ_data::formats::semantic_kitti as sk;
use occ_data::image::{read_image, write_png, RgbImage};
use occ_viz::{overlay_on_image, render_voxels, side_by_side, OverlayOptions, RenderOptions};
use std::path::Path;

fn render(g: &LabelGrid, title: &str, height: usize) -> Result<RgbImage> {
    let mut o = RenderOptions::new(g.palette);
    o.height = height;
    o.width = height * 16 / 9;
    o.color_by_height = g.occupancy_only;
    o.legend = !g.occupancy_only;
    o.title = Some(title.to_string());
    Ok(render_voxels(&g.classes, &g.grid, &o)?)
}

/// Renders `labels` (and optionally `pred`, an image overlay) into `out`.
pub fn render_panels(
    labels: &LabelGrid,
    pred: Option<&LabelGrid>,
    image: Option<(&Path, &Path)>,
    out: &Path,
    height: usize,
) -> Result<()> {
    render_panel_set(Some(labels), pred, image, out, height)
}

/// Like [`render_panels`], with the ground truth optional (`infer` on unlabelled frames): camera
/// overlay of the prediction (or labels) | prediction | ground truth, whichever are given.
pub fn render_panel_set(
    labels: Option<&LabelGrid>,
    pred: Option<&LabelGrid>,
    image: Option<(&Path, &Path)>,
    out: &Path,
    height: usize,
) -> Result<()> {
    let mut panels: Vec<(String, RgbImage)> = Vec::new();
    let Some(shown) = pred.or(labels) else {
        anyhow::bail!("{}: nothing to render", out.display());
    };
    if let Some((img_p, calib_p)) = image {
        let calib = sk::read_calib(calib_p)?;
        // The header against the size limit and the calibration before decoding.
        let (w, h) = occ_data::image::read_image_size(img_p)?;
        occ_train::dataset::check_image_fits_calibration(img_p, w, h, calib_p, &calib)?;
        let img = read_image(img_p)?;
        let view = calib.camera_view(img.width, img.height);
        let mut oo = OverlayOptions::new(shown.palette);
        oo.color_by_height = shown.occupancy_only;
        let ov = overlay_on_image(
            &img,
            &shown.classes,
            &shown.grid,
            &view.img_from_lidar(),
            &oo,
        )?;
        panels.push(("camera".into(), ov));
    }
    if let Some(p) = pred {
        panels.push(("prediction".into(), render(p, "prediction", height)?));
    }
    if let Some(l) = labels {
        panels.push((l.title.to_string(), render(l, l.title, height)?));
    }
    let refs: Vec<(&str, &RgbImage)> = panels.iter().map(|(n, i)| (n.as_str(), i)).collect();
    let img = if refs.len() == 1 {
        refs[0].1.clone()
    } else {
        side_by_side(&refs)?
    };
    if let Some(dir) = out.parent() {
        if !dir.as_os_str().is_empty() {
            std::fs::create_dir_all(dir).with_context(|| format!("creating {}", dir.display()))?;
        }
    }
    write_png(out, &img)?;
    Ok(())
}
