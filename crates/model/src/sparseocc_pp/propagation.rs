//! Geometry-guided propagation inside the model (SparseOcc++, paper Sec. 4.2, Algorithm 1).
//!
//! The anchors' predicted SCF distances (decoded on the host, [`crate::sparseocc_pp::scf_head`]) drive
//! `occ_geometry::scf::propagate_batched` (Algorithm 1 on sparse anchors: interior anchors `s < 0`
//! dilate by the planar kernel `[2|s|+1, 2|s|+1, 1]` and the vertical kernel `[1, 1, 2|s|+1]`,
//! clipped to the grid, per batch item); the new voxels join the anchors with zero features
//! (`occ_sparse::ops::extend_zero`). Anchors keep their features; the result is sorted by
//! `(b, x, y, z)`.
//!
//! Scalar ablation: an interior anchor with distance `s` dilates by the cube `[2|s|+1]^3`. The cube is
//! the planar square swept along the vertical segment, so it is computed with the same
//! `propagate_batched`: first the vertical segment of every interior anchor, then a planar dilation of
//! every segment voxel with its anchor's `|s|` (duplicates are allowed there).
//!
//! Only host work on coordinates; no features are touched except the final zero-extension.

use crate::error::ModelError;
use crate::sparseocc_pp::scf_head::ScfDecomposition;
use occ_geometry::scf::propagate_batched;
use occ_sparse::{ops::extend_zero, Coord, SparseTensor};

fn geo_err(e: occ_geometry::scf::ScfError) -> ModelError {
    ModelError::Input(format!("propagation: {e}"))
}

/// New voxels (not anchors, sorted, unique) of Algorithm 1 for anchors `(b, x, y, z)` on a grid of
/// `dims`. Decomposed: `s_planar`, `s_vertical` per anchor. Scalar: `s_planar` holds the isotropic
/// distance and `s_vertical` is ignored.
pub fn propagated_voxels(
    anchors: &[Coord],
    s_planar: &[i32],
    s_vertical: &[i32],
    dims: [usize; 3],
    decomposition: ScfDecomposition,
) -> Result<Vec<Coord>, ModelError> {
    match decomposition {
        ScfDecomposition::Decomposed => Ok(propagate_batched(anchors, s_planar, s_vertical, dims)
            .map_err(geo_err)?
            .new_voxels),
        ScfDecomposition::Scalar => {
            if s_planar.len() != anchors.len() {
                return Err(ModelError::Input(format!(
                    "propagation: {} distances for {} anchors",
                    s_planar.len(),
                    anchors.len()
                )));
            }
            let zeros = vec![0i32; anchors.len()];
            // Step 1: vertical segments.
            let seg = propagate_batched(anchors, &zeros, s_planar, dims).map_err(geo_err)?;
            // Every segment voxel with the radius of each interior anchor whose segment holds it.
            let mut seeds: Vec<Coord> = Vec::new();
            let mut radius: Vec<i32> = Vec::new();
            for (c, &s) in anchors.iter().zip(s_planar) {
                if s >= 0 {
                    continue;
                }
                let r = i64::from(s).unsigned_abs() as i64;
                let z0 = (i64::from(c[3]) - r).max(0);
                let z1 = (i64::from(c[3]) + r).min(dims[2] as i64 - 1);
                for z in z0..=z1 {
                    seeds.push([c[0], c[1], c[2], z as i32]);
                    radius.push(s);
                }
            }
            // Step 2: planar squares around every segment voxel.
            let zeros = vec![0i32; seeds.len()];
            let sq = propagate_batched(&seeds, &radius, &zeros, dims).map_err(geo_err)?;
            let mut all: Vec<Coord> = seg.new_voxels;
            all.extend(sq.new_voxels);
            all.sort_unstable();
            all.dedup();
            let mut a: Vec<Coord> = anchors.to_vec();
            a.sort_unstable();
            all.retain(|c| a.binary_search(c).is_err());
            Ok(all)
        }
    }
}

/// Completes the anchor set: anchors ∪ propagated voxels, new voxels with zero features.
/// Returns the completed tensor (sorted by `(b, x, y, z)`) and the number of new voxels.
pub fn propagate_anchors<B: occ_sparse::SparseConvBackend>(
    anchors: &SparseTensor<B>,
    s_planar: &[i32],
    s_vertical: &[i32],
    decomposition: ScfDecomposition,
) -> Result<(SparseTensor<B>, usize), ModelError> {
    let new = propagated_voxels(
        anchors.coords(),
        s_planar,
        s_vertical,
        anchors.spatial_shape(),
        decomposition,
    )?;
    let n = new.len();
    let completed = extend_zero(anchors, &new)?;
    // extend_zero returns the input unchanged when nothing is new; sort for a uniform contract.
    Ok((completed.sorted(), n))
}

