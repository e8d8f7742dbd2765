//! Scene completion field (SCF) geometry of SparseOcc++ (paper Sec. 4.2, "Compact Scene Completion"):
//! the Algorithm 2 ground truth and the Algorithm 1 geometry-guided propagation.
//!
//! This module depends on no other module of `occ-geometry`.
//!
//! # Grid convention
//! Dense grids are flat `[X][Y][Z]` arrays in C order (z fastest); `dims = [X, Y, Z]`. Voxel
//! coordinates are `[x, y, z]` (and `[b, x, y, z]` in the batched propagation).
//!
//! # Ground truth (Algorithm 2)
//! The occupancy is binarised (`occ > 0` is occupied, as in the paper's `occ_gt[occ_gt > 0] = 1`).
//! For `s_j = 1..=s_max` the paper average-pools the grid with a kernel covering radius `s_j`, stride 1
//! and zero padding `s_j` (PyTorch `avg_pool3d` default `count_include_pad=True`: the divisor is always
//! the full kernel volume, padded zeros included), and a voxel is *homogeneous* at `s_j` when the pooled
//! value equals its own value. Homogeneous occupied voxels get `-s_j`, homogeneous empty voxels `+s_j`;
//! a later (larger) `s_j` overwrites an earlier one, and voxels never homogeneous keep 0 (the boundary).
//!
//! In integer terms, with `c` the number of occupied in-grid voxels in the window of radius `s_j`:
//! - an occupied voxel is homogeneous iff `c == kernel volume`, which (because the padding counts as
//!   zeros) requires the whole window to lie inside the grid: occupied voxels within `s_j` of the
//!   border are never homogeneous at `s_j`, so they get smaller magnitudes than in an unbounded grid;
//! - an empty voxel is homogeneous iff `c == 0` (padding never breaks emptiness).
//!
//! Both conditions are monotone in `s_j` (the window of `s_j - 1` is a subset of the window of `s_j`,
//! padding positions included), so the final value is `±` the largest homogeneous radius, and the
//! search stops at the first non-homogeneous radius. The window counts come from summed-area tables
//! (planar: a 2D table per z slice, stored z-fastest; vertical: a prefix sum per column), so the cost
//! is `O(X·Y·Z·s_max)` table lookups regardless of the kernel size.
//!
//! Kernels (paper, "SCF Ground Truth Generation"): planar `[2s+1, 2s+1, 1]`, vertical `[1, 1, 2s+1]`.
//! The paper's `padding=k_j // 2` is applied per axis (0 along the axis where the kernel is 1), which
//! keeps the output the size of the input.
//!
//! # Propagation (Algorithm 1)
//! Algorithm 1 max-pools (dilates) the anchors whose predicted distance is `-s_j` with a kernel of
//! size `2 s_j + 1` and padding `s_j` (the paper writes `padding=s`; it means `s_j`) and takes the union
//! with the anchors. With the orthogonal decomposition this is done separately for the planar kernel
//! `[2|s|+1, 2|s|+1, 1]` (from the planar prediction) and the vertical kernel `[1, 1, 2|s|+1]` (from the
//! vertical prediction), and the union of all of them is the completed voxel set. Only interior
//! anchors (`s < 0`) propagate; `s >= 0` (boundary or exterior) adds nothing. Dilated voxels outside
//! the grid are dropped (max-pool output has the grid's shape). Any negative `s` dilates by `|s|`: the
//! predicted bins are in `[-s_max, s_max]` so the paper's loop bound `s_j <= s_max` never matters;
//! callers that want it should clamp first.
//!
//! The implementation works on the sparse anchors only: planar windows become `2|s|+1` runs along y
//! that are merged per `(b, x, z)` row, vertical windows add their voxels directly, and the union is
//! deduplicated by sorting and has the anchors removed by a merge walk; the cost grows with the number
//! of anchors times `|s|` (plus the output size) and never with the grid volume.

