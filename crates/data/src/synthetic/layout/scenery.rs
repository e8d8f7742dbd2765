//! Builders for the static scenery: trees (trunk + porous crown), bushes, hedges and fences
//! (`wall`), and buildings with a window facade.

use super::builder::Gen;
use super::road::sgn;
use super::{Pattern, Prim, Shape, SH_BRIGHT, SH_DIM, SH_LIGHT, SH_NEUTRAL, SH_SOFT};
use crate::synthetic::classes::*;
use std::f64::consts::FRAC_PI_2;

impl Gen<'_> {
    pub(super) fn tree(&mut self, x: f64, y: f64, big: bool) -> Vec<Prim> {
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

    pub(super) fn bush(&mut self, x: f64, y: f64) -> Vec<Prim> {
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
    pub(super) fn wall(
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

    /// Building with its street facade along x at `|y| = y_near` on `side`.
    #[allow(clippy::too_many_arguments)]
    pub(super) fn building(
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
}
