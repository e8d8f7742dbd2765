//! Scene classes of the synthetic world, their mappings to the dataset label spaces, and their
//! appearance (base colour, LiDAR reflectivity).
//!
//! The world stores one *scene class* per voxel (`u8`). Ids 1..=19 are exactly the
//! SemanticKITTI learning classes (docs/formats.md §2.4 remap table: 1 car … 19 traffic-sign), so
//! `LearningMap::to_raw` turns them into raw ids. Ids 20..=24 are object kinds that exist only
//! as finer nuScenes classes (bus, trailer, construction vehicle, barrier, traffic cone); they map
//! onto the nearest SemanticKITTI raw id (bus 13, trailer/construction vehicle 20 → learning
//! class 5 other-vehicle, barrier 51 fence, traffic cone 99 other-object → ignored).
//!
//! Appearance: every class has a base colour whose *chromaticity* (r/(r+g+b), g/(r+g+b)) is
//! at least 0.04 away from every other class's; all texture, shading and distance effects of the
//! renderer are luminance-only (multiplicative on all channels) up to 50 m, so the chromaticity
//! of a pixel identifies the class of the surface it shows.

use occ_labels::IGNORE;

/// Empty space (the label convention's [`occ_labels::EMPTY`]).
pub const EMPTY: u8 = occ_labels::EMPTY;
/// SemanticKITTI learning class 1.
pub const CAR: u8 = 1;
/// SemanticKITTI learning class 2.
pub const BICYCLE: u8 = 2;
/// SemanticKITTI learning class 3.
pub const MOTORCYCLE: u8 = 3;
/// SemanticKITTI learning class 4.
pub const TRUCK: u8 = 4;
/// SemanticKITTI learning class 5.
pub const OTHER_VEHICLE: u8 = 5;
/// SemanticKITTI learning class 6.
pub const PERSON: u8 = 6;
/// SemanticKITTI learning class 7 (rider and bicycle together).
pub const BICYCLIST: u8 = 7;
/// SemanticKITTI learning class 8 (rider and motorcycle together).
pub const MOTORCYCLIST: u8 = 8;
/// SemanticKITTI learning class 9.
pub const ROAD: u8 = 9;
/// SemanticKITTI learning class 10.
pub const PARKING: u8 = 10;
/// SemanticKITTI learning class 11.
pub const SIDEWALK: u8 = 11;
/// SemanticKITTI learning class 12.
pub const OTHER_GROUND: u8 = 12;
/// SemanticKITTI learning class 13.
pub const BUILDING: u8 = 13;
/// SemanticKITTI learning class 14.
pub const FENCE: u8 = 14;
/// SemanticKITTI learning class 15.
pub const VEGETATION: u8 = 15;
/// SemanticKITTI learning class 16.
pub const TRUNK: u8 = 16;
/// SemanticKITTI learning class 17.
pub const TERRAIN: u8 = 17;
/// SemanticKITTI learning class 18.
pub const POLE: u8 = 18;
/// SemanticKITTI learning class 19.
pub const TRAFFIC_SIGN: u8 = 19;
/// Bus (SemanticKITTI raw 13 → other-vehicle; nuScenes 3).
pub const BUS: u8 = 20;
/// Trailer (SemanticKITTI raw 20 → other-vehicle; nuScenes 9).
pub const TRAILER: u8 = 21;
/// Construction vehicle (SemanticKITTI raw 20 → other-vehicle; nuScenes 5).
pub const CONSTRUCTION_VEHICLE: u8 = 22;
/// Barrier (SemanticKITTI raw 51 fence; nuScenes 1).
pub const BARRIER: u8 = 23;
/// Traffic cone (SemanticKITTI raw 99 other-object → ignore; nuScenes 8).
pub const TRAFFIC_CONE: u8 = 24;
/// Number of scene classes including empty.
pub const NUM_SCENE_CLASSES: usize = 25;

/// Base colour (sRGB 0..255) of each scene class; index 0 (empty) is unused.
pub const BASE_COLOR: [[u8; 3]; NUM_SCENE_CLASSES] = [
    [0, 0, 0],
    [40, 70, 200],   // car
    [220, 210, 20],  // bicycle
    [150, 40, 130],  // motorcycle
    [200, 100, 20],  // truck
    [30, 160, 160],  // other-vehicle
    [240, 70, 110],  // person
    [230, 20, 240],  // bicyclist
    [110, 30, 240],  // motorcyclist
    [80, 82, 110],   // road
    [125, 90, 125],  // parking
    [180, 160, 150], // sidewalk
    [160, 120, 60],  // other-ground
    [190, 110, 90],  // building
    [160, 140, 30],  // fence
    [40, 140, 40],   // vegetation
    [110, 65, 30],   // trunk
    [130, 170, 70],  // terrain
    [90, 125, 140],  // pole
    [230, 25, 25],   // traffic-sign
    [220, 60, 140],  // bus
    [120, 160, 110], // trailer
    [240, 150, 0],   // construction vehicle
    [205, 200, 140], // barrier
    [250, 90, 30],   // traffic cone
];

/// Relative LiDAR reflectivity in 0..1 (the `intensity` channel of the simulated scan).
pub const REFLECTIVITY: [f32; NUM_SCENE_CLASSES] = [
    0.0, 0.45, 0.3, 0.35, 0.4, 0.4, 0.25, 0.25, 0.3, 0.2, 0.22, 0.3, 0.25, 0.35, 0.3, 0.5, 0.2,
    0.45, 0.55, 0.9, 0.4, 0.4, 0.45, 0.6, 0.8,
];

