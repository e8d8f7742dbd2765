//! Procedural street layout in metres, independent of the voxel size.
//!
//! World frame: x along the main road (the ego drives towards +x), y to the left, z up, with the
//! road surface at z = 0. The layout is a [`RoadPlan`] (a ground function giving class and surface
//! height for every (x, y) column: lanes, optional median, parking strips, sidewalks with curbs,
//! crossings with zebra stripes, and roadside zones) plus a list of [`Object`]s made of simple
//! solid primitives (boxes, vertical cylinders, ellipsoids): buildings, fences, trees, bushes,
//! poles, traffic signs and lights, parked and stopped vehicles, two-wheelers, riders and
//! pedestrians. The same seed gives the same layout at every voxel size.

use super::classes::*;
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;
use std::f64::consts::{FRAC_PI_2, PI};

/// Luminance factor of each 3-bit shade code stored with every voxel.
pub(crate) const SHADE_FACTOR: [f32; 8] = [1.0, 0.55, 0.72, 0.86, 1.14, 1.3, 1.6, 1.9];
pub(crate) const SH_NEUTRAL: u8 = 0;
pub(crate) const SH_DARK: u8 = 1;
pub(crate) const SH_DIM: u8 = 2;
pub(crate) const SH_SOFT: u8 = 3;
pub(crate) const SH_LIGHT: u8 = 4;
pub(crate) const SH_BRIGHT: u8 = 5;
pub(crate) const SH_MARK: u8 = 6;
pub(crate) const SH_WHITE: u8 = 7;

/// Curb height of sidewalks and medians above the road (m).
pub(crate) const CURB_H: f64 = 0.15;

/// Which dataset's object mix the world imitates.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub(crate) enum Style {
    /// SemanticKITTI (Karlsruhe): vans as other-vehicle, no cones/barriers.
    Kitti,
    /// nuScenes: buses, trailers, construction vehicles, barriers and traffic cones too.
    Nuscenes,
}

/// A solid primitive.
#[derive(Clone, Copy, Debug, PartialEq)]
pub(crate) enum Shape {
    /// Box with centre `c`, half extents `h` (local x along the heading), rotated by `yaw` about z.
    Box { c: [f64; 3], h: [f64; 3], yaw: f64 },
    /// Vertical cylinder with axis at `c`, radius `r`, from `z0` to `z1`.
    Cyl {
        c: [f64; 2],
        r: f64,
        z0: f64,
        z1: f64,
    },
    /// Axis-aligned ellipsoid.
    Ell { c: [f64; 3], r: [f64; 3] },
}

/// How the shade code varies over a primitive.
#[derive(Clone, Copy, Debug, PartialEq)]
pub(crate) enum Pattern {
    Solid,
    /// Building facade: dark windows on a floor grid.
    Facade {
        floor_h: f64,
        period: f64,
        win_w: f64,
        phase: f64,
    },
    /// Vegetation: a voxel is kept with probability `keep` (hashed on the voxel index).
    Porous {
        keep: f64,
    },
    /// Horizontal bands alternating white / base (cones, barriers).
    Stripes {
        period: f64,
    },
}

/// One primitive with its class and shade.
#[derive(Clone, Copy, Debug, PartialEq)]
pub(crate) struct Prim {
    pub shape: Shape,
    pub class: u8,
    pub shade: u8,
    pub pattern: Pattern,
}

impl Shape {
    /// Axis-aligned bounding box `(min, max)`.
    pub(crate) fn aabb(&self) -> ([f64; 3], [f64; 3]) {
        match *self {
            Shape::Box { c, h, yaw } => {
                let (s, co) = yaw.sin_cos();
                let ex = co.abs() * h[0] + s.abs() * h[1];
                let ey = s.abs() * h[0] + co.abs() * h[1];
                (
                    [c[0] - ex, c[1] - ey, c[2] - h[2]],
                    [c[0] + ex, c[1] + ey, c[2] + h[2]],
                )
            }
            Shape::Cyl { c, r, z0, z1 } => ([c[0] - r, c[1] - r, z0], [c[0] + r, c[1] + r, z1]),
            Shape::Ell { c, r } => (
                [c[0] - r[0], c[1] - r[1], c[2] - r[2]],
                [c[0] + r[0], c[1] + r[1], c[2] + r[2]],
            ),
        }
    }

    /// Whether point `p` lies inside (boundaries inclusive).
    pub(crate) fn contains(&self, p: [f64; 3]) -> bool {
        match *self {
            Shape::Box { c, h, yaw } => {
                let (s, co) = yaw.sin_cos();
                let (dx, dy) = (p[0] - c[0], p[1] - c[1]);
                let lx = co * dx + s * dy;
                let ly = -s * dx + co * dy;
                lx.abs() <= h[0] && ly.abs() <= h[1] && (p[2] - c[2]).abs() <= h[2]
            }
            Shape::Cyl { c, r, z0, z1 } => {
                p[2] >= z0 && p[2] <= z1 && (p[0] - c[0]).powi(2) + (p[1] - c[1]).powi(2) <= r * r
            }
            Shape::Ell { c, r } => {
                let q = [0, 1, 2].map(|a| (p[a] - c[a]) / r[a]);
                q[0] * q[0] + q[1] * q[1] + q[2] * q[2] <= 1.0
            }
        }
    }

    /// Points along the "skeleton" of the shape, spaced at most `step` apart: the axis of a
    /// cylinder, and for a box a lattice over its non-thin axes (thin axes, thinner than
    /// `2·step`, contribute only their centre). Rasterising these as well guarantees that thin
    /// parts (poles, sign plates, fences, bicycles) leave at least one voxel at any voxel size.
    pub(crate) fn skeleton(&self, step: f64) -> Vec<[f64; 3]> {
        let samples = |half: f64| -> Vec<f64> {
            if half * 2.0 < 2.0 * step {
                vec![0.0]
            } else {
                let n = ((2.0 * half) / step).ceil() as usize;
                (0..=n)
                    .map(|i| -half + 2.0 * half * i as f64 / n as f64)
                    .collect()
            }
        };
        match *self {
            Shape::Box { c, h, yaw } => {
                let (s, co) = yaw.sin_cos();
                let (xs, ys, zs) = (samples(h[0]), samples(h[1]), samples(h[2]));
                let mut out = Vec::with_capacity(xs.len() * ys.len() * zs.len());
                for &lx in &xs {
                    for &ly in &ys {
                        for &lz in &zs {
                            out.push([c[0] + co * lx - s * ly, c[1] + s * lx + co * ly, c[2] + lz]);
                        }
                    }
                }
                out
            }
            Shape::Cyl { c, z0, z1, .. } => samples(0.5 * (z1 - z0))
                .into_iter()
                .map(|dz| [c[0], c[1], 0.5 * (z0 + z1) + dz])
                .collect(),
            Shape::Ell { c, .. } => vec![c],
        }
    }

    /// Smallest dimension of the shape (m).
    pub(crate) fn min_extent(&self) -> f64 {
        match *self {
            Shape::Box { h, .. } => 2.0 * h[0].min(h[1]).min(h[2]),
            Shape::Cyl { r, z0, z1, .. } => (2.0 * r).min(z1 - z0),
            Shape::Ell { r, .. } => 2.0 * r[0].min(r[1]).min(r[2]),
        }
    }
}

/// One placed object (a group of primitives rasterised in order).
#[derive(Clone, Debug, PartialEq)]
pub(crate) struct Object {
    pub prims: Vec<Prim>,
    /// Placed by the class-coverage guarantee (never removed to make room).
    pub forced: bool,
}

impl Object {
    pub(crate) fn aabb(&self) -> ([f64; 3], [f64; 3]) {
        let mut lo = [f64::INFINITY; 3];
        let mut hi = [f64::NEG_INFINITY; 3];
        for p in &self.prims {
            let (a, b) = p.shape.aabb();
            for k in 0..3 {
                lo[k] = lo[k].min(a[k]);
                hi[k] = hi[k].max(b[k]);
            }
        }
        (lo, hi)
    }
}

/// Use of the land beyond a sidewalk.
#[derive(Clone, Copy, Debug, PartialEq)]
pub(crate) enum Zone {
    /// Buildings set back from the sidewalk behind a plaza of `plaza` class (sidewalk or other-ground).
    Urban { plaza: u8, setback: f64 },
    /// Grass and trees, fences, a few houses.
    Green,
    /// A parking lot `depth` metres deep behind a grass strip.
    Lot { depth: f64 },
    /// Gravel yard with a warehouse, trucks and trailers.
    Industrial,
}

/// A stretch of road between crossings, with its two roadsides (index 0 = right, y < 0).
#[derive(Clone, Copy, Debug, PartialEq)]
pub(crate) struct Block {
    pub x0: f64,
    pub x1: f64,
    pub zone: [Zone; 2],
    pub parking: [bool; 2],
}

