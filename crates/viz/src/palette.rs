//! Class palettes (RGB) and the height colour ramp.
//!
//! - SemanticKITTI: the 20 learning classes (docs/formats.md §2.4), coloured with the semantic-kitti-api
//!   `color_map` of each class's raw id (`learning_map_inv`), converted from the API's BGR order
//!   to RGB.
//! - Occ3D-nuScenes: 18 classes, 0 `others` .. 16 `vegetation`, 17 `free` (docs/formats.md §4), in the
//!   colours commonly used by Occ3D/SurroundOcc visualisations.
//! - nuScenes-Occupancy (OpenOccupancy): 17 classes, 0 `empty` then the 16 nuScenes-lidarseg
//!   classes 1 `barrier` .. 16 `vegetation` (docs/formats.md §3), with the same colours as Occ3D.
//!
//! Class names come from `occ_data::formats::{semantic_kitti, occ3d, nuscenes_occupancy}`.

use occ_data::formats::{nuscenes_occupancy, occ3d, semantic_kitti};

/// Which dataset's classes (names, colours, default empty class) a label grid uses.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash)]
pub enum Palette {
    /// SemanticKITTI SSC, 20 classes, 0 = empty.
    SemanticKitti,
    /// Occ3D-nuScenes, 18 classes, 17 = free (empty).
    Occ3d,
    /// nuScenes-Occupancy (OpenOccupancy), 17 classes, 0 = empty.
    NuScenesOccupancy,
}

/// semantic-kitti-api `color_map` (BGR there) of learning_map_inv[class], written as RGB.
const SEMANTIC_KITTI_RGB: [[u8; 3]; 20] = [
    [0, 0, 0],       // empty (raw 0)
    [100, 150, 245], // car (10)
    [100, 230, 245], // bicycle (11)
    [30, 60, 150],   // motorcycle (15)
    [80, 30, 180],   // truck (18)
    [0, 0, 255],     // other-vehicle (20)
    [255, 30, 30],   // person (30)
    [255, 40, 200],  // bicyclist (31)
    [150, 30, 90],   // motorcyclist (32)
    [255, 0, 255],   // road (40)
    [255, 150, 255], // parking (44)
    [75, 0, 75],     // sidewalk (48)
    [175, 0, 75],    // other-ground (49)
    [255, 200, 0],   // building (50)
    [255, 120, 50],  // fence (51)
    [0, 175, 0],     // vegetation (70)
    [135, 60, 0],    // trunk (71)
    [150, 240, 80],  // terrain (72)
    [255, 240, 150], // pole (80)
    [255, 0, 0],     // traffic-sign (81)
];

/// Colours of the 16 nuScenes-lidarseg classes 1 `barrier` .. 16 `vegetation`, shared by Occ3D
/// and nuScenes-Occupancy.
const NUSC_RGB: [[u8; 3]; 16] = [
    [255, 120, 50],  // barrier
    [255, 192, 203], // bicycle
    [255, 255, 0],   // bus
    [0, 150, 245],   // car
    [0, 255, 255],   // construction_vehicle
    [200, 180, 0],   // motorcycle
    [255, 0, 0],     // pedestrian
    [255, 240, 150], // traffic_cone
    [135, 60, 0],    // trailer
    [160, 32, 240],  // truck
    [255, 0, 255],   // driveable_surface
    [139, 137, 137], // other_flat
    [75, 0, 75],     // sidewalk
    [150, 240, 80],  // terrain
    [230, 230, 250], // manmade
    [0, 175, 0],     // vegetation
];

/// Colour used for class ids outside the palette (so a bad label is visible, not hidden).
pub const UNKNOWN_CLASS_RGB: [u8; 3] = [128, 128, 128];

impl Palette {
    /// Number of classes (20, 18, 17).
    pub fn num_classes(self) -> usize {
        match self {
            Palette::SemanticKitti => 20,
            Palette::Occ3d => 18,
            Palette::NuScenesOccupancy => 17,
        }
    }

