//! Minimal line plots (benchmark scans: memory against grid size), drawn with the built-in font.

use crate::{draw_text, VizError};
use occ_data::image::RgbImage;

/// One line of a plot.
#[derive(Clone, Debug)]
pub struct Series {
    /// Legend label.
    pub name: String,
    /// Line colour.
    pub color: [u8; 3],
    /// Points `(x, y)`; drawn in the order given.
    pub points: Vec<(f64, f64)>,
}

/// A plot: title, axis labels, log-scaled x axis option.
#[derive(Clone, Debug)]
pub struct PlotSpec {
    /// Title above the plot.
    pub title: String,
    /// x axis label.
    pub x_label: String,
    /// y axis label.
    pub y_label: String,
    /// Use log10 on x.
    pub log_x: bool,
    /// Use log10 on y.
    pub log_y: bool,
    /// The lines.
    pub series: Vec<Series>,
}

fn put(img: &mut RgbImage, x: i64, y: i64, c: [u8; 3]) {
    if x >= 0 && y >= 0 && (x as usize) < img.width && (y as usize) < img.height {
        let i = (y as usize * img.width + x as usize) * 3;
        img.data[i..i + 3].copy_from_slice(&c);
    }
}

fn line(img: &mut RgbImage, a: (f64, f64), b: (f64, f64), c: [u8; 3], thick: i64) {
    let steps = ((b.0 - a.0).abs().max((b.1 - a.1).abs()).ceil() as usize).max(1);
    for s in 0..=steps {
        let t = s as f64 / steps as f64;
        let (x, y) = (a.0 + (b.0 - a.0) * t, a.1 + (b.1 - a.1) * t);
        for dx in -thick / 2..=thick / 2 {
            for dy in -thick / 2..=thick / 2 {
                put(img, x.round() as i64 + dx, y.round() as i64 + dy, c);
            }
        }
    }
}

fn fmt_tick(v: f64) -> String {
    let a = v.abs();
    if a >= 1e6 {
        format!("{:.1}M", v / 1e6)
    } else if a >= 1e3 {
        format!("{:.0}k", v / 1e3)
    } else if a >= 10.0 || v == 0.0 {
        format!("{v:.0}")
    } else {
        format!("{v:.2}")
    }
}

/// Renders `spec` into a `width x height` image (white background, axes with 5 ticks, legend).
pub fn line_plot(spec: &PlotSpec, width: usize, height: usize) -> Result<RgbImage, VizError> {
    let mut img = RgbImage {
        width,
        height,
        data: vec![255; width * height * 3],
    };
    let (left, right, top, bottom) = (90.0, 20.0, 40.0, 60.0);
    let (pw, ph) = (width as f64 - left - right, height as f64 - top - bottom);
    let tx = |v: f64, log: bool| if log { v.max(1e-12).log10() } else { v };
    let pts: Vec<(f64, f64)> = spec
        .series
        .iter()
        .flat_map(|s| s.points.iter().copied())
        .filter(|p| p.0.is_finite() && p.1.is_finite())
        .collect();
    let (mut x0, mut x1, mut y0, mut y1) = (f64::MAX, f64::MIN, f64::MAX, f64::MIN);
    for (x, y) in &pts {
        let (x, y) = (tx(*x, spec.log_x), tx(*y, spec.log_y));
        x0 = x0.min(x);
        x1 = x1.max(x);
        y0 = y0.min(y);
        y1 = y1.max(y);
    }
    if pts.is_empty() {
        (x0, x1, y0, y1) = (0.0, 1.0, 0.0, 1.0);
    }
    if !spec.log_y {
        y0 = y0.min(0.0);
    }
    if x1 - x0 < 1e-9 {
        x1 = x0 + 1.0;
    }
    if y1 - y0 < 1e-9 {
        y1 = y0 + 1.0;
    }
    y1 += (y1 - y0) * 0.08;
    let px = |x: f64| left + (tx(x, spec.log_x) - x0) / (x1 - x0) * pw;
    let py = |y: f64| top + ph - (tx(y, spec.log_y) - y0) / (y1 - y0) * ph;
    let axis = [60, 60, 60];
    line(&mut img, (left, top), (left, top + ph), axis, 1);
    line(&mut img, (left, top + ph), (left + pw, top + ph), axis, 1);
    for k in 0..=4 {
        let f = k as f64 / 4.0;
        let (vx, vy) = (x0 + (x1 - x0) * f, y0 + (y1 - y0) * f);
        let (gx, gy) = (left + pw * f, top + ph - ph * f);
        line(&mut img, (gx, top + ph), (gx, top + ph + 5.0), axis, 1);
        line(&mut img, (left - 5.0, gy), (left, gy), axis, 1);
        let lx = fmt_tick(if spec.log_x { 10f64.powf(vx) } else { vx });
        let ly = fmt_tick(if spec.log_y { 10f64.powf(vy) } else { vy });
        draw_text(
            &mut img,
            gx as i64 - 12,
            (top + ph + 10.0) as i64,
            &lx,
            2,
            axis,
        )?;
        draw_text(&mut img, 8, gy as i64 - 7, &ly, 2, axis)?;
    }
    draw_text(&mut img, left as i64, 10, &spec.title, 2, [0, 0, 0])?;
    draw_text(
        &mut img,
        (left + pw / 2.0 - 100.0) as i64,
        height as i64 - 24,
        &spec.x_label,
        2,
        axis,
    )?;
    draw_text(&mut img, 8, (top - 22.0) as i64, &spec.y_label, 2, axis)?;
    for (i, s) in spec.series.iter().enumerate() {
        for w in s.points.windows(2) {
            line(
                &mut img,
                (px(w[0].0), py(w[0].1)),
                (px(w[1].0), py(w[1].1)),
                s.color,
                3,
            );
        }
        for p in &s.points {
            let (cx, cy) = (px(p.0), py(p.1));
            for dx in -4..=4 {
                for dy in -4..=4 {
                    put(&mut img, cx as i64 + dx, cy as i64 + dy, s.color);
                }
            }
        }
        let ly = top as i64 + 10 + 22 * i as i64;
        let lx = (left + 20.0) as i64;
        for dx in 0..24 {
            for dy in 0..6 {
                put(&mut img, lx + dx, ly + 5 + dy, s.color);
            }
        }
        draw_text(&mut img, lx + 32, ly, &s.name, 2, [0, 0, 0])?;
    }
    Ok(img)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn points_land_where_the_axes_say() {
        let spec = PlotSpec {
            title: "t".into(),
            x_label: "x".into(),
            y_label: "y".into(),
            log_x: false,
            log_y: false,
            series: vec![Series {
                name: "a".into(),
                color: [255, 0, 0],
                points: vec![(0.0, 0.0), (1.0, 1.0)],
            }],
        };
        let img = line_plot(&spec, 400, 300).unwrap();
        // (0, 0) is the bottom-left corner of the plot area: left = 90, top + ph = 240.
        let i = (240 * 400 + 90) * 3;
        assert_eq!(&img.data[i..i + 3], &[255, 0, 0]);
        let red = img.data.chunks(3).filter(|p| p == &[255, 0, 0]).count();
        assert!(red > 200, "the line is drawn ({red} pixels)");
    }
}
