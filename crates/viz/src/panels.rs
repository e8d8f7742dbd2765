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
    let mut canvases = Vec::with_capacity(panels.len());
    for (label, img) in panels {
        let c = image_to_canvas(img)?;
        if c.width == 0 || c.height == 0 {
            return Err(VizError::InvalidOptions(format!(
                "panel {label:?} is empty"
            )));
        }
        canvases.push(c);
    }
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
