//! A minimal RGB8 drawing surface used by all renderers (rectangles, blending, blitting,
//! bilinear resizing), converted to and from `occ_data::image::RgbImage` at the API boundary.

/// An RGB8 image, row-major, 3 bytes per pixel, origin at the top-left.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct Canvas {
    /// Width in pixels.
    pub width: usize,
    /// Height in pixels.
    pub height: usize,
    /// `width * height * 3` bytes.
    pub data: Vec<u8>,
}

impl Canvas {
    /// A `width` x `height` canvas filled with `color`.
    pub fn new(width: usize, height: usize, color: [u8; 3]) -> Self {
        let mut data = Vec::with_capacity(width * height * 3);
        for _ in 0..width * height {
            data.extend_from_slice(&color);
        }
        Canvas {
            width,
            height,
            data,
        }
    }

    /// Pixel at (`x`, `y`); black outside the canvas.
    pub fn get(&self, x: usize, y: usize) -> [u8; 3] {
        if x >= self.width || y >= self.height {
            return [0, 0, 0];
        }
        let i = (y * self.width + x) * 3;
        [self.data[i], self.data[i + 1], self.data[i + 2]]
    }

    /// Set pixel (`x`, `y`); ignored outside the canvas.
    pub fn set(&mut self, x: usize, y: usize, color: [u8; 3]) {
        if x >= self.width || y >= self.height {
            return;
        }
        let i = (y * self.width + x) * 3;
        self.data[i..i + 3].copy_from_slice(&color);
    }

    /// Fill the rectangle with top-left (`x`, `y`) and size `w` x `h`, clipped to the canvas.
    pub fn fill_rect(&mut self, x: i64, y: i64, w: i64, h: i64, color: [u8; 3]) {
        let x0 = x.max(0);
        let y0 = y.max(0);
        let x1 = (x + w).min(self.width as i64);
        let y1 = (y + h).min(self.height as i64);
        for yy in y0..y1 {
            for xx in x0..x1 {
                self.set(xx as usize, yy as usize, color);
            }
        }
    }

    /// Outline (1 px) of the rectangle with top-left (`x`, `y`) and size `w` x `h`.
    pub fn stroke_rect(&mut self, x: i64, y: i64, w: i64, h: i64, color: [u8; 3]) {
        self.fill_rect(x, y, w, 1, color);
        self.fill_rect(x, y + h - 1, w, 1, color);
        self.fill_rect(x, y, 1, h, color);
        self.fill_rect(x + w - 1, y, 1, h, color);
    }

    /// A line from `a` to `b` (pixel coordinates, centre of pixel `x` at `x`), `thick` pixels
    /// wide (a square brush), clipped to the canvas.
    pub fn draw_line(&mut self, a: [f64; 2], b: [f64; 2], color: [u8; 3], thick: usize) {
        if !(a.iter().chain(&b).all(|v| v.is_finite())) {
            return;
        }
        // Clip the parameter range to the canvas (plus the brush) so that a far endpoint does
        // not cost a step per pixel outside.
        let pad = thick as f64 + 1.0;
        let (mut t0, mut t1) = (0.0f64, 1.0f64);
        for (p, q, lo, hi) in [
            (a[0], b[0] - a[0], -pad, self.width as f64 + pad),
            (a[1], b[1] - a[1], -pad, self.height as f64 + pad),
        ] {
            if q.abs() < 1e-12 {
                if p < lo || p > hi {
                    return;
                }
                continue;
            }
            let (ta, tb) = ((lo - p) / q, (hi - p) / q);
            t0 = t0.max(ta.min(tb));
            t1 = t1.min(ta.max(tb));
        }
        if t0 > t1 {
            return;
        }
        let pa = [a[0] + (b[0] - a[0]) * t0, a[1] + (b[1] - a[1]) * t0];
        let pb = [a[0] + (b[0] - a[0]) * t1, a[1] + (b[1] - a[1]) * t1];
        let steps = ((pb[0] - pa[0]).abs().max((pb[1] - pa[1]).abs()).ceil() as usize).max(1);
        let r0 = -((thick.max(1) as i64 - 1) / 2);
        let r1 = thick.max(1) as i64 / 2;
        for s in 0..=steps {
            let t = s as f64 / steps as f64;
            let x = (pa[0] + (pb[0] - pa[0]) * t).round() as i64;
            let y = (pa[1] + (pb[1] - pa[1]) * t).round() as i64;
            for dy in r0..=r1 {
                for dx in r0..=r1 {
                    let (xx, yy) = (x + dx, y + dy);
                    if xx >= 0 && yy >= 0 {
                        self.set(xx as usize, yy as usize, color);
                    }
                }
            }
        }
    }

