//! What stands on the land beyond a sidewalk, by [`Zone`]: urban buildings with fences, trees
//! and cars in the gaps; green land with fences or hedges, trees, bushes and a house; parking
//! lots; industrial yards with warehouses, fences, trucks and trailers.

use super::builder::Gen;
use super::road::sgn;
use super::{Block, Zone};
use crate::synthetic::classes::*;
use rand::Rng;
use std::f64::consts::FRAC_PI_2;

impl Gen<'_> {
    pub(super) fn zone(&mut self, b: Block, side: usize) {
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
}