/// Errors of the SCF ground truth and the propagation. Every variant names the offending input.
#[derive(Debug, thiserror::Error, PartialEq, Eq)]
pub enum ScfError {
    /// The flat occupancy buffer does not have `X·Y·Z` entries.
    #[error(
        "SCF ground truth: occupancy buffer has {got} voxels but dims {dims:?} need {expected}"
    )]
    SizeMismatch {
        /// Grid dims `[X, Y, Z]`.
        dims: [usize; 3],
        /// `X·Y·Z`.
        expected: usize,
        /// Length of the buffer given.
        got: usize,
    },
    /// The grid dims cannot be handled (volume overflows, or a side does not fit `i32`).
    #[error("SCF: grid dims {dims:?} are not supported: {reason}")]
    BadDims {
        /// Grid dims as given.
        dims: [usize; 3],
        /// What is wrong with them.
        reason: &'static str,
    },
    /// `s_max` does not fit the int8 output.
    #[error("SCF ground truth: {axis} s_max = {s_max} does not fit int8 (must be <= 127)")]
    SMaxTooLarge {
        /// `"planar"` or `"vertical"`.
        axis: &'static str,
        /// The configured value.
        s_max: u32,
    },
    /// A per-anchor array does not have one entry per anchor.
    #[error("SCF propagation: {what} has {got} entries but there are {expected} anchors")]
    LengthMismatch {
        /// Which array (`"s_planar"` or `"s_vertical"`).
        what: &'static str,
        /// Number of anchors.
        expected: usize,
        /// Entries in the array.
        got: usize,
    },
    /// An anchor coordinate is outside the grid (or has a negative batch index).
    #[error("SCF propagation: anchor {index} at {coord:?} lies outside the grid {dims:?}")]
    AnchorOutOfBounds {
        /// Position of the anchor in the input.
        index: usize,
        /// Its coordinate (`[x, y, z]`, or `[b, x, y, z]` in the batched variant).
        coord: Vec<i32>,
        /// Grid dims.
        dims: [usize; 3],
    },
}

/// Maximum SCF distances (paper Sec. 4.2 "Discretized Learning"; the chosen setting of the
/// compact-completion ablation is `(10, 3)`, see docs/paper_notes.md §2). Each must be `<= 127`
/// (int8 output).
#[derive(Debug, Clone, Copy, PartialEq, Eq, serde::Serialize, serde::Deserialize)]
pub struct ScfConfig {
    /// `s_max^{X-Y}`: largest planar distance; planar bins are `2·s_max_planar + 1`.
    pub s_max_planar: u32,
    /// `s_max^{Z}`: largest vertical distance; vertical bins are `2·s_max_vertical + 1`.
    pub s_max_vertical: u32,
}

impl Default for ScfConfig {
    fn default() -> Self {
        Self {
            s_max_planar: 10,
            s_max_vertical: 3,
        }
    }
}

/// Algorithm 2 ground truth: signed distances in `[-s_max, s_max]`, flat `[X][Y][Z]` (z fastest).
/// Negative = occupied interior, positive = empty exterior, 0 = boundary (occupied or empty).
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct ScfGroundTruth {
    /// Grid dims `[X, Y, Z]`.
    pub dims: [usize; 3],
    /// Planar SCF (kernel `[2s+1, 2s+1, 1]`).
    pub planar: Vec<i8>,
    /// Vertical SCF (kernel `[1, 1, 2s+1]`).
    pub vertical: Vec<i8>,
}

fn check_grid(occ: &[u8], dims: [usize; 3]) -> Result<(), ScfError> {
    let expected = dims
        .iter()
        .try_fold(1usize, |acc, &d| acc.checked_mul(d))
        .ok_or(ScfError::BadDims {
            dims,
            reason: "X*Y*Z overflows usize",
        })?;
    if occ.len() != expected {
        return Err(ScfError::SizeMismatch {
            dims,
            expected,
            got: occ.len(),
        });
    }
    Ok(())
}

fn check_s_max(axis: &'static str, s_max: u32) -> Result<i8, ScfError> {
    i8::try_from(s_max).map_err(|_| ScfError::SMaxTooLarge { axis, s_max })
}

