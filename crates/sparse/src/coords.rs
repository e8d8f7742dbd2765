//! Integer voxel coordinates kept on the host, with an open-addressing hash index.
//!
//! A coordinate is `(batch, x, y, z)`, in the order of the spatial shape and of the kernel dimensions
//! (spconv convention, docs/reference_models.md §3). Coordinates live on the host because every structural decision
//! (kernel maps, unions, pruning) is integer work that GPUs gain little on at these sizes; features live on
//! the burn device.

use crate::error::{Result, SparseError};
use crate::kernel_map::{ConvCacheEntry, KernelMapKey};
use std::collections::HashMap;
use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::{Arc, Mutex};

/// One active site: `(batch, x, y, z)`.
pub type Coord = [i32; 4];

/// Largest supported extent of one spatial axis (coordinates are packed into 16 bits per axis).
pub const MAX_AXIS_EXTENT: usize = 1 << 15;
/// Largest supported batch size.
pub const MAX_BATCH: usize = 1 << 15;

/// Packs an in-range coordinate into a u64 whose integer order is the lexicographic (b, x, y, z) order.
#[inline]
pub fn pack(c: Coord) -> u64 {
    ((c[0] as u64 & 0xFFFF) << 48)
        | ((c[1] as u64 & 0xFFFF) << 32)
        | ((c[2] as u64 & 0xFFFF) << 16)
        | (c[3] as u64 & 0xFFFF)
}

/// Inverse of [`pack`].
#[inline]
pub fn unpack(k: u64) -> Coord {
    [
        ((k >> 48) & 0xFFFF) as i32,
        ((k >> 32) & 0xFFFF) as i32,
        ((k >> 16) & 0xFFFF) as i32,
        (k & 0xFFFF) as i32,
    ]
}

const EMPTY: u64 = u64::MAX;

#[inline]
fn mix(mut k: u64) -> u64 {
    // fmix64 from MurmurHash3: cheap and spreads the packed coordinate bits well.
    k ^= k >> 33;
    k = k.wrapping_mul(0xff51_afd7_ed55_8ccd);
    k ^= k >> 33;
    k = k.wrapping_mul(0xc4ce_b9fe_1a85_ec53);
    k ^= k >> 33;
    k
}

/// Open-addressing (linear probing) hash map from packed coordinates to row indices.
///
/// Memory is linear in the number of active sites (load factor <= 1/2), never in the grid volume.
#[derive(Clone, Debug)]
pub struct CoordIndex {
    keys: Vec<u64>,
    vals: Vec<u32>,
    mask: usize,
    len: usize,
}

impl CoordIndex {
    /// An empty index sized for `n` entries.
    pub fn with_capacity(n: usize) -> Self {
        let cap = (2 * n.max(8)).next_power_of_two();
        Self {
            keys: vec![EMPTY; cap],
            vals: vec![0; cap],
            mask: cap - 1,
            len: 0,
        }
    }

    /// Number of stored keys.
    pub fn len(&self) -> usize {
        self.len
    }

    /// True when no key is stored.
    pub fn is_empty(&self) -> bool {
        self.len == 0
    }

    /// Inserts `key -> val`; returns the value already stored under `key` (and keeps it) if any.
    pub fn insert(&mut self, key: u64, val: u32) -> Option<u32> {
        if 2 * (self.len + 1) > self.keys.len() {
            self.grow();
        }
        let mut slot = mix(key) as usize & self.mask;
        loop {
            let k = self.keys[slot];
            if k == EMPTY {
                self.keys[slot] = key;
                self.vals[slot] = val;
                self.len += 1;
                return None;
            }
            if k == key {
                return Some(self.vals[slot]);
            }
            slot = (slot + 1) & self.mask;
        }
    }

    /// Looks a packed key up.
    #[inline]
    pub fn get(&self, key: u64) -> Option<u32> {
        let mut slot = mix(key) as usize & self.mask;
        loop {
            let k = self.keys[slot];
            if k == key {
                return Some(self.vals[slot]);
            }
            if k == EMPTY {
                return None;
            }
            slot = (slot + 1) & self.mask;
        }
    }

