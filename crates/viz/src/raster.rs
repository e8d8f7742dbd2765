//! Scan conversion shared by the voxel renderer and the camera overlay: convex polygons over a
//! band of image rows, with edge distances (for outlines) and an affine per-pixel attribute
//! (inverse depth, which is affine in screen space for a planar face under perspective).

/// A convex polygon prepared for scan conversion (at most 8 vertices).
#[derive(Debug, Clone, Copy)]
pub struct ConvexPoly {
    n: usize,
    pts: [[f32; 2]; 8],
    /// Edge functions `a*x + b*y + c`, oriented so that the inside is >= 0, normalised so the
    /// value is the signed distance in pixels.
    edges: [[f32; 3]; 8],
    /// Bounding box (inclusive pixel rows/cols that may hold a pixel centre inside).
    pub x_min: f32,
    pub x_max: f32,
    pub y_min: f32,
    pub y_max: f32,
}

impl ConvexPoly {
    /// Prepare the polygon with vertices `pts` (either winding). Returns `None` for fewer than
    /// 3 vertices, more than 8, non-finite coordinates, or (near) zero area.
    pub fn new(pts: &[[f32; 2]]) -> Option<ConvexPoly> {
        let n = pts.len();
        if !(3..=8).contains(&n) || pts.iter().any(|p| !p[0].is_finite() || !p[1].is_finite()) {
            return None;
        }
        let mut area2 = 0.0f32;
        for i in 0..n {
            let p = pts[i];
            let q = pts[(i + 1) % n];
            area2 += p[0] * q[1] - q[0] * p[1];
        }
        if area2.abs() < 1e-6 {
            return None;
        }
        let sign = area2.signum();
        let mut poly = ConvexPoly {
            n,
            pts: [[0.0; 2]; 8],
            edges: [[0.0; 3]; 8],
            x_min: f32::INFINITY,
            x_max: f32::NEG_INFINITY,
            y_min: f32::INFINITY,
            y_max: f32::NEG_INFINITY,
        };
        for i in 0..n {
            let p = pts[i];
            let q = pts[(i + 1) % n];
            poly.pts[i] = p;
            // E(x, y) = (q - p) x ((x, y) - p), positive inside for counter-clockwise (area > 0)
            // in a y-down frame's algebra; `sign` fixes the orientation either way.
            let a = -(q[1] - p[1]);
            let b = q[0] - p[0];
            let len = (a * a + b * b).sqrt();
            let inv = if len > 0.0 { sign / len } else { 0.0 };
            let c = -(a * p[0] + b * p[1]);
            poly.edges[i] = [a * inv, b * inv, c * inv];
            poly.x_min = poly.x_min.min(p[0]);
            poly.x_max = poly.x_max.max(p[0]);
            poly.y_min = poly.y_min.min(p[1]);
            poly.y_max = poly.y_max.max(p[1]);
        }
        Some(poly)
    }

    /// Length of the shortest edge in pixels.
    pub fn min_edge_len(&self) -> f32 {
        (0..self.n)
            .map(|i| {
                let p = self.pts[i];
                let q = self.pts[(i + 1) % self.n];
                ((q[0] - p[0]).powi(2) + (q[1] - p[1]).powi(2)).sqrt()
            })
            .fold(f32::INFINITY, f32::min)
    }

    /// Call `f(x, y, edge_dist_px)` for every pixel whose centre lies inside the polygon (edges
    /// inclusive), restricted to rows `row0..row1` and columns `0..width`. Pixel centres are at
    /// integer coordinates (the centre of pixel column `i` is `u = i`, as in `occ_geometry`);
    /// `edge_dist_px` is the distance from the pixel centre to the nearest edge.
    pub fn for_each_pixel(
        &self,
        row0: usize,
        row1: usize,
        width: usize,
        mut f: impl FnMut(usize, usize, f32),
    ) {
        const EPS: f32 = 1e-4;
        if width == 0 || row1 <= row0 {
            return;
        }
        let y_lo = ((self.y_min - EPS).ceil().max(row0 as f32)) as usize;
        let y_hi_f = (self.y_max + EPS).floor().min(row1 as f32 - 1.0);
        if y_hi_f < y_lo as f32 {
            return;
        }
        let y_hi = y_hi_f as usize;
        let x_lo = ((self.x_min - EPS).ceil().max(0.0)) as usize;
        let x_hi_f = (self.x_max + EPS).floor().min(width as f32 - 1.0);
        if x_hi_f < x_lo as f32 {
            return;
        }
        let x_hi = x_hi_f as usize;
        let edges = &self.edges[..self.n];
        for y in y_lo..=y_hi {
            let py = y as f32;
            // Find the span of x where all edge functions are >= 0 (convexity => one interval).
            let mut xa = x_lo as f32;
            let mut xb = x_hi as f32;
            for e in edges {
                let (a, b, c) = (e[0], e[1], e[2]);
                let r = b * py + c; // E = a*x + r
                if a.abs() < 1e-12 {
                    if r < -EPS {
                        xb = xa - 1.0;
                        break;
                    }
                } else if a > 0.0 {
                    xa = xa.max(-r / a);
                } else {
                    xb = xb.min(-r / a);
                }
            }
            if xb < xa {
                continue;
            }
            let xs = ((xa - EPS).ceil().max(x_lo as f32)) as usize;
            let xe_f = (xb + EPS).floor().min(x_hi as f32);
            if xe_f < xs as f32 {
                continue;
            }
            for x in xs..=xe_f as usize {
                let px = x as f32;
                let mut d = f32::INFINITY;
                for e in edges {
                    d = d.min(e[0] * px + e[1] * py + e[2]);
                }
                f(x, y, d.max(0.0));
            }
        }
    }
}

