//! One sequence: its layout, the ego trajectory, the global voxel lattice, and world windows
//! rasterised around groups of frames.
//!
//! The ego drives straight along +x in one lane; frame `i` has its sensor frame (LiDAR for the
//! KITTI presets, ego for `surround`) at world `(i·step, ego_y, height)` with axes parallel to
//! the world's. `step` is a multiple of the voxel size, so every frame's grid is an exact
//! sub-box of one global lattice and the labels of consecutive frames agree voxel for voxel.

use super::layout::{generate_layout, Layout, Region, Style};
use super::util::derive_seed;
use super::world::{Lattice, World};
use occ_geometry::VoxelGrid;
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;

/// Camera rays end after this distance (m); beyond is sky / haze.
pub(crate) const CAMERA_T_MAX_M: f64 = 120.0;
/// Lateral half width of the generated world around the ego lane (m).
const WORLD_HALF_WIDTH_M: f64 = 60.0;
/// Height of the world above the road surface (m).
const WORLD_TOP_M: f64 = 16.0;
/// Frames of one world window span at most this much travel (m).
const WINDOW_TRAVEL_M: f64 = 100.0;
/// Margin of a world window around the sensors it serves (≥ camera/LiDAR reach plus mounting offsets).
const WINDOW_MARGIN_M: f64 = CAMERA_T_MAX_M + 4.0;

/// Everything about one sequence that does not depend on the world window.
pub(crate) struct SequenceScene {
    pub layout: Layout,
    pub lattice: Lattice,
    /// The per-frame grid in the sensor frame.
    pub grid: VoxelGrid,
    /// World position of the sensor frame origin of every frame.
    pub sensor_pos: Vec<[f64; 3]>,
    /// Distance travelled per frame (m).
    pub step_m: f64,
    /// Seed of textures and porous vegetation.
    pub seed: u64,
}

impl SequenceScene {
    /// Build the layout of sequence `name` with `frames` frames. `sensor_height_m` is the height of
    /// the sensor frame origin above the road; `steps_m` the travel per frame to choose from
    /// (multiples of the voxel size).
    pub(crate) fn new(
        seed: u64,
        name: &str,
        frames: usize,
        style: Style,
        grid: VoxelGrid,
        sensor_height_m: f64,
        steps_m: &[f64],
    ) -> Self {
        let mut rng = ChaCha8Rng::seed_from_u64(derive_seed(seed, &format!("sequence:{name}")));
        let step_m = steps_m[rng.random_range(0..steps_m.len())];
        let x_last = step_m * frames.saturating_sub(1) as f64;
        let g0 = grid.origin_m;
        let gmax = grid.max_m();
        let region = Region {
            lo: [g0[0], g0[1], g0[2] + sensor_height_m],
            hi: [gmax[0], gmax[1], gmax[2] + sensor_height_m],
        };
        let layout_seed = derive_seed(seed, &format!("layout:{name}"));
        let layout = generate_layout(
            layout_seed,
            style,
            g0[0] - 130.0,
            x_last + gmax[0] + 130.0,
            region,
        );
        let ego_y = layout.plan.ego_y;
        let sensor_pos: Vec<[f64; 3]> = (0..frames)
            .map(|i| [i as f64 * step_m, ego_y, sensor_height_m])
            .collect();
        let lattice = Lattice {
            origin_m: [g0[0], ego_y + g0[1], sensor_height_m + g0[2]],
            voxel_size_m: grid.voxel_size_m,
        };
        SequenceScene {
            layout,
            lattice,
            grid,
            sensor_pos,
            step_m,
            seed: derive_seed(seed, &format!("texture:{name}")),
        }
    }

    /// Global lattice index of voxel (0, 0, 0) of frame `i`'s grid.
    pub(crate) fn frame_off(&self, i: usize) -> [i64; 3] {
        let p = self.sensor_pos[i];
        let o = [0, 1, 2].map(|a| p[a] + self.grid.origin_m[a]);
        [0, 1, 2]
            .map(|a| ((o[a] - self.lattice.origin_m[a]) / self.lattice.voxel_size_m).round() as i64)
    }