#[cfg(test)]
mod tests {
    use super::*;
    use burn::backend::NdArray;
    use burn::prelude::*;
    use burn::tensor::TensorData;
    use rand::{Rng, SeedableRng};
    use rand_chacha::ChaCha8Rng;

    type NB = NdArray<f64>;

    /// Dense dilation of each anchor by the cube of radius |s| (s < 0), clipped, union with anchors.
    fn cube_dense(anchors: &[Coord], s: &[i32], dims: [usize; 3], batch: usize) -> Vec<Coord> {
        let mut m = std::collections::BTreeSet::new();
        for (a, &sa) in anchors.iter().zip(s) {
            m.insert(*a);
            if sa >= 0 {
                continue;
            }
            let r = -sa;
            for dx in -r..=r {
                for dy in -r..=r {
                    for dz in -r..=r {
                        let c = [a[0], a[1] + dx, a[2] + dy, a[3] + dz];
                        if (0..3).all(|k| c[k + 1] >= 0 && (c[k + 1] as usize) < dims[k])
                            && (c[0] as usize) < batch
                        {
                            m.insert(c);
                        }
                    }
                }
            }
        }
        m.into_iter().collect()
    }

    #[test]
    fn scalar_propagation_is_cube_dilation() {
        let mut rng = ChaCha8Rng::seed_from_u64(9);
        let dims = [12, 9, 7];
        let mut anchors = std::collections::BTreeSet::new();
        while anchors.len() < 40 {
            anchors.insert([
                rng.random_range(0..2),
                rng.random_range(0..12),
                rng.random_range(0..9),
                rng.random_range(0..7),
            ]);
        }
        let anchors: Vec<Coord> = anchors.into_iter().collect();
        let s: Vec<i32> = anchors.iter().map(|_| rng.random_range(-3..=3)).collect();
        let new = propagated_voxels(&anchors, &s, &[], dims, ScfDecomposition::Scalar).unwrap();
        let mut got: Vec<Coord> = anchors.iter().chain(&new).copied().collect();
        got.sort_unstable();
        let before = got.len();
        got.dedup();
        assert_eq!(before, got.len(), "new voxels overlap anchors");
        assert_eq!(got, cube_dense(&anchors, &s, dims, 2));
        assert!(new.len() > 100);
    }

    #[test]
    fn anchors_keep_features_and_new_voxels_are_zero() {
        let device = Default::default();
        let coords: Vec<Coord> = vec![[0, 2, 2, 2], [0, 5, 5, 1], [1, 0, 0, 0]];
        let feats = Tensor::<NB, 2>::from_data(
            TensorData::new((1..=6).map(|v| v as f32).collect::<Vec<_>>(), [3, 2]),
            &device,
        );
        let t = SparseTensor::new(coords.clone(), feats, [8, 8, 4], 2).unwrap();
        let (out, n_new) =
            propagate_anchors(&t, &[-1, 0, -2], &[0, -1, 1], ScfDecomposition::Decomposed).unwrap();
        // Anchor 0: 3x3 square minus itself = 8; anchor 1: z 0..2 minus itself = 2; anchor 2 at the
        // corner: 3x3 square minus itself = 8.
        assert_eq!(n_new, 18);
        assert_eq!(out.num_active(), 21);
        let f = out.feats_to_vec();
        let mut sorted = out.coords().to_vec();
        sorted.sort_unstable();
        assert_eq!(sorted, out.coords());
        for (row, c) in out.coords().iter().enumerate() {
            let expect = match coords.iter().position(|a| a == c) {
                Some(i) => [2.0 * i as f32 + 1.0, 2.0 * i as f32 + 2.0],
                None => [0.0, 0.0],
            };
            assert_eq!([f[2 * row], f[2 * row + 1]], expect, "{c:?}");
        }
        // Errors are typed: length mismatch, anchors out of the grid.
        assert!(propagate_anchors(&t, &[-1], &[0, 0, 0], ScfDecomposition::Decomposed).is_err());
        assert!(propagated_voxels(
            &[[0, 9, 0, 0]],
            &[-1],
            &[0],
            [8, 8, 4],
            ScfDecomposition::Scalar
        )
        .is_err());
    }
}
