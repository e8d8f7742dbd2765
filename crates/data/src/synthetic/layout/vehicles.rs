//! Vehicle builders: cars, vans (other-vehicle), trucks, buses, trailers and construction
//! vehicles, each made of boxes on wheels; `vehicle_of_kind` builds any moving-object class
//! (two-wheelers and pedestrians too) from its class id, and `kind_length` is its length.

use super::builder::Gen;
use super::{Prim, SH_BRIGHT, SH_DARK, SH_DIM, SH_LIGHT, SH_NEUTRAL, SH_SOFT};
use crate::synthetic::classes::*;

impl Gen<'_> {
    pub(super) fn car(&mut self, x: f64, y: f64, yaw: f64) -> Vec<Prim> {
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

    pub(super) fn van(&mut self, cls: u8, x: f64, y: f64, yaw: f64) -> Vec<Prim> {
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

    pub(super) fn construction_vehicle(&mut self, x: f64, y: f64, yaw: f64) -> Vec<Prim> {
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

    pub(super) fn vehicle_of_kind(&mut self, kind: u8, x: f64, y: f64, yaw: f64) -> Vec<Prim> {
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

    pub(super) fn kind_length(kind: u8) -> f64 {
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
}
