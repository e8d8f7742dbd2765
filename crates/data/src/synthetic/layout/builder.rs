//! The generator state `Gen`: the seeded random-number generator every stage draws from (in a
//! fixed order, so the same seed gives the same layout), the road plan and style, and the objects
//! placed so far; plus the helpers the object builders share (draws, ground height, box parts,
//! wheels). The object builders themselves are pure: they return the primitives and leave
//! placing them to the caller.

use super::{Object, Pattern, Prim, RoadPlan, Shape, Style};
use super::{SH_BRIGHT, SH_DARK, SH_DIM, SH_LIGHT, SH_NEUTRAL, SH_SOFT};
use rand::Rng;
use rand_chacha::ChaCha8Rng;

pub(super) struct Gen<'a> {
    pub(super) rng: ChaCha8Rng,
    pub(super) plan: &'a RoadPlan,
    pub(super) style: Style,
    pub(super) objects: Vec<Object>,
}

impl Gen<'_> {
    pub(super) fn r(&mut self, lo: f64, hi: f64) -> f64 {
        if hi > lo {
            self.rng.random_range(lo..hi)
        } else {
            lo
        }
    }
    pub(super) fn p(&mut self, prob: f64) -> bool {
        self.rng.random::<f64>() < prob
    }
    pub(super) fn pick<T: Copy>(&mut self, items: &[T]) -> T {
        items[self.rng.random_range(0..items.len())]
    }
    pub(super) fn body_shade(&mut self) -> u8 {
        self.pick(&[SH_NEUTRAL, SH_SOFT, SH_LIGHT, SH_BRIGHT, SH_DIM, SH_NEUTRAL])
    }
    pub(super) fn ground_z(&self, x: f64, y: f64) -> f64 {
        self.plan.ground(x, y, 0.1).1
    }
    pub(super) fn push(&mut self, prims: Vec<Prim>) {
        if !prims.is_empty() {
            self.objects.push(Object {
                prims,
                forced: false,
            });
        }
    }

    /// Box part of an object at `(x, y, z0)` heading `yaw`: local centre offset `(dx, dy)`,
    /// length `l` along the heading, width `w`, from `z_lo` to `z_hi` above `z0`.
    #[allow(clippy::too_many_arguments)]
    pub(super) fn part(
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
    pub(super) fn wheels(
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
}
