//! Side-by-side panels (e.g. camera image | prediction | ground truth), scaled to one height and
//! labelled.

use crate::RgbImage;

use crate::canvas::Canvas;
use crate::font::{draw_text, text_height, text_width};
use crate::render::MAX_PIXELS;
use crate::{canvas_to_image, image_to_canvas, VizError};

/// Height of the label strip above each panel.
pub const LABEL_STRIP_H: usize = crate::font::LINE_H * 2 + 10;
/// Gap between panels and around the border.
pub const PANEL_GAP: usize = 8;
const BG: [u8; 3] = [40, 40, 40];
const LABEL_COLOR: [u8; 3] = [240, 240, 240];

/// The panels' images as canvases; an error names the first empty one.
fn panel_canvases(panels: &[(&str, &RgbImage)]) -> Result<Vec<Canvas>, VizError> {
    panels
        .iter()
        .map(|(label, img)| {
            let c = image_to_canvas(img)?;
            if c.width == 0 || c.height == 0 {
                return Err(VizError::InvalidOptions(format!(
                    "panel {label:?} is empty"
                )));
            }
            Ok(c)
        })
        .collect()
}

/// Lay `panels` out row by row in a grid of `columns` columns (the last row may be short), each
/// scaled (bilinear, aspect kept) to the width of the widest one and centred in a cell as tall
/// as the tallest scaled panel, with its label centred in a strip above it. The same border,
/// gaps and label strips as [`side_by_side`]. Errors on an empty list, `columns` of 0 or an
/// empty/invalid panel.
pub fn panel_grid(panels: &[(&str, &RgbImage)], columns: usize) -> Result<RgbImage, VizError> {
    if panels.is_empty() || columns == 0 {
        return Err(VizError::InvalidOptions(format!(
            "panel_grid needs at least one panel and one column (got {} panels, {columns} columns)",
            panels.len()
        )));
    }
    let canvases = panel_canvases(panels)?;
    let cell_w = canvases.iter().map(|c| c.width).max().unwrap_or(1);
    let heights: Vec<usize> = canvases
        .iter()
        .map(|c| ((c.height as f64 * cell_w as f64 / c.width as f64).round() as usize).max(1))
        .collect();
    let cell_h = heights.iter().copied().max().unwrap_or(1);
    let cols = columns.min(panels.len());
    let rows = panels.len().div_ceil(cols);
    let total_w = cols as f64 * (cell_w + PANEL_GAP) as f64 + PANEL_GAP as f64;
    let total_h = rows as f64 * (cell_h + LABEL_STRIP_H + PANEL_GAP) as f64 + PANEL_GAP as f64;
    if total_w * total_h > MAX_PIXELS as f64 {
        return Err(VizError::InvalidOptions(format!(
            "panel grid of {total_w}x{total_h} would exceed {MAX_PIXELS} pixels"
        )));
    }
    let mut out = Canvas::new(total_w as usize, total_h as usize, BG);
    for (n, (((label, _), c), &h)) in panels.iter().zip(&canvases).zip(&heights).enumerate() {
        let (r, col) = (n / cols, n % cols);
        let x = PANEL_GAP + col * (cell_w + PANEL_GAP);
        let y = PANEL_GAP + r * (cell_h + LABEL_STRIP_H + PANEL_GAP);
        let tw = text_width(label, 2);
        let tx = x as i64 + (cell_w as i64 - tw as i64) / 2;
        let ty = y + (LABEL_STRIP_H - text_height(2)) / 2;
        draw_text(&mut out, tx.max(x as i64), ty as i64, label, 2, LABEL_COLOR);
        let scaled = c.resized(cell_w, h);
        out.blit(
            &scaled,
            x as i64,
            (y + LABEL_STRIP_H + (cell_h - h) / 2) as i64,
        );
    }
    Ok(canvas_to_image(out))
}

/// Place `panels` left to right, each scaled (bilinear, aspect kept) to the height of the
/// tallest one, with its label centred in a strip above it.
///
/// Layout: a `PANEL_GAP` border, panels separated by `PANEL_GAP`, label strips of
/// `LABEL_STRIP_H` rows. Errors on an empty list or an empty/invalid panel.
pub fn side_by_side(panels: &[(&str, &RgbImage)]) -> Result<RgbImage, VizError> {
    if panels.is_empty() {
        return Err(VizError::InvalidOptions(
            "side_by_side needs at least one panel".into(),
        ));
    }
    let canvases = panel_canvases(panels)?;
    let target_h = canvases.iter().map(|c| c.height).max().unwrap_or(1);
    let widths: Vec<f64> = canvases
        .iter()
        .map(|c| {
            (c.width as f64 * target_h as f64 / c.height as f64)
                .round()
                .max(1.0)
        })
        .collect();
    let total_w_f = widths.iter().sum::<f64>() + (PANEL_GAP * (canvases.len() + 1)) as f64;
    let total_h = target_h + LABEL_STRIP_H + 2 * PANEL_GAP;
    if total_w_f * total_h as f64 > MAX_PIXELS as f64 {
        return Err(VizError::InvalidOptions(format!(
            "side-by-side image of {total_w_f}x{total_h} would exceed {MAX_PIXELS} pixels"
        )));
    }
    let scaled: Vec<Canvas> = canvases
        .iter()
        .zip(&widths)
        .map(|(c, &w)| c.resized(w as usize, target_h))
        .collect();
    let total_w = total_w_f as usize;
    let mut out = Canvas::new(total_w, total_h, BG);
    let mut x = PANEL_GAP;
    for ((label, _), c) in panels.iter().zip(&scaled) {
        let tw = text_width(label, 2);
        let tx = x as i64 + (c.width as i64 - tw as i64) / 2;
        let ty = PANEL_GAP + (LABEL_STRIP_H - text_height(2)) / 2;
        draw_text(&mut out, tx.max(x as i64), ty as i64, label, 2, LABEL_COLOR);
        out.blit(c, x as i64, (PANEL_GAP + LABEL_STRIP_H) as i64);
        x += c.width + PANEL_GAP;
    }
    Ok(canvas_to_image(out))
}
