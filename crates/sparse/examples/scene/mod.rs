//! The driving-like scenes of the examples: a gently sloping ground plane (one voxel thick, a
//! second layer on a fifth of the columns) and hollow boxes standing on it (cars, buildings,
//! poles: surfaces only, as a LiDAR or a camera would see them).

use rand::{Rng, SeedableRng};

/// The size of a scene and of its boxes.
pub struct SceneSpec {
    /// Grid `(X, Y, Z)`.
    pub shape: [i32; 3],
    /// Ground height at the origin; it rises one voxel every `slope` steps of `x + y`.
    pub ground_z: i32,
    pub slope: i32,
    /// Number of boxes, their base height, and the `[lo, hi)` ranges of their extents (x, y, z).
    pub boxes: usize,
    pub box_z: i32,
    pub extent: [(i32, i32); 3],
}

/// The active voxels `(0, x, y, z)` of a scene, in `(x, y, z)` order.
pub fn driving_scene(spec: &SceneSpec, seed: u64) -> Vec<[i32; 4]> {
    let mut r = rand_chacha::ChaCha8Rng::seed_from_u64(seed);
    let [sx, sy, sz] = spec.shape;
    let mut occ = vec![false; (sx * sy * sz) as usize];
    let idx = |x: i32, y: i32, z: i32| ((x * sy + y) * sz + z) as usize;
    for x in 0..sx {
        for y in 0..sy {
            let g = spec.ground_z + (x + y) / spec.slope;
            occ[idx(x, y, g)] = true;
            if (x * 7 + y * 3) % 5 == 0 {
                occ[idx(x, y, g + 1)] = true;
            }
        }
    }
    let [ew, el, eh] = spec.extent;
    for _ in 0..spec.boxes {
        let (w, l, h) = (
            r.random_range(ew.0..ew.1),
            r.random_range(el.0..el.1),
            r.random_range(eh.0..eh.1),
        );
        let (x0, y0) = (r.random_range(0..sx - w), r.random_range(0..sy - l));
        let top = (spec.box_z + h).min(sz);
        for x in x0..x0 + w {
            for y in y0..y0 + l {
                for z in spec.box_z..top {
                    let surface =
                        x == x0 || x == x0 + w - 1 || y == y0 || y == y0 + l - 1 || z == top - 1;
                    if surface {
                        occ[idx(x, y, z)] = true;
                    }
                }
            }
        }
    }
    let mut v = Vec::new();
    for x in 0..sx {
        for y in 0..sy {
            for z in 0..sz {
                if occ[idx(x, y, z)] {
                    v.push([0, x, y, z]);
                }
            }
        }
    }
    v
}
