//! [`generate_layout`]: draws the road plan (lanes, median, parking, sidewalks, cross streets,
//! blocks and their zones), ensures the ground classes, then places objects block by block, at
//! the crossings and in the lanes, clears the ego corridor and ensures the object classes.

use super::builder::Gen;
use super::coverage::{ensure_ground_classes, ensure_object_classes};
use super::{overlaps, Block, Crossing, Layout, Region, RoadPlan, Style, Zone};
use crate::synthetic::classes::*;
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;

/// Generate the layout for x in `[x_min, x_max]`. `region_rel` is where every class must appear
/// (the first frame's grid volume), with y relative to the ego lane centre.
pub(crate) fn generate_layout(
    seed: u64,
    style: Style,
    x_min: f64,
    x_max: f64,
    region_rel: Region,
) -> Layout {
    let mut rng = ChaCha8Rng::seed_from_u64(seed);
    let lanes = [rng.random_range(1..=2usize), rng.random_range(1..=2usize)];
    let lane_w = rng.random_range(3.2..3.8);
    let (median_w, median_class) = if rng.random::<f64>() < 0.3 {
        (
            rng.random_range(1.5..4.0),
            if rng.random::<bool>() {
                TERRAIN
            } else {
                OTHER_GROUND
            },
        )
    } else {
        (0.0, TERRAIN)
    };
    let parking_w = rng.random_range(2.2..2.6);
    let sidewalk_w = rng.random_range(1.8..4.0);
    let ego_lane = rng.random_range(0..lanes[0]);
    let ego_y = -(0.5 * median_w + (ego_lane as f64 + 0.5) * lane_w);
    let region = Region {
        lo: [region_rel.lo[0], region_rel.lo[1] + ego_y, region_rel.lo[2]],
        hi: [region_rel.hi[0], region_rel.hi[1] + ego_y, region_rel.hi[2]],
    };
    let mut crossings = Vec::new();
    let mut x = x_min + rng.random_range(20.0..90.0);
    while x < x_max {
        let w = rng.random_range(9.0..14.0);
        crossings.push(Crossing {
            x0: x,
            x1: x + w,
            sidewalk_w: rng.random_range(1.5..3.0),
        });
        x += w + rng.random_range(60.0..150.0);
    }
    let zone = |rng: &mut ChaCha8Rng| -> Zone {
        let u: f64 = rng.random();
        if u < 0.4 {
            let plaza = if rng.random::<f64>() < 0.6 {
                SIDEWALK
            } else {
                OTHER_GROUND
            };
            Zone::Urban {
                plaza,
                setback: rng.random_range(0.5..6.0),
            }
        } else if u < 0.7 {
            Zone::Green
        } else if u < 0.85 {
            Zone::Lot {
                depth: rng.random_range(10.0..16.0),
            }
        } else {
            Zone::Industrial
        }
    };
    let mut blocks = Vec::new();
    let mut bx = x_min - 200.0;
    for c in crossings.iter().chain(std::iter::once(&Crossing {
        x0: x_max + 200.0,
        x1: x_max + 200.0,
        sidewalk_w: 0.0,
    })) {
        let zs = [zone(&mut rng), zone(&mut rng)];
        let parking = [rng.random::<f64>() < 0.55, rng.random::<f64>() < 0.55];
        blocks.push(Block {
            x0: bx,
            x1: c.x0,
            zone: zs,
            parking,
        });
        bx = c.x1;
    }
    let mut plan = RoadPlan {
        lanes,
        lane_w,
        median_w,
        median_class,
        parking_w,
        sidewalk_w,
        crossings,
        blocks,
        noise_seed: rng.random(),
        ego_y,
    };
    ensure_ground_classes(&mut plan, &mut rng, region);

    let mut g = Gen {
        rng,
        plan: &plan,
        style,
        objects: Vec::new(),
    };
    for b in plan.blocks.clone() {
        let b = Block {
            x0: b.x0.max(x_min),
            x1: b.x1.min(x_max),
            ..b
        };
        if b.x1 > b.x0 + 2.0 {
            g.roadside(b);
        }
    }
    for c in plan.crossings.clone() {
        g.crossing_objects(c);
    }
    g.traffic(x_min, x_max);
    // keep the ego corridor free of anything the ego would drive through
    let corridor = (
        [x_min - 1e3, plan.ego_y - 1.3, -1.0],
        [x_max + 1e3, plan.ego_y + 1.3, 4.5],
    );
    g.objects.retain(|o| !overlaps(&o.aabb(), &corridor));
    ensure_object_classes(&mut g, region, corridor);
    let objects = g.objects;
    Layout { plan, objects }
}
