//! Procedural street layout in metres, independent of the voxel size.
//!
//! World frame: x along the main road (the ego drives towards +x), y to the left, z up, with the
//! road surface at z = 0. The layout is a [`RoadPlan`] (a ground function giving class and surface
//! height for every (x, y) column: lanes, optional median, parking strips, sidewalks with curbs,
//! crossings with zebra stripes, and roadside zones) plus a list of [`Object`]s made of simple
//! solid primitives (boxes, vertical cylinders, ellipsoids): buildings, fences, trees, bushes,
//! poles, traffic signs and lights, parked and stopped vehicles, two-wheelers, riders and
//! pedestrians. The same seed gives the same layout at every voxel size.
//!
//! The generator is split by what each part produces; every object builder and placement stage
//! is a method of the generator state `Gen` (one `impl` block per file):
//!
//! | file | what it holds / generates |
//! |------|---------------------------|
//! | `mod.rs` | [`Style`] and the classes it requires, [`Layout`], [`Region`], [`CURB_H`] |
//! | `generate.rs` | [`generate_layout`]: the road plan, then the placement stages in order |
//! | `road.rs` | [`RoadPlan`], [`Block`], [`Crossing`], [`Zone`]: the ground of every column |
//! | `primitives.rs` | shade codes; [`Shape`], [`Pattern`], [`Prim`], [`Object`] |
//! | `builder.rs` | `Gen`: seeded RNG and draw helpers, objects so far, box parts, wheels |
//! | `vehicles.rs` | cars, vans, trucks, buses, trailers, construction vehicles |
//! | `people.rs` | bicycles, motorcycles, their riders, pedestrians |
//! | `scenery.rs` | trees, bushes, hedges and fences, buildings |
//! | `street_furniture.rs` | street lights, traffic signs and lights, cones, barriers |
//! | `placement.rs` | traffic in the lanes, each block's roadside, objects at crossings |
//! | `zones.rs` | the land beyond the sidewalk, for each [`Zone`] |
//! | `coverage.rs` | every required ground and object class placed in the region |
//! | `tests.rs` | unit tests |

mod builder;
mod coverage;
mod generate;
mod people;
mod placement;
mod primitives;
mod road;
mod scenery;
mod street_furniture;
#[cfg(test)]
mod tests;
mod vehicles;
mod zones;

pub(crate) use generate::generate_layout;
pub(crate) use primitives::{
    Object, Pattern, Prim, Shape, SHADE_FACTOR, SH_BRIGHT, SH_DARK, SH_DIM, SH_LIGHT, SH_MARK,
    SH_NEUTRAL, SH_SOFT, SH_WHITE,
};
pub(crate) use road::{Block, Crossing, RoadPlan, Zone};

use super::classes::*;

/// Curb height of sidewalks and medians above the road (m).
pub(crate) const CURB_H: f64 = 0.15;

/// Which dataset's object mix the world imitates.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub(crate) enum Style {
    /// SemanticKITTI (Karlsruhe): vans as other-vehicle, no cones/barriers.
    Kitti,
    /// nuScenes: buses, trailers, construction vehicles, barriers and traffic cones too.
    Nuscenes,
}

/// A complete layout: ground plan and objects.
#[derive(Clone, Debug, PartialEq)]
pub(crate) struct Layout {
    pub plan: RoadPlan,
    pub objects: Vec<Object>,
}

/// An axis-aligned region (world metres) in which every object class of the style, and the
/// ground classes, must appear (the first frame's grid volume).
#[derive(Clone, Copy, Debug, PartialEq)]
pub(crate) struct Region {
    pub lo: [f64; 3],
    pub hi: [f64; 3],
}

fn overlaps(a: &([f64; 3], [f64; 3]), b: &([f64; 3], [f64; 3])) -> bool {
    (0..3).all(|k| a.0[k] < b.1[k] && b.0[k] < a.1[k])
}

/// Classes that every layout of a style must show in its region.
pub(crate) fn required_object_classes(style: Style) -> Vec<u8> {
    let mut v = vec![
        CAR,
        BICYCLE,
        MOTORCYCLE,
        TRUCK,
        OTHER_VEHICLE,
        PERSON,
        BICYCLIST,
        MOTORCYCLIST,
        BUILDING,
        FENCE,
        VEGETATION,
        TRUNK,
        POLE,
        TRAFFIC_SIGN,
    ];
    if style == Style::Nuscenes {
        v.extend([BUS, TRAILER, CONSTRUCTION_VEHICLE, BARRIER, TRAFFIC_CONE]);
    }
    v
}
