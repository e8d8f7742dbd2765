//! Builders for bicycles and motorcycles (parked), bicyclists and motorcyclists (the two-wheeler
//! with its rider, one class for both), and pedestrians.

use super::builder::Gen;
use super::{Prim, SH_DARK, SH_DIM, SH_NEUTRAL, SH_SOFT};
use crate::synthetic::classes::*;

impl Gen<'_> {
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

    pub(super) fn bicycle(&mut self, x: f64, y: f64, yaw: f64) -> Vec<Prim> {
        let z0 = self.ground_z(x, y);
        Self::bicycle_parts(BICYCLE, x, y, z0, yaw)
    }

    pub(super) fn motorcycle(&mut self, x: f64, y: f64, yaw: f64) -> Vec<Prim> {
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

    pub(super) fn bicyclist(&mut self, x: f64, y: f64, yaw: f64) -> Vec<Prim> {
        let z0 = self.ground_z(x, y);
        let sh = self.body_shade();
        let mut v = Self::bicycle_parts(BICYCLIST, x, y, z0, yaw);
        v.extend(Self::rider(BICYCLIST, sh, x, y, z0, yaw, 0.95));
        v
    }

    pub(super) fn motorcyclist(&mut self, x: f64, y: f64, yaw: f64) -> Vec<Prim> {
        let z0 = self.ground_z(x, y);
        let sh = self.body_shade();
        let mut v = Self::motorcycle_parts(MOTORCYCLIST, x, y, z0, yaw);
        v.extend(Self::rider(MOTORCYCLIST, sh, x, y, z0, yaw, 0.95));
        v
    }

    pub(super) fn person(&mut self, x: f64, y: f64, yaw: f64) -> Vec<Prim> {
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
}
