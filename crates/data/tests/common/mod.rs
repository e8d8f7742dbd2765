//! Shared helpers of the occ-data integration tests (the external data folders themselves are found
//! by `occ_testdata`).
#![allow(dead_code)]

use occ_geometry::VoxelGrid;
use std::path::PathBuf;

/// The SemanticKITTI root under the real data (the folder containing `sequences/`), or `None`
/// (skip reported by `occ_testdata`) when the real-data folder is absent.
pub fn kitti_root() -> Option<PathBuf> {
    let root = occ_testdata::realdata()?.join("semantickitti");
    assert!(
        root.join("sequences").is_dir(),
        "{} has no sequences/ folder",
        root.display()
    );
    Some(root)
}

/// IoU of two occupancy grids (non-zero = occupied): (intersection, union, iou).
pub fn iou(a: &[u8], b: &[u8]) -> (usize, usize, f64) {
    assert_eq!(a.len(), b.len());
    let mut i = 0;
    let mut u = 0;
    for (&x, &y) in a.iter().zip(b) {
        let (x, y) = (x != 0, y != 0);
        i += (x && y) as usize;
        u += (x || y) as usize;
    }
    (i, u, if u == 0 { 1.0 } else { i as f64 / u as f64 })
}

/// Exact voxel traversal (Amanatides & Woo) of the ray `o + t·d` (unit `d`, `o` inside the grid)
/// through the grid: the voxels visited in order, up to and including the first one `occupied`
/// accepts (returned separately), or until the ray leaves the grid or passes `t_max`.
pub fn traverse(
    grid: &VoxelGrid,
    occupied: &dyn Fn(usize) -> bool,
    o: [f64; 3],
    d: [f64; 3],
    t_max: f64,
) -> (Vec<usize>, Option<usize>) {
    let mut visited = Vec::new();
    let Some(mut ijk) = grid.voxel_of_point_m(o) else {
        return (visited, None);
    };
    let s = grid.voxel_size_m;
    let mut t_next = [f64::INFINITY; 3];
    let mut t_delta = [f64::INFINITY; 3];
    for a in 0..3 {
        let lo = grid.origin_m[a] + ijk[a] as f64 * s;
        if d[a] > 0.0 {
            t_next[a] = (lo + s - o[a]) / d[a];
            t_delta[a] = s / d[a];
        } else if d[a] < 0.0 {
            t_next[a] = (lo - o[a]) / d[a];
            t_delta[a] = -s / d[a];
        }
    }
    loop {
        let i = grid.linear_index(ijk);
        visited.push(i);
        if occupied(i) {
            return (visited, Some(i));
        }
        // The axis whose next boundary comes first; its `t_next` never decreases along the ray.
        let a = (0..3)
            .min_by(|&x, &y| t_next[x].partial_cmp(&t_next[y]).unwrap())
            .unwrap();
        if t_next[a] > t_max {
            return (visited, None);
        }
        if d[a] > 0.0 {
            ijk[a] += 1;
            if ijk[a] >= grid.dims[a] {
                return (visited, None);
            }
        } else {
            if ijk[a] == 0 {
                return (visited, None);
            }
            ijk[a] -= 1;
        }
        t_next[a] += t_delta[a];
    }
}