/// An affine function `w(x, y) = a*x + b*y + c` fitted through three of a polygon's vertices
/// (the best-conditioned triple), used for inverse depth.
#[derive(Debug, Clone, Copy)]
pub struct AffinePlane {
    a: f32,
    b: f32,
    c: f32,
}

impl AffinePlane {
    /// Fit through `pts[k]` with values `vals[k]`, choosing the triangle of largest area.
    /// `None` when all triangles are degenerate.
    pub fn fit(pts: &[[f32; 2]], vals: &[f32]) -> Option<AffinePlane> {
        let n = pts.len().min(vals.len());
        let mut best: Option<(f32, usize, usize, usize)> = None;
        for i in 0..n {
            for j in i + 1..n {
                for k in j + 1..n {
                    let det = (pts[j][0] - pts[i][0]) * (pts[k][1] - pts[i][1])
                        - (pts[k][0] - pts[i][0]) * (pts[j][1] - pts[i][1]);
                    if best.is_none_or(|(d, ..)| det.abs() > d) {
                        best = Some((det.abs(), i, j, k));
                    }
                }
            }
        }
        let (d, i, j, k) = best?;
        if d < 1e-9 {
            return None;
        }
        let (x0, y0, w0) = (pts[i][0], pts[i][1], vals[i]);
        let (x1, y1, w1) = (pts[j][0] - x0, pts[j][1] - y0, vals[j] - w0);
        let (x2, y2, w2) = (pts[k][0] - x0, pts[k][1] - y0, vals[k] - w0);
        let det = x1 * y2 - x2 * y1;
        let a = (w1 * y2 - w2 * y1) / det;
        let b = (x1 * w2 - x2 * w1) / det;
        let c = w0 - a * x0 - b * y0;
        Some(AffinePlane { a, b, c })
    }

    /// Value at (`x`, `y`).
    #[inline]
    pub fn at(&self, x: f32, y: f32) -> f32 {
        self.a * x + self.b * y + self.c
    }
}

/// Convex hull (Andrew's monotone chain) of up to 8 points, counter-clockwise in the usual
/// x-right/y-up algebra; collinear points dropped.
pub fn convex_hull(points: &[[f32; 2]]) -> Vec<[f32; 2]> {
    let mut p: Vec<[f32; 2]> = points.to_vec();
    p.sort_by(|a, b| a[0].total_cmp(&b[0]).then(a[1].total_cmp(&b[1])));
    p.dedup();
    if p.len() < 3 {
        return p;
    }
    let cross = |o: [f32; 2], a: [f32; 2], b: [f32; 2]| {
        (a[0] - o[0]) * (b[1] - o[1]) - (a[1] - o[1]) * (b[0] - o[0])
    };
    let mut hull: Vec<[f32; 2]> = Vec::with_capacity(2 * p.len());
    for &pt in &p {
        while hull.len() >= 2 && cross(hull[hull.len() - 2], hull[hull.len() - 1], pt) <= 0.0 {
            hull.pop();
        }
        hull.push(pt);
    }
    let lower_len = hull.len() + 1;
    for &pt in p.iter().rev().skip(1) {
        while hull.len() >= lower_len
            && cross(hull[hull.len() - 2], hull[hull.len() - 1], pt) <= 0.0
        {
            hull.pop();
        }
        hull.push(pt);
    }
    hull.pop();
    hull
}

#[cfg(test)]
mod tests {
    use super::*;

    fn covered(poly: &ConvexPoly, w: usize, h: usize) -> Vec<(usize, usize)> {
        let mut v = Vec::new();
        poly.for_each_pixel(0, h, w, |x, y, _| v.push((x, y)));
        v
    }