    /// A filled disc of radius `r` pixels centred on pixel (`x`, `y`), clipped to the canvas.
    pub fn fill_disc(&mut self, x: i64, y: i64, r: usize, color: [u8; 3]) {
        let r = r as i64;
        for dy in -r..=r {
            let yy = y + dy;
            if yy < 0 || yy >= self.height as i64 {
                continue;
            }
            for dx in -r..=r {
                let xx = x + dx;
                if xx < 0 || xx >= self.width as i64 || dx * dx + dy * dy > r * r + r {
                    continue;
                }
                let i = (yy as usize * self.width + xx as usize) * 3;
                self.data[i..i + 3].copy_from_slice(&color);
            }
        }
    }

    /// Copy `src` with its top-left at (`x`, `y`), clipped to this canvas.
    pub fn blit(&mut self, src: &Canvas, x: i64, y: i64) {
        for sy in 0..src.height {
            let dy = y + sy as i64;
            if dy < 0 || dy >= self.height as i64 {
                continue;
            }
            let sx0 = (-x).max(0) as usize;
            let dx0 = (x + sx0 as i64) as usize;
            if sx0 >= src.width || dx0 >= self.width {
                continue;
            }
            let n = (src.width - sx0).min(self.width - dx0);
            let s = (sy * src.width + sx0) * 3;
            let d = (dy as usize * self.width + dx0) * 3;
            self.data[d..d + n * 3].copy_from_slice(&src.data[s..s + n * 3]);
        }
    }

    /// Bilinear resize to `width` x `height` (pixel-centre aligned). Sizes of 0 give an empty
    /// canvas.
    pub fn resized(&self, width: usize, height: usize) -> Canvas {
        let mut out = Canvas::new(width, height, [0, 0, 0]);
        if self.width == 0 || self.height == 0 || width == 0 || height == 0 {
            return out;
        }
        if width == self.width && height == self.height {
            return self.clone();
        }
        let sx = self.width as f64 / width as f64;
        let sy = self.height as f64 / height as f64;
        for y in 0..height {
            let fy = ((y as f64 + 0.5) * sy - 0.5).clamp(0.0, (self.height - 1) as f64);
            let y0 = fy.floor() as usize;
            let y1 = (y0 + 1).min(self.height - 1);
            let wy = fy - y0 as f64;
            for x in 0..width {
                let fx = ((x as f64 + 0.5) * sx - 0.5).clamp(0.0, (self.width - 1) as f64);
                let x0 = fx.floor() as usize;
                let x1 = (x0 + 1).min(self.width - 1);
                let wx = fx - x0 as f64;
                let (a, b, c, d) = (
                    self.get(x0, y0),
                    self.get(x1, y0),
                    self.get(x0, y1),
                    self.get(x1, y1),
                );
                let mut px = [0u8; 3];
                for k in 0..3 {
                    let top = a[k] as f64 * (1.0 - wx) + b[k] as f64 * wx;
                    let bot = c[k] as f64 * (1.0 - wx) + d[k] as f64 * wx;
                    px[k] = (top * (1.0 - wy) + bot * wy).round().clamp(0.0, 255.0) as u8;
                }
                out.set(x, y, px);
            }
        }
        out
    }
}