/// A perpendicular cross street spanning x in `[x0, x1)`.
#[derive(Clone, Copy, Debug, PartialEq)]
pub(crate) struct Crossing {
    pub x0: f64,
    pub x1: f64,
    pub sidewalk_w: f64,
}

/// The ground plan: road cross-section and its variation along x.
#[derive(Clone, Debug, PartialEq)]
pub(crate) struct RoadPlan {
    /// Lanes on the right (driving +x) and left (driving −x) of the centre line.
    pub lanes: [usize; 2],
    pub lane_w: f64,
    /// Width of the raised median (0 if none) and its class.
    pub median_w: f64,
    pub median_class: u8,
    pub parking_w: f64,
    pub sidewalk_w: f64,
    pub crossings: Vec<Crossing>,
    pub blocks: Vec<Block>,
    pub noise_seed: u64,
    /// Lateral position of the ego lane centre.
    pub ego_y: f64,
}

/// Sign of the y side: side 0 (right) is y < 0.
fn sgn(side: usize) -> f64 {
    if side == 0 {
        -1.0
    } else {
        1.0
    }
}

/// Is `v` within a stripe of period `period` (first half of each period)?
fn stripe(v: f64, period: f64) -> bool {
    v.rem_euclid(period) < 0.5 * period
}

impl RoadPlan {
    /// Inner edge of the lanes (half the median).
    pub(crate) fn road_in(&self) -> f64 {
        0.5 * self.median_w
    }
    /// Outer edge of the lanes on `side`.
    pub(crate) fn road_out(&self, side: usize) -> f64 {
        self.road_in() + self.lanes[side] as f64 * self.lane_w
    }
    /// Outer edge of the parking strip on `side`.
    pub(crate) fn park_out(&self, side: usize) -> f64 {
        self.road_out(side) + self.parking_w
    }
    /// Outer edge of the sidewalk on `side`.
    pub(crate) fn walk_out(&self, side: usize) -> f64 {
        self.park_out(side) + self.sidewalk_w
    }
    /// Signed y of the centre of lane `k` on `side`.
    pub(crate) fn lane_y(&self, side: usize, k: usize) -> f64 {
        sgn(side) * (self.road_in() + (k as f64 + 0.5) * self.lane_w)
    }

    pub(crate) fn crossing_at(&self, x: f64) -> Option<&Crossing> {
        self.crossings.iter().find(|c| x >= c.x0 && x < c.x1)
    }

    pub(crate) fn block_at(&self, x: f64) -> Option<&Block> {
        self.blocks.iter().find(|b| x >= b.x0 && x < b.x1)
    }

    fn terrain_h(&self, x: f64, y: f64) -> f64 {
        0.05 + 0.3 * super::util::value_noise2(self.noise_seed, x / 7.0, y / 7.0)
    }

    /// Ground at column `(x, y)`: `(class, surface height in m, shade code)`. `mark_half_w` is
    /// the half width of painted markings (at least half a voxel so they survive voxelisation).
    pub(crate) fn ground(&self, x: f64, y: f64, mark_half_w: f64) -> (u8, f64, u8) {
        let side = usize::from(y >= 0.0);
        let a = y.abs();
        let hm = mark_half_w;
        if let Some(c) = self.crossing_at(x) {
            if a <= self.walk_out(side) {
                let zebra = a > self.park_out(side) + 0.3
                    && a < self.walk_out(side) - 0.3
                    && stripe(x, 1.2);
                return (ROAD, 0.0, if zebra { SH_MARK } else { SH_NEUTRAL });
            }
            if x < c.x0 + c.sidewalk_w || x >= c.x1 - c.sidewalk_w {
                return (SIDEWALK, CURB_H, SH_NEUTRAL);
            }
            let centre = (x - 0.5 * (c.x0 + c.x1)).abs() < hm && stripe(y, 6.0);
            return (ROAD, 0.0, if centre { SH_MARK } else { SH_NEUTRAL });
        }
        let block = self.block_at(x);
        if a < self.road_in() {
            return (self.median_class, CURB_H, SH_NEUTRAL);
        }
        if a <= self.road_out(side) {
            let mut mark = false;
            for k in 1..self.lanes[side] {
                let sep = self.road_in() + k as f64 * self.lane_w;
                if (a - sep).abs() < hm && x.rem_euclid(9.0) < 3.0 {
                    mark = true;
                }
            }
            if self.median_w == 0.0 && a < hm {
                mark = true;
            }
            if (a - (self.road_out(side) - 0.3)).abs() < hm {
                mark = true;
            }
            // zebra crossings in front of and behind every crossing
            for c in &self.crossings {
                if (x >= c.x0 - 4.5 && x < c.x0 - 1.0) || (x >= c.x1 + 1.0 && x < c.x1 + 4.5) {
                    mark = stripe(y, 1.2);
                }
            }
            return (ROAD, 0.0, if mark { SH_MARK } else { SH_NEUTRAL });
        }
        if a <= self.park_out(side) {
            return match block {
                Some(b) if b.parking[side] => {
                    let stall = x.rem_euclid(6.0) < 2.0 * hm;
                    (PARKING, 0.0, if stall { SH_MARK } else { SH_NEUTRAL })
                }
                _ => (ROAD, 0.0, SH_NEUTRAL),
            };
        }
        if a <= self.walk_out(side) {
            return (SIDEWALK, CURB_H, SH_NEUTRAL);
        }
        let d = a - self.walk_out(side);
        match block.map(|b| b.zone[side]) {
            Some(Zone::Urban { plaza, setback }) => {
                if d < setback {
                    (
                        plaza,
                        if plaza == SIDEWALK { CURB_H } else { 0.0 },
                        SH_NEUTRAL,
                    )
                } else {
                    (OTHER_GROUND, 0.0, SH_NEUTRAL)
                }
            }
            Some(Zone::Lot { depth }) => {
                if d < 1.5 || d >= 1.5 + depth {
                    (TERRAIN, self.terrain_h(x, y), SH_NEUTRAL)
                } else {
                    let stall = (d - 1.5 - 0.5 * depth).abs() < hm || x.rem_euclid(2.7) < 2.0 * hm;
                    (PARKING, 0.0, if stall { SH_MARK } else { SH_NEUTRAL })
                }
            }
            Some(Zone::Industrial) => (OTHER_GROUND, 0.0, SH_NEUTRAL),
            Some(Zone::Green) | None => (TERRAIN, self.terrain_h(x, y), SH_NEUTRAL),
        }
    }
}

/// A complete layout: ground plan and objects.
#[derive(Clone, Debug, PartialEq)]
pub(crate) struct Layout {
    pub plan: RoadPlan,
    pub objects: Vec<Object>,
}

/// An axis-aligned region (world metres) in which every object class of the style, and the
/// ground classes, must appear (the first frame's grid volume).
#[derive(Clone, Copy, Debug, PartialEq)]
pub(crate) struct Region {
    pub lo: [f64; 3],
    pub hi: [f64; 3],
}

fn overlaps(a: &([f64; 3], [f64; 3]), b: &([f64; 3], [f64; 3])) -> bool {
    (0..3).all(|k| a.0[k] < b.1[k] && b.0[k] < a.1[k])
}

struct Gen<'a> {
    rng: ChaCha8Rng,
    plan: &'a RoadPlan,
    style: Style,
    objects: Vec<Object>,
}

/// Heading of traffic on `side`: +x on the right, −x on the left.
fn lane_yaw(side: usize) -> f64 {
    if side == 0 {
        0.0
    } else {
        PI
    }
}