    /// Brute force: pixel centre inside (inclusive) by the edge functions of the raw vertices.
    fn brute(pts: &[[f32; 2]], w: usize, h: usize) -> Vec<(usize, usize)> {
        let n = pts.len();
        let mut area2 = 0.0;
        for i in 0..n {
            area2 += pts[i][0] * pts[(i + 1) % n][1] - pts[(i + 1) % n][0] * pts[i][1];
        }
        let s: f32 = if area2 > 0.0 { 1.0 } else { -1.0 };
        let mut v = Vec::new();
        for y in 0..h {
            for x in 0..w {
                let (px, py) = (x as f32, y as f32);
                let inside = (0..n).all(|i| {
                    let p = pts[i];
                    let q = pts[(i + 1) % n];
                    s * ((q[0] - p[0]) * (py - p[1]) - (q[1] - p[1]) * (px - p[0])) >= -1e-4
                });
                if inside {
                    v.push((x, y));
                }
            }
        }
        v
    }

    #[test]
    fn axis_aligned_square_covers_exact_pixels_either_winding() {
        let ccw = [[1.0, 1.0], [4.0, 1.0], [4.0, 3.0], [1.0, 3.0]];
        let mut cw = ccw;
        cw.reverse();
        for pts in [ccw, cw] {
            let poly = ConvexPoly::new(&pts).unwrap();
            let mut expect = Vec::new();
            for y in 1..=3 {
                for x in 1..=4 {
                    expect.push((x, y));
                }
            }
            assert_eq!(covered(&poly, 10, 10), expect);
        }
    }

    #[test]
    fn random_convex_polygons_match_brute_force() {
        // Deterministic pseudo-random quads from hulls of jittered points.
        let mut s = 12345u64;
        let mut rnd = || {
            s = s
                .wrapping_mul(6364136223846793005)
                .wrapping_add(1442695040888963407);
            ((s >> 33) as f32) / (1u64 << 31) as f32
        };
        let mut checked = 0;
        for _ in 0..200 {
            let pts: Vec<[f32; 2]> = (0..6)
                .map(|_| [rnd() * 30.0 - 5.0, rnd() * 20.0 - 3.0])
                .collect();
            let hull = convex_hull(&pts);
            let Some(poly) = ConvexPoly::new(&hull) else {
                continue;
            };
            let got = covered(&poly, 24, 16);
            let want = brute(&hull, 24, 16);
            // Pixel centres within 1e-4 of an edge may differ by rounding; require near-equality.
            let diff = got.iter().filter(|p| !want.contains(p)).count()
                + want.iter().filter(|p| !got.contains(p)).count();
            assert!(diff <= 1, "hull {hull:?}: {diff} pixels differ");
            checked += 1;
        }
        assert!(checked > 150);
    }

    #[test]
    fn band_rows_restrict_output_and_edge_distance_is_in_pixels() {
        let poly = ConvexPoly::new(&[[0.0, 0.0], [10.0, 0.0], [10.0, 10.0], [0.0, 10.0]]).unwrap();
        let mut rows = std::collections::BTreeSet::new();
        let mut centre_d = 0.0;
        poly.for_each_pixel(3, 5, 10, |x, y, d| {
            rows.insert(y);
            if (x, y) == (4, 4) {
                centre_d = d;
            }
        });
        assert_eq!(rows.into_iter().collect::<Vec<_>>(), vec![3, 4]);
        assert!((centre_d - 4.0).abs() < 1e-5, "{centre_d}");
    }

    #[test]
    fn affine_plane_reproduces_vertex_values() {
        let pts = [[0.0, 0.0], [4.0, 1.0], [5.0, 6.0], [1.0, 5.0]];
        // w = 0.5x - 0.25y + 2 is affine, so all four vertices must be reproduced.
        let vals: Vec<f32> = pts.iter().map(|p| 0.5 * p[0] - 0.25 * p[1] + 2.0).collect();
        let plane = AffinePlane::fit(&pts, &vals).unwrap();
        for (p, v) in pts.iter().zip(&vals) {
            assert!((plane.at(p[0], p[1]) - v).abs() < 1e-5);
        }
        assert!(
            AffinePlane::fit(&[[0.0, 0.0], [1.0, 1.0], [2.0, 2.0]], &[1.0, 2.0, 3.0]).is_none()
        );
    }

    #[test]
    fn hull_of_cube_corners_drops_interior_points() {
        let pts = [
            [0.0, 0.0],
            [2.0, 0.0],
            [2.0, 2.0],
            [0.0, 2.0],
            [1.0, 1.0],
            [1.0, 0.5],
        ];
        let hull = convex_hull(&pts);
        assert_eq!(hull.len(), 4);
        for c in [[0.0, 0.0], [2.0, 0.0], [2.0, 2.0], [0.0, 2.0]] {
            assert!(hull.contains(&c));
        }
        assert!(ConvexPoly::new(&[[0.0, 0.0], [1.0, 1.0], [2.0, 2.0]]).is_none());
    }
}