/// Both SCF ground truths of Algorithm 2 for a dense occupancy grid (`occ > 0` = occupied).
///
/// `occ` is flat `[X][Y][Z]` with `dims = [X, Y, Z]`. See the module docs for the exact rule
/// (zero padding counted in the average, so occupied voxels near the border get smaller magnitudes).
pub fn scf_ground_truth(
    occ: &[u8],
    dims: [usize; 3],
    cfg: &ScfConfig,
) -> Result<ScfGroundTruth, ScfError> {
    Ok(ScfGroundTruth {
        dims,
        planar: scf_planar(occ, dims, cfg.s_max_planar)?,
        vertical: scf_vertical(occ, dims, cfg.s_max_vertical)?,
    })
}

/// Planar SCF ground truth (Algorithm 2 with kernel `[2s+1, 2s+1, 1]`, padding `[s, s, 0]`).
pub fn scf_planar(occ: &[u8], dims: [usize; 3], s_max: u32) -> Result<Vec<i8>, ScfError> {
    check_grid(occ, dims)?;
    let s_max = check_s_max("planar", s_max)?;
    let [nx, ny, nz] = dims;
    let mut out = vec![0i8; occ.len()];
    if occ.is_empty() || s_max == 0 {
        return Ok(out);
    }
    if nx.saturating_mul(ny) > u32::MAX as usize {
        return Err(ScfError::BadDims {
            dims,
            reason: "X*Y exceeds u32 range of the summed-area table",
        });
    }
    // Summed-area table, sat[(i*(ny+1)+j)*nz + z] = #occupied in x < i, y < j at slice z.
    let sy = ny + 1;
    let mut sat = vec![0u32; (nx + 1) * sy * nz];
    for x in 0..nx {
        for y in 0..ny {
            let src = (x * ny + y) * nz;
            let a = ((x + 1) * sy + (y + 1)) * nz; // (x+1, y+1)
            let b = (x * sy + (y + 1)) * nz; // (x,   y+1)
            let c = ((x + 1) * sy + y) * nz; // (x+1, y)
            let d = (x * sy + y) * nz; // (x,   y)
            for z in 0..nz {
                let v = u32::from(occ[src + z] != 0);
                sat[a + z] = v
                    .wrapping_add(sat[b + z])
                    .wrapping_add(sat[c + z])
                    .wrapping_sub(sat[d + z]);
            }
        }
    }
    let mut alive = vec![false; nz];
    for x in 0..nx {
        for y in 0..ny {
            let base = (x * ny + y) * nz;
            let occ_col = &occ[base..base + nz];
            let out_col = &mut out[base..base + nz];
            alive.fill(true);
            for s in 1..=s_max {
                let r = s as usize;
                let x1 = x.saturating_sub(r);
                let x2 = (x + r + 1).min(nx);
                let y1 = y.saturating_sub(r);
                let y2 = (y + r + 1).min(ny);
                // `count` only sees in-grid voxels while the divisor is the full kernel volume
                // (padded zeros included), so `count == full` also requires the window to lie
                // inside the grid: that is how the border shrinks occupied distances.
                let full = ((2 * r + 1) * (2 * r + 1)) as u32;
                let p22 = &sat[(x2 * sy + y2) * nz..][..nz];
                let p12 = &sat[(x1 * sy + y2) * nz..][..nz];
                let p21 = &sat[(x2 * sy + y1) * nz..][..nz];
                let p11 = &sat[(x1 * sy + y1) * nz..][..nz];
                let mut any = false;
                for z in 0..nz {
                    if !alive[z] {
                        continue;
                    }
                    let count = p22[z]
                        .wrapping_sub(p12[z])
                        .wrapping_sub(p21[z])
                        .wrapping_add(p11[z]);
                    let occupied = occ_col[z] != 0;
                    let homogeneous = if occupied { count == full } else { count == 0 };
                    if homogeneous {
                        out_col[z] = if occupied { -s } else { s };
                        any = true;
                    } else {
                        alive[z] = false;
                    }
                }
                if !any {
                    break;
                }
            }
        }
    }
    Ok(out)
}