impl Gen<'_> {
    fn r(&mut self, lo: f64, hi: f64) -> f64 {
        if hi > lo {
            self.rng.random_range(lo..hi)
        } else {
            lo
        }
    }
    fn p(&mut self, prob: f64) -> bool {
        self.rng.random::<f64>() < prob
    }
    fn pick<T: Copy>(&mut self, items: &[T]) -> T {
        items[self.rng.random_range(0..items.len())]
    }
    fn body_shade(&mut self) -> u8 {
        self.pick(&[SH_NEUTRAL, SH_SOFT, SH_LIGHT, SH_BRIGHT, SH_DIM, SH_NEUTRAL])
    }
    fn ground_z(&self, x: f64, y: f64) -> f64 {
        self.plan.ground(x, y, 0.1).1
    }
    fn push(&mut self, prims: Vec<Prim>) {
        if !prims.is_empty() {
            self.objects.push(Object {
                prims,
                forced: false,
            });
        }
    }

    // ----- object builders (pure: return the primitives) -----

    /// Box part of an object at `(x, y, z0)` heading `yaw`: local centre offset `(dx, dy)`,
    /// length `l` along the heading, width `w`, from `z_lo` to `z_hi` above `z0`.
    #[allow(clippy::too_many_arguments)]
    fn part(
        cls: u8,
        shade: u8,
        x: f64,
        y: f64,
        z0: f64,
        yaw: f64,
        dx: f64,
        dy: f64,
        l: f64,
        w: f64,
        z_lo: f64,
        z_hi: f64,
    ) -> Prim {
        let (s, c) = yaw.sin_cos();
        Prim {
            shape: Shape::Box {
                c: [
                    x + dx * c - dy * s,
                    y + dx * s + dy * c,
                    z0 + 0.5 * (z_lo + z_hi),
                ],
                h: [0.5 * l, 0.5 * w, 0.5 * (z_hi - z_lo)],
                yaw,
            },
            class: cls,
            shade,
            pattern: Pattern::Solid,
        }
    }

    #[allow(clippy::too_many_arguments)]
    fn wheels(
        cls: u8,
        x: f64,
        y: f64,
        z0: f64,
        yaw: f64,
        l: f64,
        w: f64,
        r: f64,
        axles: &[f64],
    ) -> Vec<Prim> {
        let mut v = Vec::new();
        for &ax in axles {
            for side in [-1.0, 1.0] {
                v.push(Self::part(
                    cls,
                    SH_DARK,
                    x,
                    y,
                    z0,
                    yaw,
                    ax * l,
                    side * (0.5 * w - 0.15),
                    2.0 * r,
                    0.3,
                    0.0,
                    2.0 * r,
                ));
            }
        }
        v
    }

    fn car(&mut self, x: f64, y: f64, yaw: f64) -> Vec<Prim> {
        let (l, w, h) = (self.r(3.8, 4.9), self.r(1.65, 1.9), self.r(1.38, 1.65));
        let sh = self.body_shade();
        let z0 = self.ground_z(x, y);
        let mut v = Self::wheels(CAR, x, y, z0, yaw, l, w, 0.32, &[-0.32, 0.32]);
        v.push(Self::part(
            CAR,
            sh,
            x,
            y,
            z0,
            yaw,
            0.0,
            0.0,
            l,
            w,
            0.22,
            0.58 * h,
        ));
        v.push(Self::part(
            CAR,
            SH_DIM,
            x,
            y,
            z0,
            yaw,
            -0.06 * l,
            0.0,
            0.52 * l,
            0.9 * w,
            0.58 * h,
            h,
        ));
        v
    }

    fn van(&mut self, cls: u8, x: f64, y: f64, yaw: f64) -> Vec<Prim> {
        let (l, w, h) = (self.r(4.8, 6.2), self.r(1.9, 2.1), self.r(2.0, 2.6));
        let sh = self.body_shade();
        let z0 = self.ground_z(x, y);
        let mut v = Self::wheels(cls, x, y, z0, yaw, l, w, 0.35, &[-0.33, 0.33]);
        v.push(Self::part(
            cls,
            sh,
            x,
            y,
            z0,
            yaw,
            -0.08 * l,
            0.0,
            0.84 * l,
            w,
            0.3,
            h,
        ));
        v.push(Self::part(
            cls,
            SH_DIM,
            x,
            y,
            z0,
            yaw,
            0.42 * l,
            0.0,
            0.16 * l,
            0.95 * w,
            0.3,
            0.75 * h,
        ));
        v
    }

    fn truck(&mut self, x: f64, y: f64, yaw: f64) -> Vec<Prim> {
        let (l, w, h) = (self.r(6.5, 10.0), self.r(2.3, 2.55), self.r(2.9, 3.9));
        let z0 = self.ground_z(x, y);
        let sh = self.body_shade();
        let mut v = Self::wheels(TRUCK, x, y, z0, yaw, l, w, 0.5, &[-0.38, -0.22, 0.36]);
        v.push(Self::part(
            TRUCK,
            sh,
            x,
            y,
            z0,
            yaw,
            0.5 * l - 1.1,
            0.0,
            2.2,
            w,
            0.5,
            0.8 * h,
        ));
        v.push(Self::part(
            TRUCK,
            SH_DIM,
            x,
            y,
            z0,
            yaw,
            0.5 * l - 0.4,
            0.0,
            0.8,
            0.95 * w,
            0.45 * h,
            0.75 * h,
        ));
        let cargo = self.pick(&[SH_LIGHT, SH_NEUTRAL, SH_SOFT, SH_BRIGHT]);
        v.push(Self::part(
            TRUCK,
            cargo,
            x,
            y,
            z0,
            yaw,
            -1.25,
            0.0,
            l - 2.5,
            w,
            0.9,
            h,
        ));
        v
    }

    fn bus(&mut self, x: f64, y: f64, yaw: f64) -> Vec<Prim> {
        let (l, w) = (self.r(10.0, 12.5), 2.5);
        let z0 = self.ground_z(x, y);
        let sh = self.body_shade();
        let mut v = Self::wheels(BUS, x, y, z0, yaw, l, w, 0.5, &[-0.3, 0.32]);
        v.push(Self::part(
            BUS, sh, x, y, z0, yaw, 0.0, 0.0, l, w, 0.35, 1.2,
        ));
        v.push(Self::part(
            BUS, SH_DARK, x, y, z0, yaw, 0.0, 0.0, l, w, 1.2, 2.3,
        ));
        v.push(Self::part(BUS, sh, x, y, z0, yaw, 0.0, 0.0, l, w, 2.3, 3.1));
        v
    }

    fn trailer(&mut self, x: f64, y: f64, yaw: f64) -> Vec<Prim> {
        let (l, w, h) = (self.r(7.5, 12.0), 2.5, self.r(3.4, 4.0));
        let z0 = self.ground_z(x, y);
        let sh = self.pick(&[SH_LIGHT, SH_NEUTRAL, SH_BRIGHT]);
        let mut v = Self::wheels(TRAILER, x, y, z0, yaw, l, w, 0.5, &[-0.4, -0.3]);
        v.push(Self::part(
            TRAILER, sh, x, y, z0, yaw, 0.0, 0.0, l, w, 1.0, h,
        ));
        v.push(Self::part(
            TRAILER,
            SH_DARK,
            x,
            y,
            z0,
            yaw,
            0.35 * l,
            0.0,
            0.3,
            0.3,
            0.0,
            1.0,
        ));
        v
    }

    fn construction_vehicle(&mut self, x: f64, y: f64, yaw: f64) -> Vec<Prim> {
        let z0 = self.ground_z(x, y);
        let c = CONSTRUCTION_VEHICLE;
        let mut v = vec![
            Self::part(c, SH_DARK, x, y, z0, yaw, 0.0, 1.1, 4.0, 0.6, 0.0, 0.8),
            Self::part(c, SH_DARK, x, y, z0, yaw, 0.0, -1.1, 4.0, 0.6, 0.0, 0.8),
            Self::part(c, SH_NEUTRAL, x, y, z0, yaw, -0.3, 0.0, 3.2, 2.6, 0.8, 1.9),
            Self::part(c, SH_DIM, x, y, z0, yaw, 0.6, 0.6, 1.4, 1.2, 1.9, 3.1),
        ];
        // boom and stick of an excavator arm, as stepped boxes
        for i in 0..4 {
            let f = i as f64;
            v.push(Self::part(
                c,
                SH_LIGHT,
                x,
                y,
                z0,
                yaw,
                1.6 + 0.8 * f,
                -0.3,
                0.9,
                0.4,
                2.0 + 0.35 * f,
                2.6 + 0.35 * f,
            ));
        }
        v.push(Self::part(
            c, SH_LIGHT, x, y, z0, yaw, 4.8, -0.3, 0.4, 0.4, 0.5, 3.4,
        ));
        v
    }

    fn bicycle_parts(cls: u8, x: f64, y: f64, z0: f64, yaw: f64) -> Vec<Prim> {
        vec![
            Self::part(
                cls, SH_DARK, x, y, z0, yaw, -0.55, 0.0, 0.66, 0.06, 0.0, 0.66,
            ),
            Self::part(
                cls, SH_DARK, x, y, z0, yaw, 0.55, 0.0, 0.66, 0.06, 0.0, 0.66,
            ),
            Self::part(
                cls, SH_NEUTRAL, x, y, z0, yaw, 0.0, 0.0, 1.0, 0.08, 0.4, 0.75,
            ),
            Self::part(
                cls, SH_NEUTRAL, x, y, z0, yaw, 0.45, 0.0, 0.08, 0.55, 0.9, 1.0,
            ),
        ]
    }

    fn motorcycle_parts(cls: u8, x: f64, y: f64, z0: f64, yaw: f64) -> Vec<Prim> {
        vec![
            Self::part(
                cls, SH_DARK, x, y, z0, yaw, -0.7, 0.0, 0.62, 0.16, 0.0, 0.62,
            ),
            Self::part(cls, SH_DARK, x, y, z0, yaw, 0.7, 0.0, 0.62, 0.16, 0.0, 0.62),
            Self::part(
                cls, SH_NEUTRAL, x, y, z0, yaw, 0.0, 0.0, 1.3, 0.42, 0.35, 0.95,
            ),
            Self::part(
                cls, SH_NEUTRAL, x, y, z0, yaw, 0.6, 0.0, 0.1, 0.75, 0.95, 1.1,
            ),
        ]
    }

    fn bicycle(&mut self, x: f64, y: f64, yaw: f64) -> Vec<Prim> {
        let z0 = self.ground_z(x, y);
        Self::bicycle_parts(BICYCLE, x, y, z0, yaw)
    }

    fn motorcycle(&mut self, x: f64, y: f64, yaw: f64) -> Vec<Prim> {
        let z0 = self.ground_z(x, y);
        Self::motorcycle_parts(MOTORCYCLE, x, y, z0, yaw)
    }

    fn rider(cls: u8, shade: u8, x: f64, y: f64, z0: f64, yaw: f64, seat: f64) -> Vec<Prim> {
        vec![
            Self::part(
                cls,
                shade,
                x,
                y,
                z0,
                yaw,
                0.05,
                0.0,
                0.3,
                0.38,
                seat - 0.45,
                seat,
            ),
            Self::part(
                cls,
                shade,
                x,
                y,
                z0,
                yaw,
                -0.05,
                0.0,
                0.32,
                0.45,
                seat,
                seat + 0.62,
            ),
            Self::part(
                cls,
                SH_SOFT,
                x,
                y,
                z0,
                yaw,
                0.0,
                0.0,
                0.24,
                0.22,
                seat + 0.62,
                seat + 0.88,
            ),
        ]
    }

    fn bicyclist(&mut self, x: f64, y: f64, yaw: f64) -> Vec<Prim> {
        let z0 = self.ground_z(x, y);
        let sh = self.body_shade();
        let mut v = Self::bicycle_parts(BICYCLIST, x, y, z0, yaw);
        v.extend(Self::rider(BICYCLIST, sh, x, y, z0, yaw, 0.95));
        v
    }

    fn motorcyclist(&mut self, x: f64, y: f64, yaw: f64) -> Vec<Prim> {
        let z0 = self.ground_z(x, y);
        let sh = self.body_shade();
        let mut v = Self::motorcycle_parts(MOTORCYCLIST, x, y, z0, yaw);
        v.extend(Self::rider(MOTORCYCLIST, sh, x, y, z0, yaw, 0.95));
        v
    }

    fn person(&mut self, x: f64, y: f64, yaw: f64) -> Vec<Prim> {
        let z0 = self.ground_z(x, y);
        let h = self.r(1.5, 1.95);
        let (sh_top, sh_leg) = (self.body_shade(), self.pick(&[SH_DIM, SH_DARK, SH_SOFT]));
        vec![
            Self::part(
                PERSON,
                sh_leg,
                x,
                y,
                z0,
                yaw,
                0.0,
                0.0,
                0.24,
                0.34,
                0.0,
                0.48 * h,
            ),
            Self::part(
                PERSON,
                sh_top,
                x,
                y,
                z0,
                yaw,
                0.0,
                0.0,
                0.28,
                0.46,
                0.48 * h,
                0.84 * h,
            ),
            Self::part(
                PERSON,
                SH_SOFT,
                x,
                y,
                z0,
                yaw,
                0.0,
                0.0,
                0.22,
                0.2,
                0.84 * h,
                h,
            ),
        ]
    }

    fn tree(&mut self, x: f64, y: f64, big: bool) -> Vec<Prim> {
        let z0 = self.ground_z(x, y);
        let (r_t, h_t) = (self.r(0.12, 0.28), self.r(1.8, 3.2));
        let r = if big {
            self.r(2.0, 3.4)
        } else {
            self.r(1.2, 2.2)
        };
        let rv = r * self.r(0.8, 1.3);
        let sh = self.pick(&[SH_NEUTRAL, SH_SOFT, SH_DIM, SH_LIGHT]);
        vec![
            Prim {
                shape: Shape::Cyl {
                    c: [x, y],
                    r: r_t,
                    z0,
                    z1: z0 + h_t + 0.5 * rv,
                },
                class: TRUNK,
                shade: SH_NEUTRAL,
                pattern: Pattern::Solid,
            },
            Prim {
                shape: Shape::Ell {
                    c: [x, y, z0 + h_t + 0.8 * rv],
                    r: [r, r, rv],
                },
                class: VEGETATION,
                shade: sh,
                pattern: Pattern::Porous { keep: 0.8 },
            },
        ]
    }

    fn bush(&mut self, x: f64, y: f64) -> Vec<Prim> {
        let z0 = self.ground_z(x, y);
        let (r, rv) = (self.r(0.6, 1.5), self.r(0.4, 0.9));
        let sh = self.pick(&[SH_NEUTRAL, SH_SOFT, SH_DIM]);
        vec![Prim {
            shape: Shape::Ell {
                c: [x, y, z0 + 0.8 * rv],
                r: [r, r * self.r(0.7, 1.3), rv],
            },
            class: VEGETATION,
            shade: sh,
            pattern: Pattern::Porous { keep: 0.9 },
        }]
    }

    /// A hedge or fence running along x (`along_x`) or y from `(x, y)` over `len` metres.
    #[allow(clippy::too_many_arguments)]
    fn wall(
        &mut self,
        cls: u8,
        x: f64,
        y: f64,
        len: f64,
        along_x: bool,
        thick: f64,
        h: f64,
    ) -> Vec<Prim> {
        let z0 = self.ground_z(x, y);
        let yaw = if along_x { 0.0 } else { FRAC_PI_2 };
        let (cx, cy) = if along_x {
            (x + 0.5 * len, y)
        } else {
            (x, y + 0.5 * len)
        };
        let pattern = if cls == VEGETATION {
            Pattern::Porous { keep: 0.95 }
        } else {
            Pattern::Solid
        };
        let shade = if cls == FENCE {
            self.pick(&[SH_NEUTRAL, SH_SOFT, SH_LIGHT])
        } else {
            SH_NEUTRAL
        };
        let mut v = vec![Prim {
            shape: Shape::Box {
                c: [cx, cy, z0 + 0.5 * h],
                h: [0.5 * len, 0.5 * thick, 0.5 * h],
                yaw,
            },
            class: cls,
            shade,
            pattern,
        }];
        if cls == FENCE {
            let n = (len / 2.5).floor() as usize;
            for i in 0..=n {
                let t = i as f64 * 2.5;
                let (px, py) = if along_x { (x + t, y) } else { (x, y + t) };
                v.push(Prim {
                    shape: Shape::Cyl {
                        c: [px, py],
                        r: 0.05,
                        z0,
                        z1: z0 + h + 0.1,
                    },
                    class: FENCE,
                    shade: SH_DIM,
                    pattern: Pattern::Solid,
                });
            }
        }
        v
    }

    fn street_light(&mut self, x: f64, y: f64, toward_road: f64) -> Vec<Prim> {
        let z0 = self.ground_z(x, y);
        let h = self.r(5.5, 8.0);
        vec![
            Prim {
                shape: Shape::Cyl {
                    c: [x, y],
                    r: 0.11,
                    z0,
                    z1: z0 + h,
                },
                class: POLE,
                shade: SH_NEUTRAL,
                pattern: Pattern::Solid,
            },
            Prim {
                shape: Shape::Box {
                    c: [x, y + toward_road * 0.8, z0 + h - 0.05],
                    h: [0.06, 0.8, 0.05],
                    yaw: 0.0,
                },
                class: POLE,
                shade: SH_NEUTRAL,
                pattern: Pattern::Solid,
            },
            Prim {
                shape: Shape::Box {
                    c: [x, y + toward_road * 1.55, z0 + h - 0.15],
                    h: [0.2, 0.3, 0.1],
                    yaw: 0.0,
                },
                class: POLE,
                shade: SH_LIGHT,
                pattern: Pattern::Solid,
            },
        ]
    }

    fn sign(&mut self, x: f64, y: f64) -> Vec<Prim> {
        let z0 = self.ground_z(x, y);
        let h = self.r(2.1, 2.9);
        let (hw, hh) = self.pick(&[(0.35, 0.35), (0.45, 0.3), (0.3, 0.45), (0.6, 0.25)]);
        let sh = self.pick(&[SH_NEUTRAL, SH_LIGHT, SH_BRIGHT]);
        vec![
            Prim {
                shape: Shape::Cyl {
                    c: [x, y],
                    r: 0.05,
                    z0,
                    z1: z0 + h,
                },
                class: POLE,
                shade: SH_SOFT,
                pattern: Pattern::Solid,
            },
            Prim {
                shape: Shape::Box {
                    c: [x + 0.06, y, z0 + h],
                    h: [0.03, hw, hh],
                    yaw: 0.0,
                },
                class: TRAFFIC_SIGN,
                shade: sh,
                pattern: Pattern::Solid,
            },
        ]
    }

    fn traffic_light(&mut self, x: f64, y: f64) -> Vec<Prim> {
        let z0 = self.ground_z(x, y);
        let h = self.r(3.2, 4.2);
        vec![
            Prim {
                shape: Shape::Cyl {
                    c: [x, y],
                    r: 0.1,
                    z0,
                    z1: z0 + h,
                },
                class: POLE,
                shade: SH_DIM,
                pattern: Pattern::Solid,
            },
            Prim {
                shape: Shape::Box {
                    c: [x, y, z0 + h + 0.45],
                    h: [0.16, 0.16, 0.45],
                    yaw: 0.0,
                },
                class: TRAFFIC_SIGN,
                shade: SH_DIM,
                pattern: Pattern::Solid,
            },
        ]
    }

    fn cone(&mut self, x: f64, y: f64) -> Vec<Prim> {
        let z0 = self.ground_z(x, y);
        vec![Prim {
            shape: Shape::Box {
                c: [x, y, z0 + 0.36],
                h: [0.17, 0.17, 0.36],
                yaw: 0.0,
            },
            class: TRAFFIC_CONE,
            shade: SH_NEUTRAL,
            pattern: Pattern::Stripes { period: 0.3 },
        }]
    }

    fn barrier(&mut self, x: f64, y: f64, yaw: f64) -> Vec<Prim> {
        let z0 = self.ground_z(x, y);
        vec![Prim {
            shape: Shape::Box {
                c: [x, y, z0 + 0.5],
                h: [1.0, 0.25, 0.5],
                yaw,
            },
            class: BARRIER,
            shade: SH_NEUTRAL,
            pattern: Pattern::Stripes { period: 0.5 },
        }]
    }

    /// Building with its street facade along x at `|y| = y_near` on `side`.
    #[allow(clippy::too_many_arguments)]
    fn building(
        &mut self,
        side: usize,
        x0: f64,
        x1: f64,
        y_near: f64,
        depth: f64,
        height: f64,
        sparse: bool,
    ) -> Vec<Prim> {
        let s = sgn(side);
        let yc = s * (y_near + 0.5 * depth);
        let z0 = 0.0;
        let sh = self.pick(&[SH_NEUTRAL, SH_SOFT, SH_LIGHT, SH_DIM, SH_BRIGHT]);
        let facade = Pattern::Facade {
            floor_h: self.r(2.8, 3.4),
            period: if sparse {
                self.r(5.0, 8.0)
            } else {
                self.r(2.2, 3.2)
            },
            win_w: self.r(0.9, 1.5),
            phase: self.r(0.0, 3.0),
        };
        let mut v = vec![Prim {
            shape: Shape::Box {
                c: [0.5 * (x0 + x1), yc, z0 + 0.5 * height],
                h: [0.5 * (x1 - x0), 0.5 * depth, 0.5 * height],
                yaw: 0.0,
            },
            class: BUILDING,
            shade: sh,
            pattern: facade,
        }];
        if !sparse && height < 10.0 && self.p(0.3) {
            let (l, d, h2) = (
                (x1 - x0) * self.r(0.4, 0.8),
                depth * self.r(0.4, 0.8),
                self.r(2.5, 4.0),
            );
            let cx = x0 + 0.5 * l + self.r(0.0, (x1 - x0) - l);
            v.push(Prim {
                shape: Shape::Box {
                    c: [cx, yc + s * 0.5 * (depth - d), height + 0.5 * h2],
                    h: [0.5 * l, 0.5 * d, 0.5 * h2],
                    yaw: 0.0,
                },
                class: BUILDING,
                shade: sh,
                pattern: facade,
            });
        }
        v
    }

    fn vehicle_of_kind(&mut self, kind: u8, x: f64, y: f64, yaw: f64) -> Vec<Prim> {
        match kind {
            CAR => self.car(x, y, yaw),
            TRUCK => self.truck(x, y, yaw),
            OTHER_VEHICLE => self.van(OTHER_VEHICLE, x, y, yaw),
            BUS => self.bus(x, y, yaw),
            TRAILER => self.trailer(x, y, yaw),
            CONSTRUCTION_VEHICLE => self.construction_vehicle(x, y, yaw),
            MOTORCYCLIST => self.motorcyclist(x, y, yaw),
            BICYCLIST => self.bicyclist(x, y, yaw),
            MOTORCYCLE => self.motorcycle(x, y, yaw),
            BICYCLE => self.bicycle(x, y, yaw),
            _ => self.person(x, y, yaw),
        }
    }

    fn kind_length(kind: u8) -> f64 {
        match kind {
            TRUCK => 10.0,
            BUS => 12.5,
            TRAILER => 12.0,
            CONSTRUCTION_VEHICLE => 6.0,
            OTHER_VEHICLE => 6.2,
            CAR => 4.9,
            MOTORCYCLIST | MOTORCYCLE => 2.2,
            BICYCLIST | BICYCLE => 1.9,
            _ => 0.6,
        }
    }

    // ----- placement -----

    fn traffic(&mut self, x_min: f64, x_max: f64) {
        let plan = self.plan;
        let ego_lane = lane_index_of(plan, plan.ego_y);
        for side in 0..2 {
            for k in 0..plan.lanes[side] {
                if side == 0 && Some(k) == ego_lane {
                    continue;
                }
                let y_c = plan.lane_y(side, k);
                let mut x = x_min + self.r(0.0, 20.0);
                while x < x_max {
                    let u: f64 = self.r(0.0, 1.0);
                    let kind = match self.style {
                        Style::Kitti => {
                            if u < 0.72 {
                                CAR
                            } else if u < 0.82 {
                                TRUCK
                            } else if u < 0.9 {
                                OTHER_VEHICLE
                            } else if u < 0.96 {
                                MOTORCYCLIST
                            } else {
                                BUS
                            }
                        }
                        Style::Nuscenes => {
                            if u < 0.66 {
                                CAR
                            } else if u < 0.76 {
                                TRUCK
                            } else if u < 0.84 {
                                BUS
                            } else if u < 0.9 {
                                TRAILER
                            } else if u < 0.96 {
                                MOTORCYCLIST
                            } else {
                                CONSTRUCTION_VEHICLE
                            }
                        }
                    };
                    let half = 0.5 * Self::kind_length(kind);
                    x += half;
                    let (dy, dyaw) = (self.r(-0.3, 0.3), self.r(-0.03, 0.03));
                    let prims = self.vehicle_of_kind(kind, x, y_c + dy, lane_yaw(side) + dyaw);
                    self.push(prims);
                    x += half + self.r(5.0, 40.0);
                }
            }
        }
    }

    fn roadside(&mut self, b: Block) {
        let plan = self.plan;
        let len = b.x1 - b.x0;
        for side in 0..2 {
            let s = sgn(side);
            // parking strip or shoulder
            let y_park = s * (plan.road_out(side) + 0.5 * plan.parking_w);
            let yaw = lane_yaw(side);
            let mut x = b.x0 + self.r(1.0, 4.0);
            while x < b.x1 - 3.0 {
                if b.parking[side] {
                    let u = self.r(0.0, 1.0);
                    if u < 0.62 {
                        let a0 = self.r(-0.15, 0.15);
                        let a1 = self.r(-0.03, 0.03);
                        let p = self.car(x + 2.5, y_park + a0, yaw + a1);
                        self.push(p);
                    } else if u < 0.7 && x + 6.5 < b.x1 {
                        let p = self.van(OTHER_VEHICLE, x + 3.0, y_park, yaw);
                        self.push(p);
                        x += 1.5;
                    } else if u < 0.78 {
                        let p = self.motorcycle(x + 1.5, y_park + s * 0.4, yaw + FRAC_PI_2 * 0.5);
                        self.push(p);
                    }
                    x += self.r(5.6, 6.8);
                } else {
                    if self.p(0.12) {
                        let a0 = self.r(-0.1, 0.1);
                        let p = self.bicyclist(x, y_park + s * 0.3, yaw + a0);
                        self.push(p);
                    }
                    x += self.r(10.0, 25.0);
                }
            }
            // street furniture on the sidewalk
            let y_curb = s * (plan.park_out(side) + 0.35);
            let mut x = b.x0 + self.r(2.0, 15.0);
            while x < b.x1 - 1.0 {
                let p = self.street_light(x, y_curb, -s);
                self.push(p);
                x += self.r(22.0, 40.0);
            }
            if self.p(0.55) {
                let y_tree = s * (plan.park_out(side) + 0.5 * plan.sidewalk_w.min(2.4));
                let mut x = b.x0 + self.r(2.0, 8.0);
                let spacing = self.r(7.0, 14.0);
                while x < b.x1 - 1.0 {
                    let big = self.p(0.4);
                    let p = self.tree(x, y_tree, big);
                    self.push(p);
                    x += spacing + self.r(-1.0, 1.0);
                }
            }
            let n_signs = self.rng.random_range(1..=3usize) * (1 + usize::from(len > 80.0));
            for _ in 0..n_signs {
                let x = self.r(b.x0 + 1.0, b.x1 - 1.0);
                let p = self.sign(x, s * (plan.park_out(side) + 0.25));
                self.push(p);
            }
            let n_people = self.rng.random_range(0..=(len / 12.0).ceil() as usize);
            for _ in 0..n_people {
                let (x, a) = (
                    self.r(b.x0 + 1.0, b.x1 - 1.0),
                    self.r(plan.park_out(side) + 0.6, plan.walk_out(side) - 0.3),
                );
                let yaw = self.pick(&[0.0, PI]) + self.r(-0.4, 0.4);
                let p = self.person(x, s * a, yaw);
                self.push(p);
            }
            if self.p(0.5) {
                let x0 = self.r(b.x0 + 2.0, (b.x1 - 6.0).max(b.x0 + 2.5));
                let n = self.rng.random_range(1..=4usize);
                for i in 0..n {
                    let a0 = self.r(-0.1, 0.1);
                    let p = self.bicycle(
                        x0 + 0.75 * i as f64,
                        s * (plan.walk_out(side) - 0.9),
                        s * FRAC_PI_2 + a0,
                    );
                    self.push(p);
                }
            }
            if self.p(0.25) {
                let x = self.r(b.x0 + 2.0, b.x1 - 2.0);
                let p = self.motorcycle(x, s * (plan.walk_out(side) - 1.1), s * FRAC_PI_2);
                self.push(p);
            }
            if self.p(0.2) {
                let x = self.r(b.x0 + 2.0, b.x1 - 2.0);
                let p = self.bicyclist(x, s * (plan.park_out(side) + 0.5 * plan.sidewalk_w), yaw);
                self.push(p);
            }
            self.zone(b, side);
        }
        if self.style == Style::Nuscenes && self.p(0.35) {
            // a construction site on the outer lane of the left side, closed by cones and barriers
            let side = 1;
            let y_lane = plan.lane_y(side, plan.lanes[side] - 1);
            let x0 = self.r(b.x0 + 3.0, (b.x1 - 20.0).max(b.x0 + 3.5));
            for i in 0..8 {
                let p = self.cone(x0 + 2.0 * i as f64, y_lane - 1.2);
                self.push(p);
            }
            let p = self.barrier(x0 + 8.0, y_lane + 0.6, 0.0);
            self.push(p);
            let p = self.construction_vehicle(x0 + 10.0, y_lane + 0.3, PI);
            self.push(p);
        }
    }

    fn zone(&mut self, b: Block, side: usize) {
        let plan = self.plan;
        let s = sgn(side);
        let w0 = plan.walk_out(side);
        match b.zone[side] {
            Zone::Urban { setback, .. } => {
                let mut x = b.x0 + self.r(0.5, 3.0);
                while x < b.x1 - 4.0 {
                    let l = self.r(8.0, 28.0).min(b.x1 - 1.0 - x);
                    if l < 4.0 {
                        break;
                    }
                    let (depth, height) = (self.r(8.0, 20.0), self.r(4.5, 14.0));
                    let p = self.building(side, x, x + l, w0 + setback, depth, height, false);
                    self.push(p);
                    x += l;
                    let gap = self.r(0.0, 7.0);
                    if gap > 2.5 {
                        let u = self.r(0.0, 1.0);
                        if u < 0.45 {
                            let a0 = self.r(4.0, 10.0);
                            let a1 = self.r(1.2, 2.0);
                            let p = self.wall(
                                FENCE,
                                x + 0.5 * gap,
                                s * (w0 + setback),
                                s * a0,
                                false,
                                0.06,
                                a1,
                            );
                            self.push(p);
                        } else if u < 0.8 {
                            let a0 = self.r(1.5, 5.0);
                            let p = self.tree(x + 0.5 * gap, s * (w0 + setback + a0), false);
                            self.push(p);
                        } else {
                            let p = self.car(x + 0.5 * gap, s * (w0 + setback + 4.0), FRAC_PI_2);
                            self.push(p);
                        }
                    }
                    x += gap;
                }
                if setback > 2.0 && self.p(0.5) {
                    let n = self.rng.random_range(1..=3usize);
                    for _ in 0..n {
                        let a0 = self.r(b.x0 + 2.0, b.x1 - 2.0);
                        let a1 = self.r(0.8, setback - 0.8);
                        let p = self.bush(a0, s * (w0 + a1));
                        self.push(p);
                    }
                }
            }
            Zone::Green => {
                if self.p(0.6) {
                    let off = self.r(0.3, 5.0);
                    let mut x = b.x0 + self.r(0.0, 6.0);
                    while x < b.x1 - 3.0 {
                        let l = self.r(10.0, 40.0).min(b.x1 - x - 0.5);
                        let h = self.r(1.0, 2.0);
                        let p = self.wall(FENCE, x, s * (w0 + off), l, true, 0.06, h);
                        self.push(p);
                        x += l + self.r(2.0, 12.0);
                    }
                } else if self.p(0.5) {
                    let x = b.x0 + self.r(0.0, 5.0);
                    let l = (b.x1 - x - 1.0).min(self.r(10.0, 40.0));
                    if l > 2.0 {
                        let (th, h) = (self.r(0.6, 1.1), self.r(0.8, 1.7));
                        let p = self.wall(VEGETATION, x, s * (w0 + 0.4 + 0.5 * th), l, true, th, h);
                        self.push(p);
                    }
                }
                let area = (b.x1 - b.x0) * 30.0;
                let n_trees = self.rng.random_range(0..=((area / 150.0) as usize).max(1));
                for _ in 0..n_trees {
                    let big = self.p(0.6);
                    let a0 = self.r(b.x0, b.x1);
                    let a1 = self.r(2.0, 35.0);
                    let p = self.tree(a0, s * (w0 + a1), big);
                    self.push(p);
                }
                let n_bush = self.rng.random_range(0..=((area / 200.0) as usize).max(1));
                for _ in 0..n_bush {
                    let a0 = self.r(b.x0, b.x1);
                    let a1 = self.r(1.0, 30.0);
                    let p = self.bush(a0, s * (w0 + a1));
                    self.push(p);
                }
                if self.p(0.4) {
                    let l = self.r(8.0, 14.0);
                    if b.x1 - b.x0 > l + 4.0 {
                        let x = self.r(b.x0 + 2.0, b.x1 - 2.0 - l);
                        let a0 = self.r(8.0, 20.0);
                        let a1 = self.r(7.0, 11.0);
                        let a2 = self.r(4.0, 8.0);
                        let p = self.building(side, x, x + l, w0 + a0, a1, a2, false);
                        self.push(p);
                    }
                }
            }
            Zone::Lot { depth } => {
                let rows = [w0 + 1.5 + 2.6, w0 + 1.5 + depth - 2.6];
                for (ri, &a) in rows.iter().enumerate() {
                    let mut x = b.x0 + 2.0;
                    while x < b.x1 - 2.0 {
                        if self.p(0.6) {
                            let yaw = s * FRAC_PI_2 * if ri == 0 { 1.0 } else { -1.0 };
                            let p = if self.p(0.08) {
                                self.van(OTHER_VEHICLE, x, s * a, yaw)
                            } else {
                                self.car(x, s * a, yaw)
                            };
                            self.push(p);
                        }
                        x += 2.7;
                    }
                }
                if self.p(0.6) {
                    let p = self.wall(
                        FENCE,
                        b.x0 + 1.0,
                        s * (w0 + 1.5 + depth + 0.6),
                        (b.x1 - b.x0 - 2.0).max(1.0),
                        true,
                        0.06,
                        1.8,
                    );
                    self.push(p);
                }
                let mut x = b.x0 + self.r(3.0, 10.0);
                while x < b.x1 - 2.0 {
                    let p = self.street_light(x, s * (w0 + 1.5 + 0.5 * depth), s);
                    self.push(p);
                    x += self.r(20.0, 35.0);
                }
            }
            Zone::Industrial => {
                let setback = self.r(9.0, 18.0);
                let mut x = b.x0 + self.r(2.0, 6.0);
                while x < b.x1 - 10.0 {
                    let l = self.r(20.0, 50.0).min(b.x1 - 2.0 - x);
                    let a0 = self.r(15.0, 30.0);
                    let a1 = self.r(6.0, 10.0);
                    let p = self.building(side, x, x + l, w0 + setback, a0, a1, true);
                    self.push(p);
                    x += l + self.r(4.0, 12.0);
                }
                let mut x = b.x0 + 0.5;
                while x < b.x1 - 3.0 {
                    let l = self.r(10.0, 30.0).min(b.x1 - x - 0.5);
                    let a0 = self.r(1.6, 2.2);
                    let p = self.wall(FENCE, x, s * (w0 + 0.5), l, true, 0.06, a0);
                    self.push(p);
                    x += l + self.r(4.0, 8.0);
                }
                let n = self.rng.random_range(0..=3usize);
                for _ in 0..n {
                    let x = self.r(b.x0 + 4.0, (b.x1 - 4.0).max(b.x0 + 4.5));
                    let kind = if self.p(0.5) { TRUCK } else { TRAILER };
                    let p = self.vehicle_of_kind(
                        kind,
                        x,
                        s * (w0 + 0.5 * setback + 0.5),
                        s * FRAC_PI_2,
                    );
                    self.push(p);
                }
            }
        }
    }

    fn crossing_objects(&mut self, c: Crossing) {
        let plan = self.plan;
        for side in 0..2 {
            let s = sgn(side);
            for &x in &[c.x0 + 0.4, c.x1 - 0.4] {
                let p = self.traffic_light(x, s * (plan.walk_out(side) + 0.4));
                self.push(p);
            }
            // stopped traffic on the cross street
            let mut a = plan.walk_out(side) + self.r(2.0, 8.0);
            while a < 45.0 {
                if self.p(0.5) {
                    let lane_dx = if side == 0 { 2.0 } else { -2.0 };
                    let xm = 0.5 * (c.x0 + c.x1) + lane_dx;
                    let yaw = if side == 0 { FRAC_PI_2 } else { -FRAC_PI_2 };
                    let p = self.car(xm, s * a, yaw);
                    self.push(p);
                }
                a += self.r(6.0, 14.0);
            }
            // pedestrians on the zebra crossing of the side street
            let n = self.rng.random_range(0..=2usize);
            for _ in 0..n {
                let x = self.r(c.x0 + 1.0, c.x1 - 1.0);
                let a = self.r(plan.park_out(side) + 0.5, plan.walk_out(side) - 0.3);
                let yaw = self.pick(&[0.0, PI]);
                let p = self.person(x, s * a, yaw);
                self.push(p);
            }
        }
    }
}