    fn grow(&mut self) {
        let old_keys = std::mem::take(&mut self.keys);
        let old_vals = std::mem::take(&mut self.vals);
        let cap = (old_keys.len() * 2).max(16);
        self.keys = vec![EMPTY; cap];
        self.vals = vec![0; cap];
        self.mask = cap - 1;
        self.len = 0;
        for (k, v) in old_keys.into_iter().zip(old_vals) {
            if k != EMPTY {
                self.insert(k, v);
            }
        }
    }
}

static NEXT_ID: AtomicU64 = AtomicU64::new(1);

/// A set of active sites with its hash index, spatial shape, batch size and tensor stride.
///
/// Kernel maps whose input is this set are cached inside it under a typed [`KernelMapKey`], so layers that
/// share a geometry on the same coordinates build the map once (like spconv's `indice_key`, but typed).
/// A set produced by a strided convolution remembers its parent set and map, which is how an inverse
/// convolution restores the parent coordinates.
pub struct CoordSet {
    /// Shared with the kernel maps built on this set, which may build their pairs later
    /// ([`crate::kernel_map::MapSource`]).
    coords: Arc<Vec<Coord>>,
    /// Built eagerly by the validating constructors, lazily (on the first lookup) for sets made by
    /// kernel-map building, which often never need it.
    index: std::sync::OnceLock<CoordIndex>,
    spatial_shape: [usize; 3],
    batch_size: usize,
    tensor_stride: [usize; 3],
    id: u64,
    pub(crate) cache: Mutex<HashMap<KernelMapKey, ConvCacheEntry>>,
    pub(crate) parents: Mutex<Vec<crate::kernel_map::ParentLink>>,
    /// The sites uploaded to compute devices ([`crate::kernel_map::Sites::device_table`]).
    device_sites: Arc<crate::kernel_map::DeviceTables>,
}

impl std::fmt::Debug for CoordSet {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("CoordSet")
            .field("id", &self.id)
            .field("len", &self.coords.len())
            .field("spatial_shape", &self.spatial_shape)
            .field("batch_size", &self.batch_size)
            .field("tensor_stride", &self.tensor_stride)
            .finish()
    }
}

impl CoordSet {
    /// Validates and indexes a coordinate list.
    ///
    /// Errors: a coordinate outside `[0, batch_size) x [0, spatial_shape)`, a duplicate, or a shape beyond
    /// [`MAX_AXIS_EXTENT`] / [`MAX_BATCH`].
    pub fn new(coords: Vec<Coord>, spatial_shape: [usize; 3], batch_size: usize) -> Result<Self> {
        Self::with_stride(coords, spatial_shape, batch_size, [1, 1, 1])
    }

    /// Like [`CoordSet::new`] with an explicit tensor stride (the voxel size relative to the finest grid).
    pub fn with_stride(
        coords: Vec<Coord>,
        spatial_shape: [usize; 3],
        batch_size: usize,
        tensor_stride: [usize; 3],
    ) -> Result<Self> {
        check_extents(spatial_shape, batch_size, coords.len())?;
        let mut index = CoordIndex::with_capacity(coords.len());
        for (row, &c) in coords.iter().enumerate() {
            check_in_range(row, c, spatial_shape, batch_size)?;
            if let Some(first) = index.insert(pack(c), row as u32) {
                return Err(SparseError::Duplicate {
                    coord: c,
                    first: first as usize,
                    second: row,
                });
            }
        }
        Ok(Self::from_trusted(
            coords,
            index,
            spatial_shape,
            batch_size,
            tensor_stride,
        ))
    }

    /// Builds a set from coordinates already known to be valid and unique (internal constructors).
    pub(crate) fn from_trusted(
        coords: Vec<Coord>,
        index: CoordIndex,
        spatial_shape: [usize; 3],
        batch_size: usize,
        tensor_stride: [usize; 3],
    ) -> Self {
        Self::with_index(
            coords,
            std::sync::OnceLock::from(index),
            spatial_shape,
            batch_size,
            tensor_stride,
        )
    }