    /// Groups of consecutive frames whose sensors lie within [`WINDOW_TRAVEL_M`] of the group's first.
    pub(crate) fn frame_groups(&self) -> Vec<std::ops::Range<usize>> {
        let mut out = Vec::new();
        let mut a = 0;
        while a < self.sensor_pos.len() {
            let mut b = a + 1;
            while b < self.sensor_pos.len()
                && self.sensor_pos[b][0] - self.sensor_pos[a][0] <= WINDOW_TRAVEL_M
            {
                b += 1;
            }
            out.push(a..b);
            a = b;
        }
        out
    }

    /// Rasterise the world window serving frames `r` (every ray of those frames' sensors stays
    /// inside it, or leaves it only where the world itself ends).
    pub(crate) fn build_window(&self, r: std::ops::Range<usize>) -> World {
        let s = self.lattice.voxel_size_m;
        let first = self.sensor_pos[r.start];
        let last = self.sensor_pos[r.end - 1];
        let lo = [
            first[0] - WINDOW_MARGIN_M,
            first[1] - WORLD_HALF_WIDTH_M,
            self.lattice.origin_m[2],
        ];
        let hi = [
            last[0] + WINDOW_MARGIN_M + self.grid.max_m()[0].max(0.0),
            first[1] + WORLD_HALF_WIDTH_M,
            WORLD_TOP_M,
        ];
        let off = [0, 1, 2].map(|a| ((lo[a] - self.lattice.origin_m[a]) / s).floor() as i64);
        let end = [0, 1, 2].map(|a| ((hi[a] - self.lattice.origin_m[a]) / s).ceil() as i64);
        let dims = [0, 1, 2].map(|a| (end[a] - off[a]).max(1) as usize);
        let mut w = World::new(self.lattice, off, dims, self.seed);
        w.build(&self.layout);
        w
    }

    /// Scene classes of frame `i`'s grid (C order), read from a window that contains it.
    pub(crate) fn frame_classes(&self, world: &World, i: usize) -> Vec<u8> {
        let off = self.frame_off(i);
        let d = self.grid.dims;
        let mut out = Vec::with_capacity(d[0] * d[1] * d[2]);
        for x in 0..d[0] as i64 {
            for y in 0..d[1] as i64 {
                for z in 0..d[2] as i64 {
                    out.push(super::world::class_of(world.get_global([
                        off[0] + x,
                        off[1] + y,
                        off[2] + z,
                    ])));
                }
            }
        }
        out
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn frames_are_lattice_aligned_and_windows_cover_them() {
        let grid = VoxelGrid {
            origin_m: [0.0, -25.6, -2.2],
            voxel_size_m: 0.4,
            dims: [128, 128, 16],
        };
        let sc = SequenceScene::new(3, "00", 7, Style::Kitti, grid, 1.8, &[0.8, 1.2]);
        for i in 0..7 {
            let off = sc.frame_off(i);
            let c = sc.lattice.center(off);
            let want = [0, 1, 2].map(|a| sc.sensor_pos[i][a] + grid.origin_m[a] + 0.2);
            for a in 0..3 {
                assert!((c[a] - want[a]).abs() < 1e-9);
            }
        }
        // the road surface (z = 0) is a lattice boundary: lidar 1.8 m above, grid from -2.2
        assert!(((0.0 - sc.lattice.origin_m[2]) / 0.4 - 1.0).abs() < 1e-9);
        let groups = sc.frame_groups();
        assert_eq!(groups.iter().map(|g| g.len()).sum::<usize>(), 7);
        let w = sc.build_window(groups[0].clone());
        let classes = sc.frame_classes(&w, 0);
        // the ground layer under the ego is road, and the grid is not empty
        let ijk = grid.voxel_of_point_m([5.0, 0.0, -1.9]).unwrap();
        assert_eq!(
            classes[grid.linear_index(ijk)],
            crate::synthetic::classes::ROAD
        );
        assert!(classes.iter().filter(|&&c| c != 0).count() > 10_000);
    }
}
