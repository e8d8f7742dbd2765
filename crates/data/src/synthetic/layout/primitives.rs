//! The solid primitives objects are made of: [`Shape`] (box, vertical cylinder, ellipsoid) with
//! its bounding box, inside test and skeleton, a [`Prim`] (shape + class + shade code + shade
//! [`Pattern`]), an [`Object`] (a group of primitives), and the 3-bit shade codes.

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