    /// Builds a set from valid unique coordinates; the hash index is built on first use.
    pub(crate) fn from_valid_unique(
        coords: Vec<Coord>,
        spatial_shape: [usize; 3],
        batch_size: usize,
        tensor_stride: [usize; 3],
    ) -> Self {
        Self::with_index(
            coords,
            std::sync::OnceLock::new(),
            spatial_shape,
            batch_size,
            tensor_stride,
        )
    }

    fn with_index(
        coords: Vec<Coord>,
        index: std::sync::OnceLock<CoordIndex>,
        spatial_shape: [usize; 3],
        batch_size: usize,
        tensor_stride: [usize; 3],
    ) -> Self {
        Self {
            coords: Arc::new(coords),
            index,
            spatial_shape,
            batch_size,
            tensor_stride,
            id: NEXT_ID.fetch_add(1, Ordering::Relaxed),
            cache: Mutex::new(HashMap::new()),
            parents: Mutex::new(Vec::new()),
            device_sites: Arc::default(),
        }
    }

    /// The coordinates, row `i` belonging to feature row `i`.
    pub fn coords(&self) -> &[Coord] {
        &self.coords
    }
    /// The coordinates, shared (no copy).
    pub(crate) fn shared_coords(&self) -> Arc<Vec<Coord>> {
        self.coords.clone()
    }
    /// The set's copies on compute devices, shared (see [`crate::kernel_map::Sites`]).
    pub(crate) fn device_sites(&self) -> Arc<crate::kernel_map::DeviceTables> {
        self.device_sites.clone()
    }
    /// Number of active sites.
    pub fn len(&self) -> usize {
        self.coords.len()
    }
    /// True when there is no active site.
    pub fn is_empty(&self) -> bool {
        self.coords.is_empty()
    }
    /// Spatial shape (x, y, z).
    pub fn spatial_shape(&self) -> [usize; 3] {
        self.spatial_shape
    }
    /// Batch size.
    pub fn batch_size(&self) -> usize {
        self.batch_size
    }
    /// Tensor stride: how many finest-grid voxels one voxel of this set spans per axis.
    pub fn tensor_stride(&self) -> [usize; 3] {
        self.tensor_stride
    }
    /// A process-unique id (identity, not content).
    pub fn id(&self) -> u64 {
        self.id
    }
    /// The hash index.
    pub fn index(&self) -> &CoordIndex {
        self.index.get_or_init(|| {
            let mut index = CoordIndex::with_capacity(self.coords.len());
            for (row, &c) in self.coords.iter().enumerate() {
                index.insert(pack(c), row as u32);
            }
            index
        })
    }
    /// Row of a coordinate, if active. Out-of-range coordinates are simply absent.
    #[inline]
    pub fn find(&self, c: Coord) -> Option<usize> {
        let in_range = c[0] >= 0
            && (c[0] as usize) < self.batch_size
            && (0..3).all(|a| c[a + 1] >= 0 && (c[a + 1] as usize) < self.spatial_shape[a]);
        if !in_range {
            return None;
        }
        self.index().get(pack(c)).map(|r| r as usize)
    }
    /// Permutation that sorts the rows by (b, x, y, z).
    pub fn sorted_order(&self) -> Vec<usize> {
        let mut order: Vec<usize> = (0..self.coords.len()).collect();
        order.sort_unstable_by_key(|&i| pack(self.coords[i]));
        order
    }
    /// Row-major linear index of each site in a dense `[B, X, Y, Z]` grid.
    pub fn linear_indices(&self) -> Vec<usize> {
        let [sx, sy, sz] = self.spatial_shape;
        self.coords
            .iter()
            .map(|c| {
                ((c[0] as usize * sx + c[1] as usize) * sy + c[2] as usize) * sz + c[3] as usize
            })
            .collect()
    }
}