/// Index of the right-side lane whose centre is at `y`, if any.
fn lane_index_of(plan: &RoadPlan, y: f64) -> Option<usize> {
    (0..plan.lanes[0]).find(|&k| (plan.lane_y(0, k) - y).abs() < 1e-9)
}

/// Generate the layout for x in `[x_min, x_max]`. `region_rel` is where every class must appear
/// (the first frame's grid volume), with y relative to the ego lane centre.
pub(crate) fn generate_layout(
    seed: u64,
    style: Style,
    x_min: f64,
    x_max: f64,
    region_rel: Region,
) -> Layout {
    let mut rng = ChaCha8Rng::seed_from_u64(seed);
    let lanes = [rng.random_range(1..=2usize), rng.random_range(1..=2usize)];
    let lane_w = rng.random_range(3.2..3.8);
    let (median_w, median_class) = if rng.random::<f64>() < 0.3 {
        (
            rng.random_range(1.5..4.0),
            if rng.random::<bool>() {
                TERRAIN
            } else {
                OTHER_GROUND
            },
        )
    } else {
        (0.0, TERRAIN)
    };
    let parking_w = rng.random_range(2.2..2.6);
    let sidewalk_w = rng.random_range(1.8..4.0);
    let ego_lane = rng.random_range(0..lanes[0]);
    let ego_y = -(0.5 * median_w + (ego_lane as f64 + 0.5) * lane_w);
    let region = Region {
        lo: [region_rel.lo[0], region_rel.lo[1] + ego_y, region_rel.lo[2]],
        hi: [region_rel.hi[0], region_rel.hi[1] + ego_y, region_rel.hi[2]],
    };
    let mut crossings = Vec::new();
    let mut x = x_min + rng.random_range(20.0..90.0);
    while x < x_max {
        let w = rng.random_range(9.0..14.0);
        crossings.push(Crossing {
            x0: x,
            x1: x + w,
            sidewalk_w: rng.random_range(1.5..3.0),
        });
        x += w + rng.random_range(60.0..150.0);
    }
    let zone = |rng: &mut ChaCha8Rng| -> Zone {
        let u: f64 = rng.random();
        if u < 0.4 {
            let plaza = if rng.random::<f64>() < 0.6 {
                SIDEWALK
            } else {
                OTHER_GROUND
            };
            Zone::Urban {
                plaza,
                setback: rng.random_range(0.5..6.0),
            }
        } else if u < 0.7 {
            Zone::Green
        } else if u < 0.85 {
            Zone::Lot {
                depth: rng.random_range(10.0..16.0),
            }
        } else {
            Zone::Industrial
        }
    };
    let mut blocks = Vec::new();
    let mut bx = x_min - 200.0;
    for c in crossings.iter().chain(std::iter::once(&Crossing {
        x0: x_max + 200.0,
        x1: x_max + 200.0,
        sidewalk_w: 0.0,
    })) {
        let zs = [zone(&mut rng), zone(&mut rng)];
        let parking = [rng.random::<f64>() < 0.55, rng.random::<f64>() < 0.55];
        blocks.push(Block {
            x0: bx,
            x1: c.x0,
            zone: zs,
            parking,
        });
        bx = c.x1;
    }
    let mut plan = RoadPlan {
        lanes,
        lane_w,
        median_w,
        median_class,
        parking_w,
        sidewalk_w,
        crossings,
        blocks,
        noise_seed: rng.random(),
        ego_y,
    };
    ensure_ground_classes(&mut plan, &mut rng, region);

    let mut g = Gen {
        rng,
        plan: &plan,
        style,
        objects: Vec::new(),
    };
    for b in plan.blocks.clone() {
        let b = Block {
            x0: b.x0.max(x_min),
            x1: b.x1.min(x_max),
            ..b
        };
        if b.x1 > b.x0 + 2.0 {
            g.roadside(b);
        }
    }
    for c in plan.crossings.clone() {
        g.crossing_objects(c);
    }
    g.traffic(x_min, x_max);
    // keep the ego corridor free of anything the ego would drive through
    let corridor = (
        [x_min - 1e3, plan.ego_y - 1.3, -1.0],
        [x_max + 1e3, plan.ego_y + 1.3, 4.5],
    );
    g.objects.retain(|o| !overlaps(&o.aabb(), &corridor));
    ensure_object_classes(&mut g, region, corridor);
    let objects = g.objects;
    Layout { plan, objects }
}

