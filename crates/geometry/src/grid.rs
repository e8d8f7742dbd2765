//! Axis-aligned voxel grids: index <-> metric position, flat C-order indexing, 3D flips.
//!
//! Conventions (docs/formats.md §1): voxel index `(x, y, z)`, flat arrays in C order
//! `[x][y][z]` with z fastest; voxel `(i, j, k)` covers `[origin + idx·s, origin + (idx+1)·s)` and
//! its centre is `origin + (idx + 0.5)·s` (MonoScene `vox2world`).

use crate::mat::{mat4_identity, Mat4};
use serde::{Deserialize, Serialize};

/// A regular voxel grid in a sensor frame (LiDAR / ego), in metres.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct VoxelGrid {
    /// Metric position of the minimum corner of voxel (0, 0, 0).
    pub origin_m: [f64; 3],
    /// Edge length of a (cubic) voxel.
    pub voxel_size_m: f64,
    /// Number of voxels along x, y, z.
    pub dims: [usize; 3],
}

impl VoxelGrid {
    /// SemanticKITTI SSC grid **as the released files are laid out**: 256x256x32, 0.2 m,
    /// origin (0, -25.6, -2.2) in the velodyne frame.
    ///
    /// The nominal extent (docs/formats.md §2.2, voxelizer config `min extent: [0, -25.6, -2]`) has
    /// z from -2.0 m, but the SemanticKITTI voxel files (`.bin/.label/.invalid/.occluded`) were
    /// written with an off-by-one in the flat index (jbehley/voxelizer, fixed in commit
    /// e5989b8 "Fix off-by-one error when writing out voxel grid", June 2020, after the data
    /// release): stored element `n+1` holds true voxel `n`. With z fastest this is a +1 shift in
    /// z, so stored voxel `k >= 1` covers z ∈ [-2.2 + 0.2k, -2.0 + 0.2k). Measured on the real
    /// sample files (the external `SPARSEOCC_REALDATA` folder): voxelising the scan with origin
    /// z = -2.2 matches the official `.bin` with IoU 0.93-0.997 (1.0 when the voxelizer's range
    /// filter, label vote and f32 arithmetic are emulated), against 0.11-0.23 with z = -2.0.
    /// Stored layer `k = 0` never holds the [-2.2, -2.0) slab: it holds the top voxel ([4.2, 4.4))
    /// of the previous (x, y) column (wrapped), and is empty in practice. See
    /// [`VoxelGrid::semantic_kitti_nominal`].
    pub fn semantic_kitti() -> Self {
        VoxelGrid {
            origin_m: [0.0, -25.6, -2.2],
            voxel_size_m: 0.2,
            dims: [256, 256, 32],
        }
    }

    /// The nominal SemanticKITTI extent x∈[0,51.2], y∈[-25.6,25.6], z∈[-2,4.4] (origin
    /// (0, -25.6, -2.0)) used by MonoScene/SparseOcc configs and by the voxelizer before it
    /// writes its files; see [`VoxelGrid::semantic_kitti`] for why the released files sit 0.2 m lower.
    pub fn semantic_kitti_nominal() -> Self {
        VoxelGrid {
            origin_m: [0.0, -25.6, -2.0],
            voxel_size_m: 0.2,
            dims: [256, 256, 32],
        }
    }

    /// Occ3D-nuScenes: 200x200x16, 0.4 m, range [-40,-40,-1, 40,40,5.4] (docs/formats.md §4).
    pub fn occ3d_nuscenes() -> Self {
        VoxelGrid {
            origin_m: [-40.0, -40.0, -1.0],
            voxel_size_m: 0.4,
            dims: [200, 200, 16],
        }
    }

    /// nuScenes-Occupancy (OpenOccupancy): 512x512x40, 0.2 m, range [-51.2,-51.2,-5, 51.2,51.2,3]
    /// (docs/formats.md §3).
    pub fn nuscenes_occupancy() -> Self {
        VoxelGrid {
            origin_m: [-51.2, -51.2, -5.0],
            voxel_size_m: 0.2,
            dims: [512, 512, 40],
        }
    }

    /// Total number of voxels `X·Y·Z`.
    pub fn num_voxels(&self) -> usize {
        self.dims[0] * self.dims[1] * self.dims[2]
    }

    /// Flat C-order index `x·Y·Z + y·Z + z`. The caller guarantees `ijk < dims`
    /// (checked with a debug assertion).
    pub fn linear_index(&self, ijk: [usize; 3]) -> usize {
        debug_assert!(ijk[0] < self.dims[0] && ijk[1] < self.dims[1] && ijk[2] < self.dims[2]);
        (ijk[0] * self.dims[1] + ijk[1]) * self.dims[2] + ijk[2]
    }