/// Vertical SCF ground truth (Algorithm 2 with kernel `[1, 1, 2s+1]`, padding `[0, 0, s]`).
pub fn scf_vertical(occ: &[u8], dims: [usize; 3], s_max: u32) -> Result<Vec<i8>, ScfError> {
    check_grid(occ, dims)?;
    let s_max = check_s_max("vertical", s_max)?;
    let nz = dims[2];
    let mut out = vec![0i8; occ.len()];
    if occ.is_empty() || s_max == 0 {
        return Ok(out);
    }
    let mut prefix = vec![0u32; nz + 1];
    for (occ_col, out_col) in occ.chunks_exact(nz).zip(out.chunks_exact_mut(nz)) {
        for (z, &v) in occ_col.iter().enumerate() {
            prefix[z + 1] = prefix[z] + u32::from(v != 0);
        }
        for z in 0..nz {
            let occupied = occ_col[z] != 0;
            for s in 1..=s_max {
                let r = s as usize;
                let z1 = z.saturating_sub(r);
                let z2 = (z + r + 1).min(nz);
                let count = prefix[z2] - prefix[z1];
                let homogeneous = if occupied {
                    // As in the planar case, a window crossing the border can never be full.
                    count as usize == 2 * r + 1
                } else {
                    count == 0
                };
                if !homogeneous {
                    break;
                }
                out_col[z] = if occupied { -s } else { s };
            }
        }
    }
    Ok(out)
}

/// Result of [`propagate`]: the voxels added by the propagation, not in the anchor set.
#[derive(Debug, Clone, PartialEq, Eq, Default)]
pub struct Propagation {
    /// New voxels `[x, y, z]`, sorted lexicographically, unique, none of them an anchor. The
    /// completed set of Algorithm 1 is `anchors ∪ new_voxels`; new voxels get zero features.
    pub new_voxels: Vec<[i32; 3]>,
}

/// Result of [`propagate_batched`].
#[derive(Debug, Clone, PartialEq, Eq, Default)]
pub struct BatchedPropagation {
    /// New voxels `[b, x, y, z]`, sorted lexicographically, unique, none of them an anchor.
    pub new_voxels: Vec<[i32; 4]>,
}

/// Validated grid geometry for the propagation.
struct PropGrid {
    dims: [usize; 3],
    /// X·Y·Z as u64.
    volume: u64,
}

impl PropGrid {
    fn new(dims: [usize; 3]) -> Result<Self, ScfError> {
        if dims.iter().any(|&d| d > i32::MAX as usize) {
            return Err(ScfError::BadDims {
                dims,
                reason: "a side exceeds i32::MAX",
            });
        }
        let volume = dims
            .iter()
            .try_fold(1u64, |acc, &d| acc.checked_mul(d as u64))
            .ok_or(ScfError::BadDims {
                dims,
                reason: "X*Y*Z overflows u64",
            })?;
        Ok(Self { dims, volume })
    }

    /// Linear key of an in-grid voxel (`base` = batch offset).
    #[inline]
    fn key(&self, base: u64, x: usize, y: usize, z: usize) -> u64 {
        base + ((x as u64 * self.dims[1] as u64) + y as u64) * self.dims[2] as u64 + z as u64
    }

    fn decode(&self, key: u64) -> (u64, [i32; 3]) {
        let [_, ny, nz] = self.dims;
        let b = key / self.volume;
        let rem = key % self.volume;
        let z = rem % nz as u64;
        let xy = rem / nz as u64;
        // All three are < their side, which fits i32 (checked in `new`).
        (
            b,
            [(xy / ny as u64) as i32, (xy % ny as u64) as i32, z as i32],
        )
    }

    /// In-grid `[x, y, z]` as usize, or None.
    fn locate(&self, c: [i32; 3]) -> Option<[usize; 3]> {
        let mut out = [0usize; 3];
        for a in 0..3 {
            let v = usize::try_from(c[a]).ok()?;
            if v >= self.dims[a] {
                return None;
            }
            out[a] = v;
        }
        Some(out)
    }
}

