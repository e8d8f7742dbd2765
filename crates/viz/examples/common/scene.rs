//! A procedural, driving-like SemanticKITTI label grid (road, sidewalks, terrain, buildings,
//! cars, trees, poles with signs, a fence, pedestrians), for the examples, benchmark and tests
//! of occ-viz. Shared by `#[path]` includes; not part of the library API.
//!
//! Designed for the 256x256x32 grid (0.2 m voxels, ego at x index 0, y index 128, ground at
//! z index 2 for origin z = -2.2 m); other dims are scaled proportionally.

#![allow(dead_code)]

use std::ops::Range;

use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;

/// SemanticKITTI learning classes (the scene uses car, person, road, sidewalk, building, fence,
/// vegetation, trunk, terrain, pole and traffic sign).
pub use occ_data::synthetic::classes as class;

struct Grid {
    dims: [usize; 3],
    labels: Vec<u8>,
    // Scale from the 256x256x32 design grid to `dims`.
    s: [f64; 3],
}

impl Grid {
    fn set(&mut self, i: i64, j: i64, k: i64, c: u8) {
        let [x, y, z] = self.dims;
        if i < 0 || j < 0 || k < 0 || i as usize >= x || j as usize >= y || k as usize >= z {
            return;
        }
        self.labels[(i as usize * y + j as usize) * z + k as usize] = c;
    }

    /// Fill the design-space box [i0, i1) x [j0, j1) x [k0, k1) with class `c`.
    fn fill(&mut self, i: Range<i64>, j: Range<i64>, k: Range<i64>, c: u8) {
        let m = |v: i64, a: usize| (v as f64 * self.s[a]).round() as i64;
        let (i0, i1, j0, j1) = (m(i.start, 0), m(i.end, 0), m(j.start, 1), m(j.end, 1));
        let (k0, k1) = (m(k.start, 2), m(k.end, 2));
        for i in i0..i1.max(i0 + 1) {
            for j in j0..j1.max(j0 + 1) {
                for k in k0..k1.max(k0 + 1) {
                    self.set(i, j, k, c);
                }
            }
        }
    }

    /// Fill a design-space ball.
    fn ball(&mut self, ci: i64, cj: i64, ck: i64, r: i64, c: u8) {
        for di in -r..=r {
            for dj in -r..=r {
                for dk in -r..=r {
                    if di * di + dj * dj + dk * dk <= r * r {
                        self.fill(
                            ci + di..ci + di + 1,
                            cj + dj..cj + dj + 1,
                            ck + dk..ck + dk + 1,
                            c,
                        );
                    }
                }
            }
        }
    }
}

/// A driving-like scene with `dims` voxels (C order [x][y][z]), deterministic for `seed`.
pub fn driving_scene(dims: [usize; 3], seed: u64) -> Vec<u8> {
    use class::*;
    let mut rng = ChaCha8Rng::seed_from_u64(seed);
    let mut g = Grid {
        dims,
        labels: vec![0; dims[0] * dims[1] * dims[2]],
        s: [
            dims[0] as f64 / 256.0,
            dims[1] as f64 / 256.0,
            dims[2] as f64 / 32.0,
        ],
    };
    let c = 128i64; // lateral centre (ego)
    let kg = 2i64; // ground layer
                   // Ground: road, raised sidewalks, terrain beyond.
    g.fill(0..256, 0..256, kg..kg + 1, TERRAIN);
    g.fill(0..256, c - 35..c + 35, kg..kg + 1, ROAD);
    for side in [-1i64, 1] {
        let (a, b) = if side < 0 {
            (c - 48, c - 35)
        } else {
            (c + 35, c + 48)
        };
        g.fill(0..256, a..b, kg..kg + 2, SIDEWALK);
    }
    // Buildings on both sides, with gaps.
    for side in [-1i64, 1] {
        let mut x = rng.random_range(5..25i64);
        while x < 250 {
            let len = rng.random_range(30..70i64);
            let setback = rng.random_range(58..72i64);
            let depth = rng.random_range(25..60i64);
            let height = rng.random_range(12..29i64);
            let (j0, j1) = if side < 0 {
                (c - setback - depth, c - setback)
            } else {
                (c + setback, c + setback + depth)
            };
            g.fill(x..x + len, j0..j1, kg + 1..kg + 1 + height, BUILDING);
            x += len + rng.random_range(8..22i64);
        }
    }
    // A fence along part of the left terrain strip.
    g.fill(120..200, c + 55..c + 56, kg + 1..kg + 6, FENCE);
    // Trees and poles along the sidewalks.
    for side in [-1i64, 1] {
        let mut x = rng.random_range(10..30i64);
        while x < 250 {
            let j = c + side * 51;
            g.fill(x..x + 2, j..j + 2, kg + 1..kg + 11, TRUNK);
            let r = rng.random_range(4..7i64);
            g.ball(x + 1, j + 1, kg + 11 + r - 1, r, VEGETATION);
            x += rng.random_range(30..50i64);
        }
        let mut x = rng.random_range(15..40i64);
        while x < 250 {
            let j = c + side * 46;
            g.fill(x..x + 1, j..j + 1, kg + 2..kg + 23, POLE);
            if rng.random_bool(0.5) {
                g.fill(x..x + 1, j - 1..j + 2, kg + 19..kg + 22, TRAFFIC_SIGN);
            }
            x += rng.random_range(35..60i64);
        }
    }
    // Cars in both lanes and parked along the kerb.
    for lane_j in [c - 28, c - 14, c + 6, c + 22] {
        let mut x = rng.random_range(8..30i64);
        while x < 240 {
            let (len, wid) = (rng.random_range(18..24i64), rng.random_range(8..10i64));
            g.fill(x..x + len, lane_j..lane_j + wid, kg + 1..kg + 5, CAR);
            g.fill(
                x + 4..x + len - 5,
                lane_j + 1..lane_j + wid - 1,
                kg + 5..kg + 8,
                CAR,
            );
            x += len + rng.random_range(15..60i64);
        }
    }
    // Pedestrians on the sidewalks.
    for _ in 0..6 {
        let x = rng.random_range(20..240i64);
        let j = if rng.random_bool(0.5) { c - 42 } else { c + 40 };
        g.fill(x..x + 2, j..j + 2, kg + 2..kg + 11, PERSON);
    }
    g.labels
}
