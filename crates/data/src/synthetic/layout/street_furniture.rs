//! Builders for street furniture: street lights, traffic signs on poles, traffic lights, and the
//! traffic cones and barriers of nuScenes-style construction sites.

use super::builder::Gen;
use super::{Pattern, Prim, Shape, SH_BRIGHT, SH_DIM, SH_LIGHT, SH_NEUTRAL, SH_SOFT};
use crate::synthetic::classes::*;

impl Gen<'_> {
    pub(super) fn street_light(&mut self, x: f64, y: f64, toward_road: f64) -> Vec<Prim> {
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

    pub(super) fn sign(&mut self, x: f64, y: f64) -> Vec<Prim> {
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

    pub(super) fn traffic_light(&mut self, x: f64, y: f64) -> Vec<Prim> {
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

    pub(super) fn cone(&mut self, x: f64, y: f64) -> Vec<Prim> {
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

    pub(super) fn barrier(&mut self, x: f64, y: f64, yaw: f64) -> Vec<Prim> {
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
}