/// Clipped inclusive range `[c - r, c + r] ∩ [0, n)` for a radius `r = |s|` (s may be i32::MIN).
#[inline]
fn clipped(c: usize, s: i32, n: usize) -> std::ops::Range<usize> {
    let r = s.unsigned_abs() as usize;
    c.saturating_sub(r)..c.saturating_add(r).saturating_add(1).min(n)
}

/// Core of the propagation on validated anchors given as (batch base key, in-grid coordinate).
/// Returns the sorted, unique keys of the dilated voxels that are not anchors.
///
/// A planar window is `2|s|+1` runs along y (one per x row at the anchor's z), so each interior
/// anchor contributes `2|s|+1` intervals instead of `(2|s|+1)²` voxels; intervals of the same
/// `(b, x, z)` row are sorted and merged, then expanded to voxels. Vertical windows add at most
/// `2|s|+1` voxels each. The union is sorted and deduplicated, and anchors are removed by a merge
/// walk against the sorted anchor keys. Cost: `O(A·s log(A·s) + V log V)` for `A` anchors and `V`
/// output voxels, independent of the grid volume.
fn propagate_keys(
    grid: &PropGrid,
    anchors: &[(u64, [usize; 3])],
    s_planar: &[i32],
    s_vertical: &[i32],
) -> Vec<u64> {
    let [nx, ny, nz] = grid.dims;
    // Planar runs: (row key = base + (x*ny)*nz + z, i.e. the key of voxel (x, 0, z), y0, y1 inclusive).
    let mut runs: Vec<(u64, usize, usize)> = Vec::new();
    let mut keys: Vec<u64> = Vec::new();
    for (i, &(b, [x, y, z])) in anchors.iter().enumerate() {
        let sp = s_planar[i];
        if sp < 0 {
            let ys = clipped(y, sp, ny);
            for xi in clipped(x, sp, nx) {
                runs.push((grid.key(b, xi, 0, z), ys.start, ys.end - 1));
            }
        }
        let sv = s_vertical[i];
        if sv < 0 {
            keys.extend(clipped(z, sv, nz).map(|zi| grid.key(b, x, y, zi)));
        }
    }
    runs.sort_unstable();
    let stride_y = nz as u64;
    let emit = |row: u64, y0: usize, y1: usize, keys: &mut Vec<u64>| {
        keys.extend((y0..=y1).map(|yi| row + yi as u64 * stride_y));
    };
    let mut current: Option<(u64, usize, usize)> = None;
    for &(row, y0, y1) in &runs {
        current = match current {
            Some((r, c0, c1)) if r == row && y0 <= c1 + 1 => Some((r, c0, c1.max(y1))),
            Some((r, c0, c1)) => {
                emit(r, c0, c1, &mut keys);
                Some((row, y0, y1))
            }
            None => Some((row, y0, y1)),
        };
    }
    if let Some((r, c0, c1)) = current {
        emit(r, c0, c1, &mut keys);
    }
    keys.sort_unstable();
    keys.dedup();
    let mut anchor_keys: Vec<u64> = anchors
        .iter()
        .map(|&(b, [x, y, z])| grid.key(b, x, y, z))
        .collect();
    anchor_keys.sort_unstable();
    // Both sorted: drop keys that are anchors.
    let mut a = anchor_keys.iter().peekable();
    keys.retain(|&k| {
        while a.next_if(|&&ak| ak < k).is_some() {}
        a.peek() != Some(&&k)
    });
    keys
}

fn check_lengths(n: usize, s_planar: &[i32], s_vertical: &[i32]) -> Result<(), ScfError> {
    for (what, len) in [
        ("s_planar", s_planar.len()),
        ("s_vertical", s_vertical.len()),
    ] {
        if len != n {
            return Err(ScfError::LengthMismatch {
                what,
                expected: n,
                got: len,
            });
        }
    }
    Ok(())
}