/// `dst` blended towards `src` by `alpha` in [0, 1] (0 keeps `dst`).
#[inline]
pub fn blend(dst: [u8; 3], src: [u8; 3], alpha: f32) -> [u8; 3] {
    let a = alpha.clamp(0.0, 1.0);
    let mut out = [0u8; 3];
    for k in 0..3 {
        out[k] = (dst[k] as f32 * (1.0 - a) + src[k] as f32 * a).round() as u8;
    }
    out
}

/// `color` multiplied by `factor` (clamped to 0..=255).
#[inline]
pub fn shade(color: [u8; 3], factor: f32) -> [u8; 3] {
    let mut out = [0u8; 3];
    for k in 0..3 {
        out[k] = (color[k] as f32 * factor).round().clamp(0.0, 255.0) as u8;
    }
    out
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn fill_and_blit_clip_to_bounds() {
        let mut c = Canvas::new(4, 3, [1, 2, 3]);
        c.fill_rect(-2, 2, 10, 5, [9, 9, 9]);
        assert_eq!(c.get(0, 2), [9, 9, 9]);
        assert_eq!(c.get(3, 2), [9, 9, 9]);
        assert_eq!(c.get(3, 1), [1, 2, 3]);
        let src = Canvas::new(3, 3, [7, 7, 7]);
        c.blit(&src, 2, -1);
        assert_eq!(c.get(1, 0), [1, 2, 3]);
        assert_eq!(c.get(2, 0), [7, 7, 7]);
        assert_eq!(c.get(3, 1), [7, 7, 7]);
        assert_eq!(c.get(2, 2), [9, 9, 9]);
    }

    #[test]
    fn resize_of_constant_is_constant_and_halving_averages() {
        let c = Canvas::new(5, 3, [10, 20, 30]);
        let r = c.resized(11, 7);
        assert!(r.data.chunks(3).all(|p| p == [10, 20, 30]));
        // Two columns 0 and 200 shrunk to one pixel: bilinear at the midpoint gives 100.
        let mut two = Canvas::new(2, 1, [0, 0, 0]);
        two.set(1, 0, [200, 200, 200]);
        assert_eq!(two.resized(1, 1).get(0, 0), [100, 100, 100]);
    }

    #[test]
    fn lines_and_discs_cover_their_pixels_and_clip() {
        let mut c = Canvas::new(10, 6, [0, 0, 0]);
        c.draw_line([1.0, 2.0], [8.0, 2.0], [255, 0, 0], 1);
        for x in 0..10 {
            let want = if (1..=8).contains(&x) {
                [255, 0, 0]
            } else {
                [0, 0, 0]
            };
            assert_eq!(c.get(x, 2), want, "x {x}");
        }
        assert_eq!(c.get(4, 1), [0, 0, 0]);
        // A diagonal far outside on both ends is clipped, not walked pixel by pixel.
        c.draw_line([-1e9, -1e9], [1e9, 1e9], [0, 255, 0], 1);
        assert_eq!(c.get(3, 3), [0, 255, 0]);
        assert_eq!(c.get(5, 5), [0, 255, 0]);
        c.draw_line([f64::NAN, 0.0], [3.0, 3.0], [9, 9, 9], 1);
        let mut d = Canvas::new(9, 9, [0, 0, 0]);
        d.fill_disc(4, 4, 2, [1, 1, 1]);
        let n = d.data.chunks(3).filter(|p| p == &[1, 1, 1]).count();
        assert_eq!(n, 21, "radius-2 disc");
        assert_eq!(d.get(4, 2), [1, 1, 1]);
        assert_eq!(d.get(2, 2), [0, 0, 0]);
        d.fill_disc(-1, 0, 1, [2, 2, 2]);
        assert_eq!(d.get(0, 0), [2, 2, 2]);
    }

    #[test]
    fn blend_and_shade() {
        assert_eq!(blend([0, 100, 200], [200, 100, 0], 0.5), [100, 100, 100]);
        assert_eq!(blend([5, 5, 5], [250, 250, 250], 0.0), [5, 5, 5]);
        assert_eq!(shade([100, 200, 250], 0.5), [50, 100, 125]);
        assert_eq!(shade([200, 200, 200], 2.0), [255, 255, 255]);
    }
}