    /// The class id that means "empty/free" in this dataset (0, 17, 0); not drawn by default.
    pub fn default_empty_class(self) -> u8 {
        match self {
            Palette::SemanticKitti | Palette::NuScenesOccupancy => occ_labels::EMPTY,
            Palette::Occ3d => 17,
        }
    }

    /// Name of `class`, or `None` outside the palette.
    pub fn name(self, class: u8) -> Option<&'static str> {
        let c = class as usize;
        match self {
            Palette::SemanticKitti => semantic_kitti::CLASS_NAMES.get(c).copied(),
            Palette::Occ3d => occ3d::CLASS_NAMES.get(c).copied(),
            Palette::NuScenesOccupancy => nuscenes_occupancy::CLASS_NAMES.get(c).copied(),
        }
    }

    /// RGB colour of `class`, or `None` outside the palette.
    pub fn color(self, class: u8) -> Option<[u8; 3]> {
        let c = class as usize;
        match self {
            Palette::SemanticKitti => SEMANTIC_KITTI_RGB.get(c).copied(),
            Palette::Occ3d => match c {
                0 => Some([0, 0, 0]),
                1..=16 => Some(NUSC_RGB[c - 1]),
                17 => Some([255, 255, 255]),
                _ => None,
            },
            Palette::NuScenesOccupancy => match c {
                0 => Some([0, 0, 0]),
                1..=16 => Some(NUSC_RGB[c - 1]),
                _ => None,
            },
        }
    }

    /// RGB colour of `class`, grey ([`UNKNOWN_CLASS_RGB`]) outside the palette.
    pub fn color_or_unknown(self, class: u8) -> [u8; 3] {
        self.color(class).unwrap_or(UNKNOWN_CLASS_RGB)
    }

    /// Colour table for all 256 label values (unknown ids grey), for fast lookup.
    pub fn lut(self) -> [[u8; 3]; 256] {
        let mut lut = [UNKNOWN_CLASS_RGB; 256];
        for (c, px) in lut.iter_mut().enumerate() {
            if let Some(rgb) = self.color(c as u8) {
                *px = rgb;
            }
        }
        lut
    }
}

/// Control points of the height ramp: deep blue (low) → cyan → green → yellow → red (high).
const HEIGHT_RAMP: [(f32, [f32; 3]); 6] = [
    (0.0, [48.0, 18.0, 160.0]),
    (0.2, [40.0, 110.0, 230.0]),
    (0.4, [30.0, 200.0, 200.0]),
    (0.6, [90.0, 220.0, 80.0]),
    (0.8, [250.0, 210.0, 40.0]),
    (1.0, [220.0, 50.0, 30.0]),
];

/// Height colour for `t` in [0, 1] (clamped; NaN maps to 0): piecewise-linear ramp
/// blue → cyan → green → yellow → red.
pub fn height_color(t: f32) -> [u8; 3] {
    let t = if t.is_nan() { 0.0 } else { t.clamp(0.0, 1.0) };
    for w in HEIGHT_RAMP.windows(2) {
        let (t0, c0) = w[0];
        let (t1, c1) = w[1];
        if t <= t1 {
            let a = (t - t0) / (t1 - t0);
            return [
                (c0[0] + (c1[0] - c0[0]) * a).round() as u8,
                (c0[1] + (c1[1] - c0[1]) * a).round() as u8,
                (c0[2] + (c1[2] - c0[2]) * a).round() as u8,
            ];
        }
    }
    let c = HEIGHT_RAMP[HEIGHT_RAMP.len() - 1].1;
    [c[0] as u8, c[1] as u8, c[2] as u8]
}

const DEPTH_RAMP: [(f32, [f32; 3]); 5] = [
    (0.0, [255.0, 40.0, 40.0]),
    (0.25, [255.0, 200.0, 0.0]),
    (0.5, [60.0, 230.0, 60.0]),
    (0.75, [0.0, 200.0, 255.0]),
    (1.0, [120.0, 70.0, 255.0]),
];