/// Make sure road, parking, sidewalk, other-ground and terrain occur in `region`, by changing
/// the parking flags and zones of the blocks overlapping it.
fn ensure_ground_classes(plan: &mut RoadPlan, rng: &mut ChaCha8Rng, region: Region) {
    let present = |plan: &RoadPlan, cls: u8| -> bool {
        let mut x = region.lo[0] + 2.0;
        while x < region.hi[0] - 1.0 {
            let mut y = region.lo[1] + 0.5;
            while y < region.hi[1] - 0.5 {
                if plan.ground(x, y, 0.2).0 == cls {
                    return true;
                }
                y += 0.5;
            }
            x += 1.0;
        }
        false
    };
    // the block with the largest overlap with the region
    let bi = plan
        .blocks
        .iter()
        .enumerate()
        .map(|(i, b)| {
            (
                i,
                (b.x1.min(region.hi[0]) - b.x0.max(region.lo[0] + 2.0)).max(0.0),
            )
        })
        .fold(
            (0usize, -1.0f64),
            |acc, (i, o)| if o > acc.1 { (i, o) } else { acc },
        )
        .0;
    let side = rng.random_range(0..2usize);
    if !present(plan, PARKING) {
        plan.blocks[bi].parking[side] = true;
    }
    if !present(plan, OTHER_GROUND) {
        let s = rng.random_range(0..2usize);
        plan.blocks[bi].zone[s] = Zone::Urban {
            plaza: OTHER_GROUND,
            setback: rng.random_range(3.0..6.0),
        };
    }
    if !present(plan, TERRAIN) {
        let s = if matches!(
            plan.blocks[bi].zone[0],
            Zone::Urban {
                plaza: OTHER_GROUND,
                ..
            }
        ) {
            1
        } else {
            0
        };
        plan.blocks[bi].zone[s] = Zone::Green;
        if !present(plan, OTHER_GROUND) {
            plan.blocks[bi].zone[1 - s] = Zone::Industrial;
        }
    }
}

