//! Scan oracle: a DIAGNOSTIC, not a model component (NOT in the SparseOcc++ paper; it reads the
//! frame's LiDAR scan at test time, so a model with it is no camera-only model). It bounds what
//! perfect depth could give the 3D part: every anchor candidate and every voxel of the final stage
//! is told, through a learned `2 → D` embedding added to its query, which share of its
//! full-resolution voxels hold a return of the frame's scan (a visible surface) and which share a
//! ray of the scan crossed before its return (seen free space). That is what a dense, exact depth map
//! of the frame would say about each voxel; what it cannot say (hidden sides, what is out of view)
//! the network must still complete. VoxFormer's first stage (query proposals from depth) is the
//! learned version of the same input.
//!
//! By default only the returns that some camera of the sample sees (their projection lies in its
//! image) count, with their rays: what a perfect depth map of the cameras gives. `full_scan` keeps
//! the whole 360° scan (a LiDAR-camera fusion bound rather than a camera one).
//!
//! Frames are in the LiDAR frame with the sensor at the origin, as every reader and the synthetic
//! generator produce them (the lateral mirror keeps the sensor on the mirror plane).

use crate::batch::Batch;
use crate::error::ModelError;
use burn::prelude::*;
use burn::tensor::TensorData;
use occ_geometry::VoxelGrid;
use occ_sparse::Coord;

/// Ray-march step along each LiDAR ray, in voxels.
const MARCH_STEP_VOXELS: f64 = 0.5;

/// Per-voxel scan evidence of every sample of a batch, on the full-resolution grid.
#[derive(Clone, Debug)]
pub struct ScanOracle {
    /// `[B][X·Y·Z]`: 1 where a return lies in the voxel.
    hit: Vec<Vec<u8>>,
    /// `[B][X·Y·Z]`: 1 where a ray crossed the voxel before its return (and no return lies in it).
    free: Vec<Vec<u8>>,
    dims: [usize; 3],
}

impl ScanOracle {
    /// From the batch's LiDAR points (`None` when it has none): the returns some camera sees, or
    /// every return with `full_scan`.
    pub fn from_batch<B: Backend>(
        batch: &Batch<B>,
        full_scan: bool,
    ) -> Result<Option<Self>, ModelError> {
        let Some(points) = &batch.points else {
            return Ok(None);
        };
        if points.len() != batch.batch_size() || batch.cameras.len() != batch.batch_size() {
            return Err(ModelError::Input(format!(
                "scan oracle: {} point sets and {} camera sets for a batch of {}",
                points.len(),
                batch.cameras.len(),
                batch.batch_size()
            )));
        }
        let grid = &batch.grid;
        let (h, w) = batch.image_hw();
        let (hit, free) = points
            .iter()
            .zip(&batch.cameras)
            .map(|(pts, cams)| {
                if full_scan {
                    return evidence(grid, pts);
                }
                let seen: Vec<[f32; 3]> = pts
                    .iter()
                    .copied()
                    .filter(|p| {
                        cams.iter().any(|cam| {
                            let m = cam.img_from_lidar;
                            let p = [p[0] as f64, p[1] as f64, p[2] as f64];
                            let q: [f64; 3] = std::array::from_fn(|r| {
                                m[r][0] * p[0] + m[r][1] * p[1] + m[r][2] * p[2] + m[r][3]
                            });
                            let (u, v) = (q[0] / q[2], q[1] / q[2]);
                            q[2] > 1e-6 && u >= 0.0 && v >= 0.0 && u < w as f64 && v < h as f64
                        })
                    })
                    .collect();
                evidence(grid, &seen)
            })
            .unzip();
        Ok(Some(ScanOracle {
            hit,
            free,
            dims: grid.dims,
        }))
    }