    /// Inverse of [`VoxelGrid::linear_index`].
    pub fn ijk_of(&self, linear: usize) -> [usize; 3] {
        let z = linear % self.dims[2];
        let y = (linear / self.dims[2]) % self.dims[1];
        let x = linear / (self.dims[1] * self.dims[2]);
        [x, y, z]
    }

    /// Metric centre `origin + (idx + 0.5)·voxel_size` of voxel `ijk`.
    pub fn voxel_center_m(&self, ijk: [usize; 3]) -> [f64; 3] {
        let mut c = [0.0; 3];
        for a in 0..3 {
            c[a] = self.origin_m[a] + (ijk[a] as f64 + 0.5) * self.voxel_size_m;
        }
        c
    }

    /// The voxel containing `p_m` (index `floor((p - origin)/voxel_size)`), or `None` if the point
    /// is outside the grid or not finite. The lower faces are inclusive, the upper exclusive.
    pub fn voxel_of_point_m(&self, p_m: [f64; 3]) -> Option<[usize; 3]> {
        let mut ijk = [0usize; 3];
        for a in 0..3 {
            let f = ((p_m[a] - self.origin_m[a]) / self.voxel_size_m).floor();
            if !f.is_finite() || f < 0.0 || f >= self.dims[a] as f64 {
                return None;
            }
            ijk[a] = f as usize;
        }
        Some(ijk)
    }

    /// Metric upper corner `origin + dims·voxel_size`.
    pub fn max_m(&self) -> [f64; 3] {
        std::array::from_fn(|a| self.origin_m[a] + self.dims[a] as f64 * self.voxel_size_m)
    }

    /// Metric centre of the whole grid volume.
    pub fn center_m(&self) -> [f64; 3] {
        std::array::from_fn(|a| self.origin_m[a] + 0.5 * self.dims[a] as f64 * self.voxel_size_m)
    }

    /// The same volume with voxels `factor` times larger: `dims / factor` (integer division),
    /// `voxel_size·factor`, same origin. `factor = 0` is treated as 1.
    pub fn downsampled(&self, factor: usize) -> Self {
        let f = factor.max(1);
        VoxelGrid {
            origin_m: self.origin_m,
            voxel_size_m: self.voxel_size_m * f as f64,
            dims: [self.dims[0] / f, self.dims[1] / f, self.dims[2] / f],
        }
    }

    /// Metric transform of the 3D flip augmentation (SparseOcc `loading_kitti_occ.py`, docs/formats.md §2.9):
    /// `new_from_old` mirrors each flagged axis about the grid centre, `p' = 2c - p`.
    ///
    /// Mirroring about the grid centre is exactly what reversing the label array along that axis
    /// ([`flip_grid`]) does to voxel centres. (SparseOcc mirrors about the centre of the
    /// nominal range, (25.6, 0, 1.2); with [`VoxelGrid::semantic_kitti`] the z centre is 1.0.)
    pub fn flip_matrix(&self, flip: [bool; 3]) -> Mat4 {
        let c = self.center_m();
        let mut m = mat4_identity();
        for a in 0..3 {
            if flip[a] {
                m[a][a] = -1.0;
                m[a][3] = 2.0 * c[a];
            }
        }
        m
    }
}

