//! Visibility bookkeeping: lock-free bitsets over boxes of the global lattice, filled by the
//! rays of the LiDAR and the cameras (every voxel a ray traverses or stops in is "seen").

use std::sync::atomic::{AtomicU64, Ordering};

/// A bitset over a box of the global lattice (`off`, `dims`, C order `[x][y][z]`).
#[derive(Debug)]
pub(crate) struct VisBox {
    pub off: [i64; 3],
    pub dims: [usize; 3],
    bits: Vec<AtomicU64>,
}

impl VisBox {
    pub(crate) fn new(off: [i64; 3], dims: [usize; 3]) -> Self {
        let n = dims[0] * dims[1] * dims[2];
        VisBox {
            off,
            dims,
            bits: (0..n.div_ceil(64)).map(|_| AtomicU64::new(0)).collect(),
        }
    }

    /// Flat index of a global voxel, if inside the box.
    #[inline]
    pub(crate) fn flat(&self, g: [i64; 3]) -> Option<usize> {
        let x = g[0] - self.off[0];
        let y = g[1] - self.off[1];
        let z = g[2] - self.off[2];
        if x < 0
            || y < 0
            || z < 0
            || x >= self.dims[0] as i64
            || y >= self.dims[1] as i64
            || z >= self.dims[2] as i64
        {
            return None;
        }
        Some((x as usize * self.dims[1] + y as usize) * self.dims[2] + z as usize)
    }

    /// Mark a global voxel (no-op outside the box). Thread-safe; the result does not depend on
    /// the order of calls.
    #[inline]
    pub(crate) fn mark(&self, g: [i64; 3]) {
        if let Some(i) = self.flat(g) {
            let w = &self.bits[i >> 6];
            let m = 1u64 << (i & 63);
            if w.load(Ordering::Relaxed) & m == 0 {
                w.fetch_or(m, Ordering::Relaxed);
            }
        }
    }

    pub(crate) fn get(&self, g: [i64; 3]) -> bool {
        self.flat(g)
            .is_some_and(|i| self.bits[i >> 6].load(Ordering::Relaxed) & (1u64 << (i & 63)) != 0)
    }

    /// One 0/1 byte per voxel of the sub-box at global offset `off` with `dims` (voxels of the
    /// sub-box outside this box read 0).
    pub(crate) fn extract(&self, off: [i64; 3], dims: [usize; 3]) -> Vec<u8> {
        let mut out = Vec::with_capacity(dims[0] * dims[1] * dims[2]);
        for i in 0..dims[0] as i64 {
            for j in 0..dims[1] as i64 {
                for k in 0..dims[2] as i64 {
                    out.push(u8::from(self.get([off[0] + i, off[1] + j, off[2] + k])));
                }
            }
        }
        out
    }
}

/// The boxes a ray marks as seen.
#[derive(Clone, Copy)]
pub(crate) struct Marker<'a> {
    pub boxes: &'a [&'a VisBox],
}

impl Marker<'_> {
    /// Bounding box `[lo, hi)` of all boxes, in the local indices of a window at global `off`.
    pub(crate) fn local_box(&self, off: [i64; 3]) -> ([i64; 3], [i64; 3]) {
        let mut lo = [i64::MAX; 3];
        let mut hi = [i64::MIN; 3];
        for b in self.boxes {
            for a in 0..3 {
                lo[a] = lo[a].min(b.off[a] - off[a]);
                hi[a] = hi[a].max(b.off[a] + b.dims[a] as i64 - off[a]);
            }
        }
        if self.boxes.is_empty() {
            return ([0; 3], [0; 3]);
        }
        (lo, hi)
    }

    #[inline]
    pub(crate) fn mark(&self, g: [i64; 3]) {
        for b in self.boxes {
            b.mark(g);
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn mark_get_extract() {
        let b = VisBox::new([-2, 3, 0], [4, 5, 3]);
        b.mark([-2, 3, 0]);
        b.mark([1, 7, 2]);
        b.mark([2, 7, 2]); // outside
        assert!(b.get([-2, 3, 0]) && b.get([1, 7, 2]) && !b.get([0, 4, 1]) && !b.get([2, 7, 2]));
        let e = b.extract([-2, 3, 0], [4, 5, 3]);
        assert_eq!(e.iter().filter(|&&v| v == 1).count(), 2);
        assert_eq!(e[0], 1);
        assert_eq!(e[(3 * 5 + 4) * 3 + 2], 1);
        let e2 = b.extract([1, 7, 2], [2, 1, 1]);
        assert_eq!(e2, vec![1, 0]);
    }
}
