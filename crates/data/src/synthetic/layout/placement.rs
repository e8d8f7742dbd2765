//! Placement along the street: stopped traffic in the lanes (`traffic`), the roadside of each
//! block (`roadside`: parked vehicles, street lights, trees, signs, people and two-wheelers on the
//! sidewalk, a construction site in nuScenes style, then the zone beyond, see `zones.rs`), and
//! traffic lights, waiting cars and pedestrians at the cross streets (`crossing_objects`).

use super::builder::Gen;
use super::road::sgn;
use super::{Block, Crossing, RoadPlan, Style};
use crate::synthetic::classes::*;
use rand::Rng;
use std::f64::consts::{FRAC_PI_2, PI};

/// Heading of traffic on `side`: +x on the right, −x on the left.
fn lane_yaw(side: usize) -> f64 {
    if side == 0 {
        0.0
    } else {
        PI
    }
}

impl Gen<'_> {
    pub(super) fn traffic(&mut self, x_min: f64, x_max: f64) {
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

    pub(super) fn roadside(&mut self, b: Block) {
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

    pub(super) fn crossing_objects(&mut self, c: Crossing) {
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