/// Reverse a flat C-order `[x][y][z]` grid along each flagged axis (numpy `[::-1]`).
/// Returns `None` if `data.len() != dims[0]·dims[1]·dims[2]`.
pub fn flip_grid<T: Copy>(data: &[T], dims: [usize; 3], flip: [bool; 3]) -> Option<Vec<T>> {
    let n = dims[0].checked_mul(dims[1])?.checked_mul(dims[2])?;
    if data.len() != n {
        return None;
    }
    let mut out = Vec::with_capacity(n);
    for x in 0..dims[0] {
        let sx = if flip[0] { dims[0] - 1 - x } else { x };
        for y in 0..dims[1] {
            let sy = if flip[1] { dims[1] - 1 - y } else { y };
            let base = (sx * dims[1] + sy) * dims[2];
            if flip[2] {
                out.extend(data[base..base + dims[2]].iter().rev());
            } else {
                out.extend_from_slice(&data[base..base + dims[2]]);
            }
        }
    }
    Some(out)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::mat::transform_point;
    use rand::{Rng, SeedableRng};
    use rand_chacha::ChaCha8Rng;

    #[test]
    fn presets() {
        let k = VoxelGrid::semantic_kitti();
        assert_eq!(k.num_voxels(), 2_097_152);
        let mx = k.max_m();
        assert!(
            (mx[0] - 51.2).abs() < 1e-9
                && (mx[1] - 25.6).abs() < 1e-9
                && (mx[2] - 4.2).abs() < 1e-9
        );
        let n = VoxelGrid::semantic_kitti_nominal().max_m();
        assert!((n[2] - 4.4).abs() < 1e-9);
        let o = VoxelGrid::occ3d_nuscenes().max_m();
        assert!((o[0] - 40.0).abs() < 1e-9 && (o[2] - 5.4).abs() < 1e-9);
        let u = VoxelGrid::nuscenes_occupancy().max_m();
        assert!((u[0] - 51.2).abs() < 1e-9 && (u[2] - 3.0).abs() < 1e-9);
        let d = k.downsampled(2);
        assert_eq!(d.dims, [128, 128, 16]);
        assert!((d.voxel_size_m - 0.4).abs() < 1e-12);
        assert_eq!(d.max_m(), k.max_m());
    }

    #[test]
    fn linear_index_matches_c_order_and_round_trips() {
        let g = VoxelGrid {
            origin_m: [0.0; 3],
            voxel_size_m: 1.0,
            dims: [3, 4, 5],
        };
        let mut n = 0;
        for x in 0..3 {
            for y in 0..4 {
                for z in 0..5 {
                    assert_eq!(g.linear_index([x, y, z]), n);
                    assert_eq!(g.ijk_of(n), [x, y, z]);
                    n += 1;
                }
            }
        }
    }

    #[test]
    fn point_voxel_mapping_brute_force() {
        let g = VoxelGrid::semantic_kitti();
        let mut rng = ChaCha8Rng::seed_from_u64(3);
        for _ in 0..10_000 {
            let p = [
                rng.random_range(-2.0..53.0),
                rng.random_range(-27.0..27.0),
                rng.random_range(-3.0..5.0),
            ];
            let got = g.voxel_of_point_m(p);
            // brute force: find the voxel whose half-open box contains p by scanning each axis
            let mut want = Some([0usize; 3]);
            for a in 0..3 {
                let found = (0..g.dims[a]).find(|&i| {
                    let lo = g.origin_m[a] + i as f64 * g.voxel_size_m;
                    let hi = g.origin_m[a] + (i + 1) as f64 * g.voxel_size_m;
                    p[a] >= lo && p[a] < hi
                });
                match (found, want.as_mut()) {
                    (Some(i), Some(w)) => w[a] = i,
                    _ => want = None,
                }
            }
            // Float rounding at exact faces could differ; random points essentially never hit them.
            assert_eq!(got, want, "p = {p:?}");
            if let Some(ijk) = got {
                let c = g.voxel_center_m(ijk);
                assert_eq!(g.voxel_of_point_m(c), Some(ijk));
                for a in 0..3 {
                    assert!((c[a] - p[a]).abs() <= 0.5 * g.voxel_size_m + 1e-9);
                }
            }
        }
        assert_eq!(g.voxel_of_point_m([f64::NAN, 0.0, 0.0]), None);
        assert_eq!(g.voxel_of_point_m([51.2, 0.0, 0.0]), None);
        assert_eq!(g.voxel_of_point_m([0.0, -25.6, -2.2]), Some([0, 0, 0]));
    }

    #[test]
    fn flip_matrix_agrees_with_array_flip() {
        let g = VoxelGrid {
            origin_m: [0.0, -25.6, -2.2],
            voxel_size_m: 0.2,
            dims: [6, 5, 4],
        };
        let data: Vec<u32> = (0..g.num_voxels() as u32).collect();
        for bits in 0..8u32 {
            let flip = [bits & 1 != 0, bits & 2 != 0, bits & 4 != 0];
            let flipped = flip_grid(&data, g.dims, flip).unwrap();
            let m = g.flip_matrix(flip);
            for (n, &v) in data.iter().enumerate() {
                // the value at old voxel n must land at the voxel containing the mapped centre
                let c = transform_point(&m, g.voxel_center_m(g.ijk_of(n)));
                let ijk = g.voxel_of_point_m(c).unwrap();
                assert_eq!(flipped[g.linear_index(ijk)], v);
            }
            // involution
            assert_eq!(flip_grid(&flipped, g.dims, flip).unwrap(), data);
        }
        assert!(flip_grid(&data[1..], g.dims, [true, false, false]).is_none());
    }
}