/// Classes that every layout of a style must show in its region.
pub(crate) fn required_object_classes(style: Style) -> Vec<u8> {
    let mut v = vec![
        CAR,
        BICYCLE,
        MOTORCYCLE,
        TRUCK,
        OTHER_VEHICLE,
        PERSON,
        BICYCLIST,
        MOTORCYCLIST,
        BUILDING,
        FENCE,
        VEGETATION,
        TRUNK,
        POLE,
        TRAFFIC_SIGN,
    ];
    if style == Style::Nuscenes {
        v.extend([BUS, TRAILER, CONSTRUCTION_VEHICLE, BARRIER, TRAFFIC_CONE]);
    }
    v
}

fn ensure_object_classes(g: &mut Gen<'_>, region: Region, corridor: ([f64; 3], [f64; 3])) {
    let rbox = (region.lo, region.hi);
    // keep forced objects in the front part of the region so that cameras see them too
    let x_lo = region.lo[0] + 6.0;
    let mut next_x = [x_lo + 8.0, x_lo, x_lo, x_lo, x_lo, x_lo, x_lo + 15.0];
    // forced objects may displace random ones: repeat until every class is present
    for _pass in 0..4 {
        let missing: Vec<u8> = required_object_classes(g.style)
            .into_iter()
            .filter(|&cls| {
                !g.objects.iter().any(|o| {
                    o.prims
                        .iter()
                        .any(|p| p.class == cls && overlaps(&p.shape.aabb(), &rbox))
                })
            })
            .collect();
        if missing.is_empty() {
            break;
        }
        for cls in missing {
            place_forced(g, cls, &mut next_x, corridor);
        }
    }
}

