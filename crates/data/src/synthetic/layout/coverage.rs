//! The class-coverage guarantee: every ground class and every object class the style requires
//! must appear in the region (the first frame's grid volume). Ground classes are ensured by
//! changing the blocks' parking flags and zones before any object is placed; missing object
//! classes are then placed by force (`place_forced`), displacing random objects if needed.

use super::builder::Gen;
use super::road::sgn;
use super::{overlaps, required_object_classes, Object, Region, RoadPlan, Zone};
use crate::synthetic::classes::*;
use rand::Rng;
use rand_chacha::ChaCha8Rng;
use std::f64::consts::{FRAC_PI_2, PI};

/// Make sure road, parking, sidewalk, other-ground and terrain occur in `region`, by changing
/// the parking flags and zones of the blocks overlapping it.
pub(super) fn ensure_ground_classes(plan: &mut RoadPlan, rng: &mut ChaCha8Rng, region: Region) {
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

pub(super) fn ensure_object_classes(
    g: &mut Gen<'_>,
    region: Region,
    corridor: ([f64; 3], [f64; 3]),
) {
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