/// Depth colour for `t` in [0, 1] (clamped; NaN maps to 0): near red → yellow → green → cyan →
/// far violet (the LiDAR points of the surround-camera panels).
pub fn depth_color(t: f32) -> [u8; 3] {
    let t = if t.is_nan() { 0.0 } else { t.clamp(0.0, 1.0) };
    for w in DEPTH_RAMP.windows(2) {
        let (t0, c0) = w[0];
        let (t1, c1) = w[1];
        if t <= t1 {
            let a = (t - t0) / (t1 - t0);
            return [0, 1, 2].map(|i| (c0[i] + (c1[i] - c0[i]) * a).round() as u8);
        }
    }
    DEPTH_RAMP[DEPTH_RAMP.len() - 1].1.map(|v| v as u8)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn palette_sizes_and_empty_classes() {
        assert_eq!(SEMANTIC_KITTI_RGB.len(), semantic_kitti::CLASS_NAMES.len());
        assert_eq!(Palette::Occ3d.num_classes(), occ3d::CLASS_NAMES.len());
        assert_eq!(
            Palette::NuScenesOccupancy.num_classes(),
            nuscenes_occupancy::CLASS_NAMES.len()
        );
        assert_eq!(Palette::Occ3d.default_empty_class(), occ3d::FREE);
        for (p, n, empty) in [
            (Palette::SemanticKitti, 20, 0u8),
            (Palette::Occ3d, 18, 17),
            (Palette::NuScenesOccupancy, 17, 0),
        ] {
            assert_eq!(p.num_classes(), n);
            for c in 0..n {
                assert!(p.name(c as u8).is_some(), "{p:?} class {c}");
                assert!(p.color(c as u8).is_some(), "{p:?} class {c}");
            }
            assert!(p.name(n as u8).is_none());
            assert!(p.color(n as u8).is_none());
            assert_eq!(p.color_or_unknown(255), UNKNOWN_CLASS_RGB);
            assert_eq!(p.default_empty_class(), empty);
            let en = p.name(empty).unwrap_or_default();
            assert!(en == "empty" || en == "free", "{p:?}: {en}");
        }
    }

    #[test]
    fn semantic_kitti_colours_are_the_api_colours_in_rgb() {
        // Spot checks against semantic-kitti-api color_map (BGR): car 10 -> [245,150,100],
        // building 50 -> [0,200,255], vegetation 70 -> [0,175,0], terrain 72 -> [80,240,150].
        let p = Palette::SemanticKitti;
        assert_eq!(p.name(1), Some("car"));
        assert_eq!(p.color(1), Some([100, 150, 245]));
        assert_eq!(p.name(13), Some("building"));
        assert_eq!(p.color(13), Some([255, 200, 0]));
        assert_eq!(p.color(15), Some([0, 175, 0]));
        assert_eq!(p.color(17), Some([150, 240, 80]));
        assert_eq!(p.name(19), Some("traffic-sign"));
    }

    #[test]
    fn nuscenes_palettes_share_the_16_classes() {
        for c in 1..=16u8 {
            assert_eq!(Palette::Occ3d.name(c), Palette::NuScenesOccupancy.name(c));
            assert_eq!(Palette::Occ3d.color(c), Palette::NuScenesOccupancy.color(c));
        }
        assert_eq!(Palette::Occ3d.name(4), Some("car"));
        assert_eq!(Palette::Occ3d.name(11), Some("driveable_surface"));
        assert_eq!(Palette::Occ3d.name(17), Some("free"));
    }

    #[test]
    fn lut_matches_color() {
        let lut = Palette::Occ3d.lut();
        for c in 0..=255u8 {
            assert_eq!(lut[c as usize], Palette::Occ3d.color_or_unknown(c));
        }
    }

    #[test]
    fn height_ramp_endpoints_and_monotone_hue_path() {
        assert_eq!(height_color(0.0), [48, 18, 160]);
        assert_eq!(height_color(1.0), [220, 50, 30]);
        assert_eq!(height_color(-3.0), height_color(0.0));
        assert_eq!(height_color(f32::NAN), height_color(0.0));
        assert_eq!(height_color(0.6), [90, 220, 80]);
        // Low is blue-dominant, high is red-dominant.
        let lo = height_color(0.05);
        let hi = height_color(0.95);
        assert!(lo[2] > lo[0] && hi[0] > hi[2]);
    }
}