/// Geometry-guided propagation (Algorithm 1) of sparse anchors `[x, y, z]` in a grid of `dims`.
///
/// `s_planar[i]` / `s_vertical[i]` are the predicted SCF distances of anchor `i`; interior anchors
/// (`s < 0`) are dilated by `[2|s|+1, 2|s|+1, 1]` (planar) and `[1, 1, 2|s|+1]` (vertical), clipped to
/// the grid. Returns the voxels of the union that are not anchors. Duplicate anchors are allowed.
/// Errors if an anchor is outside the grid or the arrays differ in length.
pub fn propagate(
    anchors: &[[i32; 3]],
    s_planar: &[i32],
    s_vertical: &[i32],
    dims: [usize; 3],
) -> Result<Propagation, ScfError> {
    // One batch element of the batched propagation; errors name the anchor as given, `[x, y, z]`.
    let batched: Vec<[i32; 4]> = anchors.iter().map(|&[x, y, z]| [0, x, y, z]).collect();
    let out = propagate_batched(&batched, s_planar, s_vertical, dims).map_err(|e| match e {
        ScfError::AnchorOutOfBounds { index, coord, dims } => ScfError::AnchorOutOfBounds {
            index,
            coord: coord[1..].to_vec(),
            dims,
        },
        e => e,
    })?;
    Ok(Propagation {
        new_voxels: out
            .new_voxels
            .into_iter()
            .map(|[_, x, y, z]| [x, y, z])
            .collect(),
    })
}

/// Batched [`propagate`]: anchors `[b, x, y, z]` with `b >= 0`; each batch element is propagated in its
/// own grid of `dims` (voxels never cross batch elements). New voxels are sorted by `(b, x, y, z)`.
pub fn propagate_batched(
    anchors: &[[i32; 4]],
    s_planar: &[i32],
    s_vertical: &[i32],
    dims: [usize; 3],
) -> Result<BatchedPropagation, ScfError> {
    check_lengths(anchors.len(), s_planar, s_vertical)?;
    let grid = PropGrid::new(dims)?;
    let located = anchors
        .iter()
        .enumerate()
        .map(|(index, &c)| {
            let out_of_bounds = || ScfError::AnchorOutOfBounds {
                index,
                coord: c.to_vec(),
                dims,
            };
            let b = u64::try_from(c[0]).map_err(|_| out_of_bounds())?;
            let p = grid.locate([c[1], c[2], c[3]]).ok_or_else(out_of_bounds)?;
            // b <= i32::MAX; the product may overflow u64 only for absurd grids.
            let base = b.checked_mul(grid.volume).ok_or(ScfError::BadDims {
                dims,
                reason: "batch index times X*Y*Z overflows u64",
            })?;
            grid.volume.checked_add(base).ok_or(ScfError::BadDims {
                dims,
                reason: "batch index times X*Y*Z overflows u64",
            })?;
            Ok((base, p))
        })
        .collect::<Result<Vec<_>, _>>()?;
    let keys = propagate_keys(&grid, &located, s_planar, s_vertical);
    Ok(BatchedPropagation {
        new_voxels: keys
            .into_iter()
            .map(|k| {
                let (b, [x, y, z]) = grid.decode(k);
                // b came from an i32 batch index.
                [b as i32, x, y, z]
            })
            .collect(),
    })
}