/// Checks a grid's extents and a site count against what the packed keys and `u32` rows hold.
fn check_extents(spatial_shape: [usize; 3], batch_size: usize, n: usize) -> Result<()> {
    if spatial_shape.iter().any(|&s| s == 0 || s > MAX_AXIS_EXTENT) {
        return Err(SparseError::Config(format!(
            "spatial shape {spatial_shape:?}: each axis must be in 1..={MAX_AXIS_EXTENT}"
        )));
    }
    if batch_size == 0 || batch_size > MAX_BATCH {
        return Err(SparseError::Config(format!(
            "batch size {batch_size}: must be in 1..={MAX_BATCH}"
        )));
    }
    if n > u32::MAX as usize {
        return Err(SparseError::Config("more than 2^32 active sites".into()));
    }
    Ok(())
}

/// Errors unless site `c` (row `row`) lies in `[0, batch_size) x [0, spatial_shape)`.
#[inline]
fn check_in_range(
    row: usize,
    c: Coord,
    spatial_shape: [usize; 3],
    batch_size: usize,
) -> Result<()> {
    let in_range = c[0] >= 0
        && (c[0] as usize) < batch_size
        && (0..3).all(|a| c[a + 1] >= 0 && (c[a + 1] as usize) < spatial_shape[a]);
    if in_range {
        Ok(())
    } else {
        Err(SparseError::OutOfRange {
            row,
            coord: c,
            shape: spatial_shape,
            batch_size,
        })
    }
}

/// Validates a coordinate list as [`CoordSet::new`] does (every site inside the grid and the batch,
/// no duplicates) by sorting instead of hashing, and returns the permutation that puts the rows in
/// (b, x, y, z) order: `None` when they already are (then no copy is needed).
///
/// A duplicate is reported as [`CoordSet::new`] reports it: the pair whose second row comes first.
pub fn validate_sorted_order(
    coords: &[Coord],
    spatial_shape: [usize; 3],
    batch_size: usize,
) -> Result<Option<Vec<u32>>> {
    check_extents(spatial_shape, batch_size, coords.len())?;
    let mut keys = Vec::with_capacity(coords.len());
    for (row, &c) in coords.iter().enumerate() {
        check_in_range(row, c, spatial_shape, batch_size)?;
        keys.push(pack(c));
    }
    if keys.windows(2).all(|w| w[0] < w[1]) {
        return Ok(None);
    }
    // (key, row) in one u128: one sort orders by key, and by row among equal keys.
    let mut tagged: Vec<u128> = keys
        .iter()
        .enumerate()
        .map(|(row, &k)| ((k as u128) << 32) | row as u128)
        .collect();
    tagged.sort_unstable();
    let row_of = |t: u128| (t & 0xFFFF_FFFF) as usize;
    let duplicate = tagged
        .windows(2)
        .filter(|w| w[0] >> 32 == w[1] >> 32)
        .min_by_key(|w| row_of(w[1]));
    if let Some(w) = duplicate {
        // rows ascend within a key's group, so the window with the group's smallest second row
        // starts at the group's first row
        return Err(SparseError::Duplicate {
            coord: unpack((w[0] >> 32) as u64),
            first: row_of(w[0]),
            second: row_of(w[1]),
        });
    }
    Ok(Some(tagged.into_iter().map(|t| row_of(t) as u32).collect()))
}

/// Sorts and deduplicates packed keys and returns the coordinates (internal helper).
pub(crate) fn unique_sorted(mut keys: Vec<u64>) -> Vec<Coord> {
    keys.sort_unstable();
    keys.dedup();
    keys.into_iter().map(unpack).collect()
}

/// Every site of a `[B, X, Y, Z]` grid in C order (`b` slowest, `z` fastest): the row order of a dense
/// `[B, C, X, Y, Z]` tensor permuted to `[B, X, Y, Z, C]` and flattened.
pub fn full_grid_coords(batch: usize, dims: [usize; 3]) -> Vec<Coord> {
    let mut coords = Vec::with_capacity(batch * dims.iter().product::<usize>());
    for b in 0..batch {
        for x in 0..dims[0] {
            for y in 0..dims[1] {
                for z in 0..dims[2] {
                    coords.push([b as i32, x as i32, y as i32, z as i32]);
                }
            }
        }
    }
    coords
}