fn place_forced(g: &mut Gen<'_>, cls: u8, next_x: &mut [f64; 7], corridor: ([f64; 3], [f64; 3])) {
    let plan = g.plan;
    {
        // (track, y, yaw, length)
        let left_lane = if plan.lanes[1] > 0 {
            plan.lane_y(1, plan.lanes[1] - 1)
        } else {
            plan.lane_y(0, 0)
        };
        let sidewalk = |side: usize| sgn(side) * (plan.park_out(side) + 0.5 * plan.sidewalk_w);
        let beyond = |side: usize, d: f64| sgn(side) * (plan.walk_out(side) + d);
        let (track, y, yaw) = match cls {
            TRUCK | BUS | TRAILER | MOTORCYCLIST => (0, left_lane, PI),
            CAR | OTHER_VEHICLE => (6, -(plan.road_out(0) + 0.5 * plan.parking_w), 0.0),
            BICYCLIST | MOTORCYCLE => (1, -(plan.road_out(0) + 0.5 * plan.parking_w), 0.0),
            PERSON | BICYCLE | BARRIER | TRAFFIC_CONE => (2, sidewalk(1), FRAC_PI_2),
            POLE | TRAFFIC_SIGN | TRUNK | VEGETATION => (3, sidewalk(0), 0.0),
            FENCE | CONSTRUCTION_VEHICLE => (4, beyond(0, 1.5), 0.0),
            _ => (5, beyond(1, 2.0), 0.0),
        };
        let len = match cls {
            FENCE => 8.0,
            BUILDING => 10.0,
            POLE | TRAFFIC_SIGN => 2.0,
            TRUNK | VEGETATION => 4.0,
            _ => Gen::kind_length(cls),
        };
        let x = next_x[track] + 0.5 * len;
        next_x[track] += len + 1.5;
        let prims = match cls {
            POLE => g.street_light(x, y, -1.0),
            TRAFFIC_SIGN => g.sign(x, y),
            TRUNK | VEGETATION => g.tree(x, y, false),
            FENCE => g.wall(FENCE, x - 0.5 * len, y, len, true, 0.06, 1.6),
            BUILDING => g.building(1, x - 0.5 * len, x + 0.5 * len, y.abs(), 8.0, 6.0, false),
            BARRIER => g.barrier(x, y, 0.0),
            TRAFFIC_CONE => g.cone(x, y),
            _ => g.vehicle_of_kind(cls, x, y, yaw),
        };
        let obj = Object {
            prims,
            forced: true,
        };
        if overlaps(&obj.aabb(), &corridor) {
            return;
        }
        let bb = obj.aabb();
        g.objects.retain(|o| o.forced || !overlaps(&o.aabb(), &bb));
        g.objects.push(obj);
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn region() -> Region {
        Region {
            lo: [0.0, -25.6, -0.4],
            hi: [51.2, 25.6, 6.0],
        }
    }

    #[test]
    fn shapes_contain_their_skeleton_and_centre() {
        let shapes = [
            Shape::Box {
                c: [1.0, 2.0, 0.5],
                h: [2.0, 0.03, 0.4],
                yaw: 0.7,
            },
            Shape::Cyl {
                c: [0.0, 0.0],
                r: 0.05,
                z0: 0.0,
                z1: 3.0,
            },
            Shape::Ell {
                c: [0.0, 1.0, 2.0],
                r: [1.0, 2.0, 0.5],
            },
        ];
        for s in shapes {
            let (lo, hi) = s.aabb();
            let inflated = match s {
                Shape::Box { c, h, yaw } => Shape::Box {
                    c,
                    h: h.map(|v| v + 1e-9),
                    yaw,
                },
                Shape::Cyl { c, r, z0, z1 } => Shape::Cyl {
                    c,
                    r: r + 1e-9,
                    z0: z0 - 1e-9,
                    z1: z1 + 1e-9,
                },
                Shape::Ell { c, r } => Shape::Ell {
                    c,
                    r: r.map(|v| v * (1.0 + 1e-9)),
                },
            };
            for p in s.skeleton(0.1) {
                assert!(inflated.contains(p), "{s:?} {p:?}");
                for k in 0..3 {
                    assert!(p[k] >= lo[k] - 1e-9 && p[k] <= hi[k] + 1e-9);
                }
            }
        }
        // rotated box: brute-force check that contained points are inside the AABB
        let b = Shape::Box {
            c: [0.0, 0.0, 0.0],
            h: [2.0, 1.0, 0.5],
            yaw: 0.4,
        };
        let (lo, hi) = b.aabb();
        for i in -30..=30 {
            for j in -30..=30 {
                let p = [i as f64 * 0.1, j as f64 * 0.1, 0.0];
                if b.contains(p) {
                    assert!(p[0] >= lo[0] && p[0] <= hi[0] && p[1] >= lo[1] && p[1] <= hi[1]);
                }
            }
        }
    }

    #[test]
    fn layout_is_deterministic_and_keeps_ego_corridor_free() {
        let a = generate_layout(5, Style::Kitti, -40.0, 200.0, region());
        let b = generate_layout(5, Style::Kitti, -40.0, 200.0, region());
        assert_eq!(a, b);
        let c = generate_layout(6, Style::Kitti, -40.0, 200.0, region());
        assert_ne!(a, c);
        let ey = a.plan.ego_y;
        assert_eq!(a.plan.ground(10.0, ey, 0.1).0, ROAD);
        for o in &a.objects {
            let (lo, hi) = o.aabb();
            assert!(
                hi[1] <= ey - 1.3 || lo[1] >= ey + 1.3 || lo[2] >= 4.5,
                "object in ego corridor: {lo:?} {hi:?}"
            );
        }
    }

    #[test]
    fn every_required_class_is_placed_in_the_region() {
        for seed in 0..20 {
            for style in [Style::Kitti, Style::Nuscenes] {
                let l = generate_layout(seed, style, -40.0, 200.0, region());
                let r = region();
                let r = Region {
                    lo: [r.lo[0], r.lo[1] + l.plan.ego_y, r.lo[2]],
                    hi: [r.hi[0], r.hi[1] + l.plan.ego_y, r.hi[2]],
                };
                for cls in required_object_classes(style) {
                    let found = l.objects.iter().any(|o| {
                        o.prims
                            .iter()
                            .any(|p| p.class == cls && overlaps(&p.shape.aabb(), &(r.lo, r.hi)))
                    });
                    assert!(found, "seed {seed} style {style:?} class {cls}");
                }
                for cls in [ROAD, PARKING, SIDEWALK, OTHER_GROUND, TERRAIN] {
                    let mut found = false;
                    for xi in 0..50 {
                        for yi in 0..100 {
                            if l.plan
                                .ground(xi as f64 + 0.5, r.lo[1] + yi as f64 * 0.5, 0.1)
                                .0
                                == cls
                            {
                                found = true;
                            }
                        }
                    }
                    assert!(found, "seed {seed} ground class {cls}");
                }
            }
        }
    }
}