    /// Shares of hit and free full-resolution voxels in each level voxel `(b, x, y, z)` of a grid
    /// `factor` times coarser, `[N·2]` row-major (hit, free).
    pub fn shares(&self, coords: &[Coord], factor: usize) -> Result<Vec<f32>, ModelError> {
        let f = factor.max(1);
        let [nx, ny, nz] = self.dims;
        let inv = 1.0 / (f * f * f) as f32;
        let mut out = Vec::with_capacity(coords.len() * 2);
        for c in coords {
            let (hit, free) = match (self.hit.get(c[0] as usize), self.free.get(c[0] as usize)) {
                (Some(h), Some(fr)) if c[0] >= 0 => (h, fr),
                _ => {
                    return Err(ModelError::Input(format!(
                        "scan oracle: batch index {} of {} samples",
                        c[0],
                        self.hit.len()
                    )))
                }
            };
            let (mut h, mut e) = (0u32, 0u32);
            for dx in 0..f {
                for dy in 0..f {
                    for dz in 0..f {
                        let ijk = [
                            c[1] as usize * f + dx,
                            c[2] as usize * f + dy,
                            c[3] as usize * f + dz,
                        ];
                        if c[1] < 0 || c[2] < 0 || c[3] < 0 || ijk[0] >= nx || ijk[1] >= ny {
                            continue;
                        }
                        if ijk[2] >= nz {
                            continue;
                        }
                        let lin = (ijk[0] * ny + ijk[1]) * nz + ijk[2];
                        h += hit[lin] as u32;
                        e += free[lin] as u32;
                    }
                }
            }
            out.push(h as f32 * inv);
            out.push(e as f32 * inv);
        }
        Ok(out)
    }

    /// [`ScanOracle::shares`] as a `[N, 2]` tensor.
    pub fn features<B: Backend>(
        &self,
        coords: &[Coord],
        factor: usize,
        device: &B::Device,
    ) -> Result<Tensor<B, 2>, ModelError> {
        let v = self.shares(coords, factor)?;
        Ok(Tensor::from_data(
            TensorData::new(v, [coords.len(), 2]).convert::<B::FloatElem>(),
            device,
        ))
    }
}

/// Hit and free masks of one scan (`[x][y][z]` flat, like the label grids).
fn evidence(grid: &VoxelGrid, points: &[[f32; 3]]) -> (Vec<u8>, Vec<u8>) {
    let n = grid.num_voxels();
    let mut hit = vec![0u8; n];
    let mut free = vec![0u8; n];
    let step_m = grid.voxel_size_m * MARCH_STEP_VOXELS;
    for p in points {
        let p = [p[0] as f64, p[1] as f64, p[2] as f64];
        if !p.iter().all(|v| v.is_finite()) {
            continue;
        }
        let range = (p[0] * p[0] + p[1] * p[1] + p[2] * p[2]).sqrt();
        if let Some(ijk) = grid.voxel_of_point_m(p) {
            hit[grid.linear_index(ijk)] = 1;
        }
        if range <= step_m {
            continue;
        }
        // March from the sensor to one step short of the return.
        let steps = (range / step_m).floor() as usize;
        for k in 1..steps {
            let t = k as f64 * step_m / range;
            if let Some(ijk) = grid.voxel_of_point_m([p[0] * t, p[1] * t, p[2] * t]) {
                free[grid.linear_index(ijk)] = 1;
            }
        }
    }
    for (f, h) in free.iter_mut().zip(&hit) {
        if *h == 1 {
            *f = 0;
        }
    }
    (hit, free)
}

#[cfg(test)]
mod tests {
    use super::*;

    fn grid() -> VoxelGrid {
        VoxelGrid {
            origin_m: [0.0, -2.0, -1.0],
            voxel_size_m: 1.0,
            dims: [8, 4, 2],
        }
    }

    #[test]
    fn a_return_marks_its_voxel_hit_and_the_voxels_before_it_free() {
        let g = grid();
        // A ray along +x at y = 0.5, z = -0.5: return in voxel x = 5.
        let (hit, free) = evidence(&g, &[[5.5, 0.5, -0.5]]);
        for x in 0..8 {
            let lin = g.linear_index([x, 2, 0]);
            assert_eq!(hit[lin], (x == 5) as u8, "hit at x = {x}");
            assert_eq!(free[lin], (x < 5) as u8, "free at x = {x}");
        }
        assert_eq!(hit.iter().map(|&v| v as usize).sum::<usize>(), 1);
        assert_eq!(free.iter().map(|&v| v as usize).sum::<usize>(), 5);
    }

    #[test]
    fn shares_count_the_children_of_each_coarse_voxel() {
        let g = grid();
        let (hit, free) = evidence(&g, &[[5.5, 0.5, -0.5]]);
        let o = ScanOracle {
            hit: vec![hit],
            free: vec![free],
            dims: g.dims,
        };
        // Factor 2: coarse voxel (2, 1, 0) holds x 4-5, y 2-3, z 0-1: one hit, one free of 8.
        let s = o.shares(&[[0, 2, 1, 0], [0, 3, 1, 0]], 2).unwrap();
        assert_eq!(s, vec![1.0 / 8.0, 1.0 / 8.0, 0.0, 0.0]);
        assert!(o.shares(&[[1, 0, 0, 0]], 2).is_err());
    }
}