/// Shared handle.
pub type CoordSetRef = Arc<CoordSet>;

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn pack_order_is_lexicographic() {
        let a = [0, 5, 1, 9];
        let b = [0, 5, 2, 0];
        let c = [1, 0, 0, 0];
        assert!(pack(a) < pack(b) && pack(b) < pack(c));
        assert_eq!(unpack(pack([3, 17, 300, 31])), [3, 17, 300, 31]);
    }

    #[test]
    fn index_insert_get_grow() {
        let mut idx = CoordIndex::with_capacity(2);
        for i in 0..1000u32 {
            assert_eq!(
                idx.insert(pack([0, i as i32, 2 * i as i32 % 97, 3]), i),
                None
            );
        }
        assert_eq!(idx.len(), 1000);
        for i in 0..1000u32 {
            assert_eq!(idx.get(pack([0, i as i32, 2 * i as i32 % 97, 3])), Some(i));
        }
        assert_eq!(idx.get(pack([1, 0, 0, 0])), None);
        assert_eq!(idx.insert(pack([0, 0, 0, 3]), 7), Some(0));
    }

    #[test]
    fn coordset_rejects_bad_input() {
        let e = CoordSet::new(vec![[0, 1, 1, 1], [0, 4, 0, 0]], [4, 4, 4], 1).unwrap_err();
        assert!(matches!(e, SparseError::OutOfRange { row: 1, .. }));
        let e = CoordSet::new(vec![[0, 1, 1, 1], [0, 1, 1, 1]], [4, 4, 4], 1).unwrap_err();
        assert!(matches!(
            e,
            SparseError::Duplicate {
                first: 0,
                second: 1,
                ..
            }
        ));
        let e = CoordSet::new(vec![[1, 1, 1, 1]], [4, 4, 4], 1).unwrap_err();
        assert!(matches!(e, SparseError::OutOfRange { .. }));
        let e = CoordSet::new(vec![[0, -1, 1, 1]], [4, 4, 4], 1).unwrap_err();
        assert!(matches!(e, SparseError::OutOfRange { .. }));
        assert!(CoordSet::new(vec![], [0, 4, 4], 1).is_err());
    }

    /// The sorting validation accepts and refuses what `CoordSet::new` does, reports a duplicate
    /// as it does (the pair whose second row comes first), and sorts.
    #[test]
    fn validate_sorted_order_agrees_with_coordset_new() {
        let sorted = vec![[0, 0, 1, 1], [0, 1, 0, 0], [1, 0, 0, 0]];
        assert_eq!(validate_sorted_order(&sorted, [4, 4, 4], 2).unwrap(), None);
        let shuffled = vec![[1, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 1]];
        assert_eq!(
            validate_sorted_order(&shuffled, [4, 4, 4], 2).unwrap(),
            Some(vec![2, 1, 0])
        );
        let bad: [Vec<Coord>; 4] = [
            vec![[0, 1, 1, 1], [0, 4, 0, 0]],
            vec![[1, 1, 1, 1]],
            vec![[0, -1, 1, 1]],
            // two duplicated sites; the one whose repeat comes first (rows 0 and 2) is reported
            vec![
                [0, 2, 2, 2],
                [0, 3, 3, 3],
                [0, 2, 2, 2],
                [0, 3, 3, 3],
                [0, 2, 2, 2],
            ],
        ];
        for coords in bad {
            let a = validate_sorted_order(&coords, [4, 4, 4], 1).unwrap_err();
            let b = CoordSet::new(coords.clone(), [4, 4, 4], 1).unwrap_err();
            assert_eq!(a.to_string(), b.to_string(), "{coords:?}");
        }
        assert!(validate_sorted_order(&[], [0, 4, 4], 1).is_err());
        assert!(validate_sorted_order(&[], [4, 4, 4], 0).is_err());
    }
}