/// Dense `[X][Y][Z]` occupancy (1 = in `anchors ∪ new_voxels`) for a single-grid propagation; a
/// convenience for tests and visualisation. Coordinates outside `dims` are ignored.
pub fn propagation_to_dense(
    anchors: &[[i32; 3]],
    prop: &Propagation,
    dims: [usize; 3],
) -> Result<Vec<u8>, ScfError> {
    let grid = PropGrid::new(dims)?;
    let volume = usize::try_from(grid.volume).map_err(|_| ScfError::BadDims {
        dims,
        reason: "X*Y*Z overflows usize",
    })?;
    let mut dense = vec![0u8; volume];
    for &c in anchors.iter().chain(prop.new_voxels.iter()) {
        if let Some([x, y, z]) = grid.locate(c) {
            dense[(x * dims[1] + y) * dims[2] + z] = 1;
        }
    }
    Ok(dense)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn tiny_planar_hand_computed() {
        // 5x5x1, a 3x3 occupied block in the middle.
        let mut occ = vec![0u8; 25];
        for x in 1..4 {
            for y in 1..4 {
                occ[x * 5 + y] = 1;
            }
        }
        let p = scf_planar(&occ, [5, 5, 1], 3).unwrap();
        // Centre: window of radius 1 is all ones and inside -> -1; radius 2 touches zeros.
        assert_eq!(p[2 * 5 + 2], -1);
        // Other occupied voxels touch an empty neighbour at radius 1 -> boundary 0.
        assert_eq!(p[5 + 1], 0);
        // Corner (0,0) is empty; its radius-1 window contains (1,1) -> 0.
        assert_eq!(p[0], 0);
        // Empty voxels on the border edge centre (0,2): radius-1 window has (1,1..3) -> 0.
        assert_eq!(p[2], 0);
    }

    #[test]
    fn full_grid_border_counts_padding() {
        // Fully occupied 7x7x1: distance = distance to the border (padding counts as empty).
        let occ = vec![1u8; 49];
        let p = scf_planar(&occ, [7, 7, 1], 10).unwrap();
        for x in 0..7i8 {
            for y in 0..7i8 {
                let d = x.min(y).min(6 - x).min(6 - y);
                assert_eq!(p[(x as usize) * 7 + y as usize], -d, "at ({x},{y})");
            }
        }
        // Empty grid: every voxel reaches s_max (padding never breaks emptiness).
        let v = scf_vertical(&[0u8; 10], [1, 1, 10], 3).unwrap();
        assert!(v.iter().all(|&s| s == 3));
        let v = scf_vertical(&[1u8; 10], [1, 1, 10], 3).unwrap();
        assert_eq!(v, vec![0, -1, -2, -3, -3, -3, -3, -2, -1, 0]);
    }

    #[test]
    fn errors_are_typed() {
        assert!(matches!(
            scf_planar(&[0u8; 5], [2, 2, 2], 3),
            Err(ScfError::SizeMismatch { .. })
        ));
        assert!(matches!(
            scf_vertical(&[0u8; 8], [2, 2, 2], 200),
            Err(ScfError::SMaxTooLarge { .. })
        ));
        assert!(matches!(
            propagate(&[[0, 0, 2]], &[-1], &[0], [2, 2, 2]),
            Err(ScfError::AnchorOutOfBounds { index: 0, .. })
        ));
        assert!(matches!(
            propagate(&[[0, 0, 0]], &[-1, 2], &[0], [2, 2, 2]),
            Err(ScfError::LengthMismatch { .. })
        ));
        assert!(matches!(
            propagate_batched(&[[-1, 0, 0, 0]], &[-1], &[0], [2, 2, 2]),
            Err(ScfError::AnchorOutOfBounds { .. })
        ));
    }

    #[test]
    fn propagation_tiny_hand_computed() {
        // One interior anchor at the corner: planar radius 1 -> 2x2 square at z, vertical radius 2.
        let p = propagate(&[[0, 0, 1]], &[-1], &[-2], [4, 4, 4]).unwrap();
        assert_eq!(
            p.new_voxels,
            vec![
                [0, 0, 0],
                [0, 0, 2],
                [0, 0, 3],
                [0, 1, 1],
                [1, 0, 1],
                [1, 1, 1]
            ]
        );
        // Non-negative distances add nothing; i32::MIN does not overflow.
        let p = propagate(&[[1, 1, 1]], &[0], &[5], [4, 4, 4]).unwrap();
        assert!(p.new_voxels.is_empty());
        let p = propagate(&[[1, 1, 1]], &[i32::MIN], &[0], [3, 3, 3]).unwrap();
        assert_eq!(p.new_voxels.len(), 8);
        // Batched: same anchor in two batch elements, anchors excluded per element.
        let b = propagate_batched(
            &[[0, 0, 0, 1], [1, 0, 0, 1], [1, 0, 0, 0]],
            &[0, 0, 0],
            &[-1, -1, 0],
            [4, 4, 4],
        )
        .unwrap();
        assert_eq!(b.new_voxels, vec![[0, 0, 0, 0], [0, 0, 0, 2], [1, 0, 0, 2]]);
    }
}
