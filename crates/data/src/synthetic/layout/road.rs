//! The ground plan: the road cross-section (lanes, median, parking strips, sidewalks with curbs),
//! its blocks and cross streets along x, and [`RoadPlan::ground`], the class, surface height and
//! shade code of every `(x, y)` column (markings, zebra stripes, plazas, lots, terrain).

use super::{CURB_H, SH_MARK, SH_NEUTRAL};
use crate::synthetic::classes::*;

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
pub(super) fn sgn(side: usize) -> f64 {
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
        0.05 + 0.3 * crate::synthetic::util::value_noise2(self.noise_seed, x / 7.0, y / 7.0)
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