/// SemanticKITTI learning class (0..=19, 255 = ignore) of a scene class.
pub fn kitti_learning_class(c: u8) -> u8 {
    match c {
        0..=19 => c,
        BUS | TRAILER | CONSTRUCTION_VEHICLE => OTHER_VEHICLE,
        BARRIER => FENCE,
        _ => IGNORE,
    }
}

/// Raw SemanticKITTI id for a scene class that is not a learning class, or `None` for 0..=19
/// (those go through `LearningMap::to_raw`).
pub fn kitti_raw_extra(c: u8) -> Option<u16> {
    match c {
        BUS => Some(13),
        TRAILER | CONSTRUCTION_VEHICLE => Some(20),
        BARRIER => Some(51),
        TRAFFIC_CONE => Some(99),
        _ => None,
    }
}

/// nuScenes-lidarseg / Occ3D class id (0..=16) of an occupied scene class; `EMPTY` maps to
/// [`OCC3D_FREE`].
pub fn nuscenes_class(c: u8) -> u8 {
    match c {
        EMPTY => OCC3D_FREE,
        CAR => 4,
        BICYCLE | BICYCLIST => 2,
        MOTORCYCLE | MOTORCYCLIST => 6,
        TRUCK => 10,
        OTHER_VEHICLE | BUS => 3,
        PERSON => 7,
        ROAD | PARKING => 11,
        SIDEWALK => 13,
        OTHER_GROUND => 12,
        BUILDING | FENCE | POLE | TRAFFIC_SIGN => 15,
        VEGETATION | TRUNK => 16,
        TERRAIN => 14,
        TRAILER => 9,
        CONSTRUCTION_VEHICLE => 5,
        BARRIER => 1,
        TRAFFIC_CONE => 8,
        _ => 0,
    }
}

/// Occ3D "free" class id (docs/formats.md §4).
pub const OCC3D_FREE: u8 = 17;

/// Chromaticity `(r, g)` = `(R/(R+G+B), G/(R+G+B))` of a colour; `None` for black.
pub fn chromaticity(rgb: [u8; 3]) -> Option<[f64; 2]> {
    let s = rgb[0] as f64 + rgb[1] as f64 + rgb[2] as f64;
    if s <= 0.0 {
        return None;
    }
    Some([rgb[0] as f64 / s, rgb[1] as f64 / s])
}

/// The scene class (1..NUM_SCENE_CLASSES) whose base colour has the nearest chromaticity to
/// `rgb`, among `candidates`; `None` for black or no candidates. Used to check that rendered
/// appearance carries the class.
pub fn nearest_class_by_chroma(rgb: [u8; 3], candidates: &[u8]) -> Option<u8> {
    let q = chromaticity(rgb)?;
    let mut best: Option<(f64, u8)> = None;
    for &c in candidates {
        let Some(b) = BASE_COLOR
            .get(c as usize)
            .and_then(|col| chromaticity(*col))
        else {
            continue;
        };
        let d = (q[0] - b[0]).powi(2) + (q[1] - b[1]).powi(2);
        if best.is_none_or(|(bd, _)| d < bd) {
            best = Some((d, c));
        }
    }
    best.map(|(_, c)| c)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn base_colours_are_chromatically_separated() {
        let mut min_d = f64::INFINITY;
        for (a, col_a) in BASE_COLOR.iter().enumerate().skip(1) {
            for col_b in BASE_COLOR.iter().skip(a + 1) {
                let ca = chromaticity(*col_a).unwrap();
                let cb = chromaticity(*col_b).unwrap();
                let d = ((ca[0] - cb[0]).powi(2) + (ca[1] - cb[1]).powi(2)).sqrt();
                min_d = min_d.min(d);
            }
        }
        assert!(min_d >= 0.04, "min chromaticity distance {min_d}");
    }

    #[test]
    fn mappings_cover_every_class() {
        for c in 1..NUM_SCENE_CLASSES as u8 {
            let l = kitti_learning_class(c);
            assert!(l <= 19 || l == IGNORE);
            let n = nuscenes_class(c);
            assert!((1..=16).contains(&n), "class {c} -> nuScenes {n}");
            if c > 19 {
                assert!(kitti_raw_extra(c).is_some());
            }
        }
        assert_eq!(nuscenes_class(EMPTY), OCC3D_FREE);
        // every nuScenes class 1..=16 is produced by some scene class
        for n in 1..=16u8 {
            assert!(
                (1..NUM_SCENE_CLASSES as u8).any(|c| nuscenes_class(c) == n),
                "nuScenes class {n}"
            );
        }
    }

    #[test]
    fn nearest_class_recovers_shaded_base_colours() {
        let all: Vec<u8> = (1..NUM_SCENE_CLASSES as u8).collect();
        for &c in &all {
            for f in [0.45, 0.7, 1.0] {
                let b = BASE_COLOR[c as usize];
                let rgb = [0, 1, 2].map(|i| ((b[i] as f64 * f).round()).min(255.0) as u8);
                assert_eq!(
                    nearest_class_by_chroma(rgb, &all),
                    Some(c),
                    "class {c} factor {f}"
                );
            }
        }
    }
}
