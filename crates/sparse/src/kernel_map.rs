//! Kernel maps (rulebooks): for every kernel offset, the (input row, output row) pairs it connects.
//!
//! Building a map is integer work kept apart from the feature compute ([`crate::backend`]), as in
//! spconv and torchsparse. [`conv_map`] builds the pairs on the host; [`conv_map_deferred`] builds
//! only the output sites there and leaves the pairs to whoever needs them: a device builds its
//! gather table from the map's [`MapSource`] (`crate::cube`), the host builds the pairs on first
//! use (the same pairs). Maps are cached inside the input [`CoordSet`] under a typed
//! [`KernelMapKey`].
//!
//! Offsets are numbered `k = (kx * KY + ky) * KZ + kz`, matching weights `[Cout, kx, ky, kz, Cin]` seen as
//! `[Cout, K, Cin]`. The arithmetic is cross-correlation, as in spconv and torch (docs/reference_models.md §3):
//! a regular/submanifold convolution connects output `o` to input `i = o * stride - padding + k * dilation`;
//! a transposed convolution connects input `i` to output `o = i * stride - padding + k * dilation`.

use crate::coords::{pack, unique_sorted, Coord, CoordSet, MAX_AXIS_EXTENT};
use crate::error::{Result, SparseError};
use rayon::prelude::*;
use std::any::Any;
use std::sync::{Arc, Mutex, OnceLock, Weak};
use std::time::Instant;

/// Kernel size, stride, padding and dilation of a convolution or pooling, per axis (x, y, z).
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash)]
pub struct ConvGeometry {
    /// Kernel extent per axis.
    pub kernel: [usize; 3],
    /// Stride per axis.
    pub stride: [usize; 3],
    /// Zero padding per axis.
    pub padding: [usize; 3],
    /// Dilation per axis.
    pub dilation: [usize; 3],
}

impl ConvGeometry {
    /// Stride 1, no padding, no dilation.
    pub fn new(kernel: [usize; 3]) -> Self {
        Self {
            kernel,
            stride: [1; 3],
            padding: [0; 3],
            dilation: [1; 3],
        }
    }
    /// Sets the stride.
    pub fn with_stride(mut self, stride: [usize; 3]) -> Self {
        self.stride = stride;
        self
    }
    /// Sets the padding.
    pub fn with_padding(mut self, padding: [usize; 3]) -> Self {
        self.padding = padding;
        self
    }
    /// Sets the dilation.
    pub fn with_dilation(mut self, dilation: [usize; 3]) -> Self {
        self.dilation = dilation;
        self
    }
    /// Number of kernel offsets.
    pub fn volume(&self) -> usize {
        self.kernel.iter().product()
    }
    /// The kernel offsets `[kx, ky, kz]` in map order.
    pub fn offsets(&self) -> Vec<[usize; 3]> {
        let [a, b, c] = self.kernel;
        let mut v = Vec::with_capacity(a * b * c);
        for x in 0..a {
            for y in 0..b {
                for z in 0..c {
                    v.push([x, y, z]);
                }
            }
        }
        v
    }
    /// Errors unless kernel, stride and dilation are positive and every value (padding included,
    /// and the dilated kernel's reach) is at most [`MAX_AXIS_EXTENT`], the largest grid axis: the
    /// site arithmetic is in `i32` and nothing larger can reach a site.
    fn validate(&self) -> Result<()> {
        if self.kernel.contains(&0) || self.stride.contains(&0) || self.dilation.contains(&0) {
            return Err(SparseError::Config(format!(
                "kernel {:?}, stride {:?} and dilation {:?} must be positive",
                self.kernel, self.stride, self.dilation
            )));
        }
        let too_large = (0..3).any(|a| {
            let reach = (self.kernel[a] - 1).saturating_mul(self.dilation[a]);
            [
                self.kernel[a],
                self.stride[a],
                self.padding[a],
                self.dilation[a],
                reach,
            ]
            .iter()
            .any(|&v| v > MAX_AXIS_EXTENT)
        });
        if too_large {
            return Err(SparseError::Config(format!(
                "kernel {:?}, stride {:?}, padding {:?}, dilation {:?}: each value and each \
                 (kernel - 1) * dilation must be at most {MAX_AXIS_EXTENT}, the largest grid axis",
                self.kernel, self.stride, self.padding, self.dilation
            )));
        }
        Ok(())
    }

    /// Errors unless every axis of an output grid is at most [`MAX_AXIS_EXTENT`].
    fn check_output_shape(&self, out: [usize; 3]) -> Result<[usize; 3]> {
        if out.iter().any(|&s| s > MAX_AXIS_EXTENT) {
            return Err(SparseError::Config(format!(
                "output spatial shape {out:?} (kernel {:?}, stride {:?}, padding {:?}, dilation \
                 {:?}): each axis must be at most {MAX_AXIS_EXTENT}",
                self.kernel, self.stride, self.padding, self.dilation
            )));
        }
        Ok(out)
    }
    /// Output spatial shape of a regular (strided) convolution: `floor((in + 2p - d(k-1) - 1)/s) + 1`.
    pub fn regular_output_shape(&self, input: [usize; 3]) -> Result<[usize; 3]> {
        self.validate()?;
        let mut out = [0; 3];
        for a in 0..3 {
            let num = input[a] as i64 + 2 * self.padding[a] as i64
                - self.dilation[a] as i64 * (self.kernel[a] as i64 - 1)
                - 1;
            if num < 0 {
                return Err(SparseError::Config(format!(
                    "kernel {:?} (dilation {:?}, padding {:?}) is larger than the input shape {:?}",
                    self.kernel, self.dilation, self.padding, input
                )));
            }
            out[a] = (num as usize) / self.stride[a] + 1;
        }
        self.check_output_shape(out)
    }
    /// Output spatial shape of a transposed convolution: `(in-1)s - 2p + d(k-1) + 1 + output_padding`.
    pub fn transposed_output_shape(
        &self,
        input: [usize; 3],
        output_padding: [usize; 3],
    ) -> Result<[usize; 3]> {
        self.validate()?;
        if output_padding.iter().any(|&p| p > MAX_AXIS_EXTENT) {
            return Err(SparseError::Config(format!(
                "output padding {output_padding:?}: each value must be at most {MAX_AXIS_EXTENT}"
            )));
        }
        let mut out = [0; 3];
        for a in 0..3 {
            let v = (input[a] as i64 - 1) * self.stride[a] as i64 - 2 * self.padding[a] as i64
                + self.dilation[a] as i64 * (self.kernel[a] as i64 - 1)
                + 1
                + output_padding[a] as i64;
            if v <= 0 {
                return Err(SparseError::Config(format!(
                    "transposed convolution output shape would be empty on axis {a}"
                )));
            }
            out[a] = v as usize;
        }
        self.check_output_shape(out)
    }
}

/// Which rule connects inputs and outputs.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash)]
pub enum MapKind {
    /// Outputs are the input sites; the kernel is centred (padding `(k/2)*d`, stride 1). Kernel must be odd.
    Submanifold,
    /// Every output reached by an active input; grows the active set at stride 1, downsamples when strided.
    Regular,
    /// Transposed convolution; upsamples.
    Transposed {
        /// Extra size added to one side of the output shape.
        output_padding: [usize; 3],
    },
}

/// Typed cache key of a kernel map (never a string).
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash)]
pub struct KernelMapKey {
    /// The connection rule.
    pub kind: MapKind,
    /// Kernel, stride, padding, dilation.
    pub geometry: ConvGeometry,
    /// Tensor stride of the input set.
    pub tensor_stride: [usize; 3],
}

/// The pairs of one convolution, grouped by kernel offset, sorted by output row inside each group.
///
/// A map built for a device ([`conv_map_deferred`]) holds its [`MapSource`] (the two site lists
/// and the rule between them) and builds its host pairs only when something on the host asks for
/// them; a device builds its table from the same source ([`crate::cube`]).
#[derive(Debug)]
pub struct KernelMap {
    kernel_volume: usize,
    n_in: usize,
    n_out: usize,
    pairs: OnceLock<Pairs>,
    source: Option<MapSource>,
    transposed: OnceLock<Arc<KernelMap>>,
    gather_table: OnceLock<Option<Vec<u32>>>,
    by_output: OnceLock<OutputPairs>,
    device_tables: DeviceTables,
}

/// The pair lists of a map, grouped by offset.
#[derive(Debug)]
struct Pairs {
    in_idx: Vec<u32>,
    out_idx: Vec<u32>,
    offset_start: Vec<usize>,
    build_ms: f64,
}

/// How an output site reaches its input site through kernel offset `k`.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash)]
pub enum MapRule {
    /// `input = output · stride - padding + k · dilation`: regular and strided convolutions,
    /// and submanifold ones (stride 1, padding `(kernel / 2) · dilation`).
    Forward,
    /// `input = (output + padding - k · dilation) / stride` where the division is exact:
    /// transposed convolutions, and the transpose of a [`MapRule::Forward`] map.
    Backward,
}

/// One side of a map: its sites (row `i` = coordinate `i`) and the grid they lie in. Made only
/// from a [`CoordSet`], so every site is unique and on its grid (what a device builder relies on).
#[derive(Clone, Debug)]
pub struct Sites {
    /// `(b, x, y, z)` of every row.
    pub(crate) coords: Arc<Vec<Coord>>,
    /// Grid shape `(X, Y, Z)`.
    pub(crate) shape: [usize; 3],
    /// Batch size.
    pub(crate) batch: usize,
    /// The sites on compute devices, shared with the set and every map built on it.
    pub(crate) device: Arc<DeviceTables>,
}

impl Sites {
    /// `(b, x, y, z)` of every row.
    pub fn coords(&self) -> &[Coord] {
        &self.coords
    }
    /// Grid shape `(X, Y, Z)`.
    pub fn shape(&self) -> [usize; 3] {
        self.shape
    }
    /// Batch size.
    pub fn batch(&self) -> usize {
        self.batch
    }

    /// The sites uploaded to one compute device: the first cached value of type `T` that
    /// `matches` accepts, or else the one `make` builds, kept with the set they come from, so
    /// that the maps of one set (a level's submanifold map, the strided map into it and its
    /// transpose) upload its sites once. Any backend type fits, as for
    /// [`KernelMap::device_table`].
    pub fn device_table<T: Any + Send + Sync + Clone>(
        &self,
        matches: impl Fn(&T) -> bool,
        make: impl FnOnce() -> T,
    ) -> T {
        self.device.get_or_make(matches, make)
    }

    fn of(set: &CoordSet) -> Self {
        Self {
            coords: set.shared_coords(),
            shape: set.spatial_shape(),
            batch: set.batch_size(),
            device: set.device_sites(),
        }
    }
}

/// What a map connects: output row `o` and offset `k` reach the input site
/// `rule(outputs[o], k)` when it is one of `inputs`. Everything a builder needs, on the host
/// ([`KernelMap::pairs`]) or on a device. Made only by [`conv_map_deferred`] (read-only outside
/// this crate).
#[derive(Clone, Debug)]
pub struct MapSource {
    /// The rule.
    pub(crate) rule: MapRule,
    /// Kernel, stride, padding and dilation of the rule.
    pub(crate) geometry: ConvGeometry,
    /// The map's input rows.
    pub(crate) inputs: Sites,
    /// The map's output rows.
    pub(crate) outputs: Sites,
}

impl MapSource {
    /// The rule.
    pub fn rule(&self) -> MapRule {
        self.rule
    }
    /// Kernel, stride, padding and dilation of the rule.
    pub fn geometry(&self) -> ConvGeometry {
        self.geometry
    }
    /// The map's input rows.
    pub fn inputs(&self) -> &Sites {
        &self.inputs
    }
    /// The map's output rows.
    pub fn outputs(&self) -> &Sites {
        &self.outputs
    }

    /// The input coordinate that output coordinate `o` reaches through offset `k`, before the
    /// bounds check (`None` where a [`MapRule::Backward`] division is not exact or negative).
    #[inline]
    pub fn input_of(&self, o: Coord, k: [usize; 3]) -> Option<Coord> {
        let g = &self.geometry;
        let mut c = [o[0], 0, 0, 0];
        for a in 0..3 {
            let (s, p, d) = (
                g.stride[a] as i32,
                g.padding[a] as i32,
                g.dilation[a] as i32,
            );
            c[a + 1] = match self.rule {
                MapRule::Forward => o[a + 1] * s - p + k[a] as i32 * d,
                MapRule::Backward => {
                    let t = o[a + 1] + p - k[a] as i32 * d;
                    if t < 0 || t % s != 0 {
                        return None;
                    }
                    t / s
                }
            };
        }
        Some(c)
    }

    /// The source of the transposed map: sides swapped, the inverse rule.
    pub fn transposed(&self) -> MapSource {
        MapSource {
            rule: match self.rule {
                MapRule::Forward => MapRule::Backward,
                MapRule::Backward => MapRule::Forward,
            },
            geometry: self.geometry,
            inputs: self.outputs.clone(),
            outputs: self.inputs.clone(),
        }
    }

    /// The host pairs (a dense row table of the inputs where it pays off, else a hash index).
    fn build(&self) -> Pairs {
        let inputs = &self.inputs;
        let lookups = self.outputs.coords.len() * self.geometry.volume();
        let input_of = |o, k| self.input_of(o, k);
        match DenseRows::of_coords(&inputs.coords, inputs.batch, inputs.shape, lookups) {
            Some(t) => {
                build_pairs_with(&self.outputs.coords, &self.geometry, input_of, |c| t.get(c))
            }
            None => {
                let mut index = crate::coords::CoordIndex::with_capacity(inputs.coords.len());
                for (row, &c) in inputs.coords.iter().enumerate() {
                    index.insert(pack(c), row as u32);
                }
                let inside = |c: Coord| {
                    c[0] >= 0
                        && (c[0] as usize) < inputs.batch
                        && (0..3).all(|a| c[a + 1] >= 0 && (c[a + 1] as usize) < inputs.shape[a])
                };
                build_pairs_with(&self.outputs.coords, &self.geometry, input_of, |c| {
                    if inside(c) {
                        index.get(pack(c))
                    } else {
                        None
                    }
                })
            }
        }
    }
}

/// Copies of a map's tables, or of a set's sites, on compute devices (see
/// [`KernelMap::device_table`], [`Sites::device_table`]), type-erased so that the map and the set
/// stay independent of any backend.
#[derive(Default)]
pub(crate) struct DeviceTables(Mutex<Vec<Box<dyn Any + Send + Sync>>>);

impl DeviceTables {
    /// The first cached value of type `T` that `matches` accepts, or else the one `make` builds,
    /// which is kept.
    fn get_or_make<T: Any + Send + Sync + Clone>(
        &self,
        matches: impl Fn(&T) -> bool,
        make: impl FnOnce() -> T,
    ) -> T {
        let mut tables = self
            .0
            .lock()
            .unwrap_or_else(|poisoned| poisoned.into_inner());
        if let Some(t) = tables
            .iter()
            .filter_map(|b| b.downcast_ref::<T>())
            .find(|t| matches(t))
        {
            return t.clone();
        }
        let t = make();
        tables.push(Box::new(t.clone()));
        t
    }
}

impl std::fmt::Debug for DeviceTables {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        let n = self.0.lock().map(|v| v.len()).unwrap_or(0);
        write!(f, "DeviceTables({n})")
    }
}

/// A map's pairs grouped by output row (compressed sparse rows): the pairs of output `o` are
/// entries `start[o]..start[o + 1]` of `ins` / `offsets`, in ascending kernel offset. The layout of
/// an output-major compute, which writes each output row once (see [`crate::host`]).
#[derive(Debug)]
pub struct OutputPairs {
    /// `n_out + 1` entry offsets.
    pub start: Vec<u32>,
    /// Input row of each entry.
    pub ins: Vec<u32>,
    /// Kernel offset of each entry.
    pub offsets: Vec<u32>,
}

impl KernelMap {
    /// Builds a map from explicit per-offset pair lists (each sorted by output row).
    pub fn from_pairs(n_in: usize, n_out: usize, pairs: Vec<(Vec<u32>, Vec<u32>)>) -> Result<Self> {
        let mut in_idx = Vec::new();
        let mut out_idx = Vec::new();
        let mut offset_start = vec![0];
        for (ins, outs) in pairs {
            if ins.len() != outs.len() {
                return Err(SparseError::Shape("pair lists of different lengths".into()));
            }
            if ins.iter().any(|&i| i as usize >= n_in) || outs.iter().any(|&o| o as usize >= n_out)
            {
                return Err(SparseError::Shape("pair index out of range".into()));
            }
            if outs.windows(2).any(|w| w[0] > w[1]) {
                return Err(SparseError::Shape(
                    "pairs must be sorted by output row".into(),
                ));
            }
            in_idx.extend_from_slice(&ins);
            out_idx.extend_from_slice(&outs);
            offset_start.push(in_idx.len());
        }
        Ok(Self::eager(
            offset_start.len() - 1,
            n_in,
            n_out,
            Pairs {
                in_idx,
                out_idx,
                offset_start,
                build_ms: 0.0,
            },
        ))
    }

    /// A map with its host pairs.
    fn eager(kernel_volume: usize, n_in: usize, n_out: usize, pairs: Pairs) -> Self {
        Self {
            kernel_volume,
            n_in,
            n_out,
            pairs: OnceLock::from(pairs),
            source: None,
            transposed: OnceLock::new(),
            gather_table: OnceLock::new(),
            by_output: OnceLock::new(),
            device_tables: DeviceTables::default(),
        }
    }

    /// A map that builds its host pairs from `source` on first use.
    fn deferred(source: MapSource) -> Self {
        Self {
            kernel_volume: source.geometry.volume(),
            n_in: source.inputs.coords.len(),
            n_out: source.outputs.coords.len(),
            pairs: OnceLock::new(),
            source: Some(source),
            transposed: OnceLock::new(),
            gather_table: OnceLock::new(),
            by_output: OnceLock::new(),
            device_tables: DeviceTables::default(),
        }
    }

    /// The host pairs, built now if the map was deferred.
    fn host(&self) -> &Pairs {
        self.pairs.get_or_init(|| {
            self.source
                .as_ref()
                .expect("a map without pairs has a source")
                .build()
        })
    }

    /// The sites and rule of a deferred map ([`conv_map_deferred`]), from which a device builds
    /// its table without the host pairs; `None` for a map built with its pairs.
    pub fn source(&self) -> Option<&MapSource> {
        self.source.as_ref()
    }

    /// Whether the host pairs exist yet (always for maps not deferred).
    pub fn has_host_pairs(&self) -> bool {
        self.pairs.get().is_some()
    }

    /// Number of kernel offsets K.
    pub fn kernel_volume(&self) -> usize {
        self.kernel_volume
    }
    /// Number of input rows.
    pub fn n_in(&self) -> usize {
        self.n_in
    }
    /// Number of output rows.
    pub fn n_out(&self) -> usize {
        self.n_out
    }
    /// Total number of pairs (builds the host pairs of a deferred map).
    pub fn num_pairs(&self) -> usize {
        self.host().in_idx.len()
    }
    /// Milliseconds spent building this map's host pairs (for a regular convolution on a
    /// well-filled grid also the output sites, which the dense path finds in the same passes);
    /// 0 for a deferred map whose pairs were never asked for.
    pub fn build_ms(&self) -> f64 {
        self.pairs.get().map_or(0.0, |p| p.build_ms)
    }
    /// The (input rows, output rows) of offset `k` (builds the host pairs of a deferred map).
    pub fn pairs(&self, k: usize) -> (&[u32], &[u32]) {
        let p = self.host();
        let (a, b) = (p.offset_start[k], p.offset_start[k + 1]);
        (&p.in_idx[a..b], &p.out_idx[a..b])
    }
    /// Number of neighbours (pairs) of every output row.
    pub fn neighbour_counts(&self) -> Vec<u32> {
        let mut c = vec![0u32; self.n_out];
        for &o in &self.host().out_idx {
            c[o as usize] += 1;
        }
        c
    }
    /// The input row of every (output row, kernel offset), row-major `[n_out, K]`, with `n_in` where
    /// the offset has no input: the layout of an implicit GEMM (one gather of `[n_out, K·C_in]`,
    /// one matrix product), used by the portable compute path. `None` when some output row has two
    /// inputs at the same offset (possible only for maps built with [`KernelMap::from_pairs`]).
    /// Computed once and cached.
    pub fn gather_table(&self) -> Option<&[u32]> {
        self.gather_table
            .get_or_init(|| {
                let kv = self.kernel_volume;
                let mut table = vec![self.n_in as u32; self.n_out * kv];
                for k in 0..kv {
                    let (ins, outs) = self.pairs(k);
                    for (&i, &o) in ins.iter().zip(outs) {
                        let slot = &mut table[o as usize * kv + k];
                        if *slot != self.n_in as u32 {
                            return None;
                        }
                        *slot = i;
                    }
                }
                Some(table)
            })
            .as_deref()
    }

    /// A table derived from this map on one compute device (the gather table uploaded to a GPU):
    /// the first cached value of type `T` that `matches` accepts, or else the one `make` builds,
    /// which is kept with the map (so a frame's layers that share a map, and their backward
    /// passes, upload it once). Any backend type fits; the map never looks inside.
    pub fn device_table<T: Any + Send + Sync + Clone>(
        &self,
        matches: impl Fn(&T) -> bool,
        make: impl FnOnce() -> T,
    ) -> T {
        self.device_tables.get_or_make(matches, make)
    }

    /// The pairs grouped by output row, in ascending kernel offset within a row (a counting sort
    /// of the pairs, `O(pairs + n_out)`). Computed once and cached.
    pub fn by_output(&self) -> &OutputPairs {
        self.by_output.get_or_init(|| {
            let mut start = vec![0u32; self.n_out + 1];
            for &o in &self.host().out_idx {
                start[o as usize + 1] += 1;
            }
            for o in 0..self.n_out {
                start[o + 1] += start[o];
            }
            let mut next = start.clone();
            let total = self.num_pairs();
            let mut ins = vec![0u32; total];
            let mut offsets = vec![0u32; total];
            for k in 0..self.kernel_volume {
                let (ki, ko) = self.pairs(k);
                for (&i, &o) in ki.iter().zip(ko) {
                    let slot = &mut next[o as usize];
                    ins[*slot as usize] = i;
                    offsets[*slot as usize] = k as u32;
                    *slot += 1;
                }
            }
            OutputPairs {
                start,
                ins,
                offsets,
            }
        })
    }

    /// The same pairs with every input row `i` renamed `rows[i]`: the map of the same convolution
    /// over the input rows in another order (e.g. the caller's order where the map was built on
    /// sorted sites), so that the features need not be permuted. `rows` must be a permutation of
    /// `0..n_in`.
    pub(crate) fn with_input_rows(&self, rows: &[u32]) -> KernelMap {
        debug_assert_eq!(rows.len(), self.n_in);
        let p = self.host();
        KernelMap::eager(
            self.kernel_volume,
            self.n_in,
            self.n_out,
            Pairs {
                in_idx: p.in_idx.iter().map(|&i| rows[i as usize]).collect(),
                out_idx: p.out_idx.clone(),
                offset_start: p.offset_start.clone(),
                build_ms: p.build_ms,
            },
        )
    }

    /// The map with inputs and outputs swapped (same offset numbering), sorted by its new output rows.
    /// Used by gradients and by inverse convolution. Computed once and cached; the transpose of a
    /// deferred map is deferred too (its source transposed), so no host pairs are built for it.
    pub fn transposed(&self) -> Arc<KernelMap> {
        self.transposed
            .get_or_init(|| {
                if let (Some(source), None) = (&self.source, self.pairs.get()) {
                    return Arc::new(KernelMap::deferred(source.transposed()));
                }
                let t0 = Instant::now();
                let mut in_idx = Vec::with_capacity(self.num_pairs());
                let mut out_idx = Vec::with_capacity(self.num_pairs());
                let mut offset_start = vec![0];
                for k in 0..self.kernel_volume {
                    let (ins, outs) = self.pairs(k);
                    let mut order: Vec<u32> = (0..ins.len() as u32).collect();
                    order.sort_by_key(|&j| ins[j as usize]);
                    for j in order {
                        in_idx.push(outs[j as usize]);
                        out_idx.push(ins[j as usize]);
                    }
                    offset_start.push(in_idx.len());
                }
                Arc::new(KernelMap::eager(
                    self.kernel_volume,
                    self.n_out,
                    self.n_in,
                    Pairs {
                        in_idx,
                        out_idx,
                        offset_start,
                        build_ms: t0.elapsed().as_secs_f64() * 1e3,
                    },
                ))
            })
            .clone()
    }
}

/// A cached convolution: its map and its output set (`None` when the output set is the input set).
#[derive(Clone, Debug)]
pub(crate) struct ConvCacheEntry {
    pub(crate) output: Option<Weak<CoordSet>>,
    pub(crate) map: Arc<KernelMap>,
}

/// Link from a downsampled set back to the set and map of the strided convolution that produced it.
#[derive(Clone, Debug)]
pub(crate) struct ParentLink {
    pub(crate) geometry: ConvGeometry,
    pub(crate) parent: Arc<CoordSet>,
    pub(crate) map: Arc<KernelMap>,
}

const CHUNK: usize = 2048;

/// A grid of `[B, X, Y, Z]` voxels always gets a dense row table (4 bytes per voxel) when it has at
/// most this many voxels per active site: the table then costs at most twice the hash index's memory
/// (16 bytes per slot at load factor 1/2), and a lookup is one load instead of a hash probe.
const DENSE_VOXELS_PER_SITE: usize = 16;

/// A sparser grid still gets the table when filling it costs less than the hash probes it saves
/// (about [`DENSE_VOXELS_PER_LOOKUP`] voxels of memset and scan per probe, measured on the spconv
/// comparison's cases: BENCHMARKS.md) and it holds at most this many voxels (16 MiB). Memory stays
/// linear in the active sites: at most `max(16, DENSE_VOXELS_PER_LOOKUP · K)` voxels per site for a
/// kernel of volume K, and at most a constant.
const DENSE_MAX_VOXELS: usize = 1 << 22;

/// Voxels of table that one saved hash probe pays for (see [`DENSE_MAX_VOXELS`]).
const DENSE_VOXELS_PER_LOOKUP: usize = 8;

/// Row of every voxel of a `[B, X, Y, Z]` grid (`u32::MAX` = inactive): the dense alternative to the
/// hash index for kernel-map building on well-filled grids.
struct DenseRows {
    shape: [usize; 3],
    batch: usize,
    rows: Vec<u32>,
}

impl DenseRows {
    /// An empty table for the grid, if it pays off for `n_sites` active sites and `lookups` lookups
    /// (see [`DENSE_VOXELS_PER_SITE`] and [`DENSE_MAX_VOXELS`]).
    fn empty(batch: usize, shape: [usize; 3], n_sites: usize, lookups: usize) -> Option<Self> {
        let volume = shape.iter().try_fold(batch, |acc, &d| acc.checked_mul(d))?;
        let well_filled = volume <= DENSE_VOXELS_PER_SITE.saturating_mul(n_sites);
        let pays_off =
            volume <= DENSE_MAX_VOXELS && volume <= DENSE_VOXELS_PER_LOOKUP.saturating_mul(lookups);
        if n_sites == 0 || !(well_filled || pays_off) {
            return None;
        }
        Some(Self {
            shape,
            batch,
            rows: vec![u32::MAX; volume],
        })
    }

    /// The table of an existing set, if it pays off for `lookups` lookups.
    fn of_set(set: &CoordSet, lookups: usize) -> Option<Self> {
        Self::of_coords(set.coords(), set.batch_size(), set.spatial_shape(), lookups)
    }

    /// The table of valid, unique sites of a `[batch, shape]` grid.
    fn of_coords(
        coords: &[Coord],
        batch: usize,
        shape: [usize; 3],
        lookups: usize,
    ) -> Option<Self> {
        let mut t = Self::empty(batch, shape, coords.len(), lookups)?;
        for (row, &c) in coords.iter().enumerate() {
            let i = t.lin_unchecked(c);
            t.rows[i] = row as u32;
        }
        Some(t)
    }

    #[inline]
    fn lin_unchecked(&self, c: Coord) -> usize {
        let [sx, sy, sz] = self.shape;
        ((c[0] as usize * sx + c[1] as usize) * sy + c[2] as usize) * sz + c[3] as usize
    }

    #[inline]
    fn lin(&self, c: Coord) -> Option<usize> {
        let inside = c[0] >= 0
            && (c[0] as usize) < self.batch
            && (0..3).all(|a| c[a + 1] >= 0 && (c[a + 1] as usize) < self.shape[a]);
        inside.then(|| self.lin_unchecked(c))
    }

    #[inline]
    fn get(&self, c: Coord) -> Option<u32> {
        self.lin(c).map(|i| self.rows[i]).filter(|&r| r != u32::MAX)
    }
}

/// Output `o` of a regular convolution connected to input `c` through offset `k`
/// (`o = (c + p - k d) / s` when exact and inside the output grid).
#[inline]
fn regular_output_of(
    c: Coord,
    k: [usize; 3],
    s: [i32; 3],
    p: [i32; 3],
    d: [i32; 3],
    os: [i32; 3],
) -> Option<Coord> {
    let mut o = [c[0], 0, 0, 0];
    for a in 0..3 {
        let t = c[a + 1] + p[a] - k[a] as i32 * d[a];
        if t < 0 || t % s[a] != 0 || t / s[a] >= os[a] {
            return None;
        }
        o[a + 1] = t / s[a];
    }
    Some(o)
}

/// The output sites of a regular convolution on a well-filled grid (see [`build_regular_dense`],
/// steps 1 and 2), with the dense table of their rows; `None` when the table does not pay off.
fn regular_outputs_dense(
    input: &CoordSet,
    geom: &ConvGeometry,
    out_shape: [usize; 3],
) -> Option<(Vec<Coord>, DenseRows)> {
    let kv = geom.volume();
    let mut table = DenseRows::empty(input.batch_size(), out_shape, input.len(), input.len() * kv)?;
    let mut scratch = Vec::new();
    // 1. Mark every reachable output.
    for &c in input.coords() {
        for_each_regular_output(c, geom, out_shape, &mut scratch, |_, lin| {
            table.rows[lin] = 0
        });
    }
    // 2. Number them in linear (= lexicographic) order.
    let mut outputs = Vec::new();
    let [sx, sy, sz] = out_shape;
    let mut next = 0u32;
    let mut i = 0usize;
    for b in 0..input.batch_size() as i32 {
        for x in 0..sx as i32 {
            for y in 0..sy as i32 {
                for z in 0..sz as i32 {
                    let r = &mut table.rows[i];
                    if *r == 0 {
                        *r = next;
                        next += 1;
                        outputs.push([b, x, y, z]);
                    }
                    i += 1;
                }
            }
        }
    }
    Some((outputs, table))
}

/// Regular convolution on a well-filled grid, without hashing: mark the outputs reached from every
/// input and offset in a dense table of the output grid, number them in (b, x, y, z) order by one scan
/// of the table, then emit the pairs input-major over the inputs in (b, x, y, z) order. For a fixed
/// offset the input → output correspondence is a translation followed by an exact division, which
/// preserves that order, so each offset's pairs come out sorted by output row without a sort.
/// `None` when the output grid is too large for a table (the hash path is used then).
fn build_regular_dense(
    input: &CoordSet,
    geom: &ConvGeometry,
    out_shape: [usize; 3],
) -> Option<(Vec<Coord>, KernelMap)> {
    let t0 = Instant::now();
    let kv = geom.volume();
    let (outputs, table) = regular_outputs_dense(input, geom, out_shape)?;
    // 3. Pairs, input-major in sorted input order.
    let coords = input.coords();
    let sorted = coords.windows(2).all(|w| pack(w[0]) < pack(w[1]));
    let order: Vec<u32> = if sorted {
        (0..coords.len() as u32).collect()
    } else {
        input.sorted_order().into_iter().map(|i| i as u32).collect()
    };
    let table = &table;
    let chunks: Vec<Vec<(Vec<u32>, Vec<u32>)>> = order
        .par_chunks(CHUNK)
        .map(|chunk| {
            let mut per: Vec<(Vec<u32>, Vec<u32>)> = (0..kv)
                .map(|_| {
                    (
                        Vec::with_capacity(chunk.len()),
                        Vec::with_capacity(chunk.len()),
                    )
                })
                .collect();
            let mut scratch = Vec::new();
            for &row in chunk {
                for_each_regular_output(
                    coords[row as usize],
                    geom,
                    out_shape,
                    &mut scratch,
                    |k, lin| {
                        per[k].0.push(row);
                        per[k].1.push(table.rows[lin]);
                    },
                );
            }
            per
        })
        .collect();
    let map = KernelMap::eager(kv, input.len(), outputs.len(), assemble(kv, &chunks, t0));
    Some((outputs, map))
}

/// Calls `f(k, linear output index)` for every offset `k` through which input `c` reaches an output of
/// a regular convolution on an output grid of `out_shape` (linear index `((b·X + x)·Y + y)·Z + z`).
/// The per-axis output coordinates are computed once per kernel index (`Kx + Ky + Kz` divisions, not
/// `3·Kx·Ky·Kz`), then combined.
#[inline]
fn for_each_regular_output(
    c: Coord,
    geom: &ConvGeometry,
    out_shape: [usize; 3],
    scratch: &mut Vec<i32>,
    mut f: impl FnMut(usize, usize),
) {
    let [kx, ky, kz] = geom.kernel;
    scratch.clear();
    for a in 0..3 {
        let (s, p, d) = (
            geom.stride[a] as i32,
            geom.padding[a] as i32,
            geom.dilation[a] as i32,
        );
        for ka in 0..geom.kernel[a] {
            let t = c[a + 1] + p - ka as i32 * d;
            let o = if t < 0 || t % s != 0 { -1 } else { t / s };
            scratch.push(if o >= out_shape[a] as i32 { -1 } else { o });
        }
    }
    let (ax, rest) = scratch.split_at(kx);
    let (ay, az) = rest.split_at(ky);
    let [sx, sy, sz] = out_shape;
    let base = c[0] as usize * sx;
    for (ix, &ox) in ax.iter().enumerate() {
        if ox < 0 {
            continue;
        }
        let bx = (base + ox as usize) * sy;
        for (iy, &oy) in ay.iter().enumerate() {
            if oy < 0 {
                continue;
            }
            let bxy = (bx + oy as usize) * sz;
            let kxy = (ix * ky + iy) * kz;
            for (iz, &oz) in az.iter().enumerate() {
                if oz >= 0 {
                    f(kxy + iz, bxy + oz as usize);
                }
            }
        }
    }
}

/// Builds the pairs for the given output sites: `input_of(out_coord, offset)` gives the input coordinate
/// connected to an output through an offset (or None).
fn build_pairs<F>(
    input: &CoordSet,
    outputs: &[Coord],
    geom: &ConvGeometry,
    input_of: F,
) -> KernelMap
where
    F: Fn(Coord, [usize; 3]) -> Option<Coord> + Sync,
{
    let pairs = match DenseRows::of_set(input, outputs.len() * geom.volume()) {
        Some(table) => build_pairs_with(outputs, geom, input_of, |c| table.get(c)),
        None => build_pairs_with(outputs, geom, input_of, |c| input.find(c).map(|r| r as u32)),
    };
    KernelMap::eager(geom.volume(), input.len(), outputs.len(), pairs)
}

/// [`build_pairs`] with an explicit input lookup.
fn build_pairs_with<F, L>(outputs: &[Coord], geom: &ConvGeometry, input_of: F, find: L) -> Pairs
where
    F: Fn(Coord, [usize; 3]) -> Option<Coord> + Sync,
    L: Fn(Coord) -> Option<u32> + Sync,
{
    let t0 = Instant::now();
    let offsets = geom.offsets();
    let kv = offsets.len();
    let chunks: Vec<Vec<(Vec<u32>, Vec<u32>)>> = outputs
        .par_chunks(CHUNK)
        .enumerate()
        .map(|(ci, chunk)| {
            let mut per: Vec<(Vec<u32>, Vec<u32>)> = (0..kv)
                .map(|_| {
                    (
                        Vec::with_capacity(chunk.len()),
                        Vec::with_capacity(chunk.len()),
                    )
                })
                .collect();
            for (j, &o) in chunk.iter().enumerate() {
                let orow = (ci * CHUNK + j) as u32;
                for (k, off) in offsets.iter().enumerate() {
                    if let Some(ic) = input_of(o, *off) {
                        if let Some(irow) = find(ic) {
                            per[k].0.push(irow);
                            per[k].1.push(orow);
                        }
                    }
                }
            }
            per
        })
        .collect();
    assemble(kv, &chunks, t0)
}

/// Concatenates per-chunk, per-offset pair lists (chunks in output order) into one map.
fn assemble(kv: usize, chunks: &[Vec<(Vec<u32>, Vec<u32>)>], t0: Instant) -> Pairs {
    let total: usize = chunks
        .iter()
        .flat_map(|c| c.iter().map(|p| p.0.len()))
        .sum();
    let mut in_idx = Vec::with_capacity(total);
    let mut out_idx = Vec::with_capacity(total);
    let mut offset_start = Vec::with_capacity(kv + 1);
    offset_start.push(0);
    for k in 0..kv {
        for c in chunks {
            in_idx.extend_from_slice(&c[k].0);
            out_idx.extend_from_slice(&c[k].1);
        }
        offset_start.push(in_idx.len());
    }
    Pairs {
        in_idx,
        out_idx,
        offset_start,
        build_ms: t0.elapsed().as_secs_f64() * 1e3,
    }
}

/// The geometry of a submanifold convolution as a [`MapRule::Forward`] rule: stride 1, padding
/// `(kernel / 2) · dilation`. Errors if a kernel extent is even.
fn submanifold_geometry(kernel: [usize; 3], dilation: [usize; 3]) -> Result<ConvGeometry> {
    let geom = ConvGeometry::new(kernel).with_dilation(dilation);
    geom.validate()?;
    if kernel.iter().any(|k| k % 2 == 0) {
        return Err(SparseError::Config(format!(
            "submanifold convolution needs an odd kernel, got {kernel:?}"
        )));
    }
    Ok(geom.with_padding(std::array::from_fn(|a| (kernel[a] / 2) * dilation[a])))
}

/// Submanifold map: outputs are the inputs, the kernel centred. Errors if a kernel extent is even.
pub fn build_submanifold(
    input: &CoordSet,
    kernel: [usize; 3],
    dilation: [usize; 3],
) -> Result<KernelMap> {
    let geom = submanifold_geometry(kernel, dilation)?;
    let half: [i32; 3] = std::array::from_fn(|a| ((kernel[a] / 2) * dilation[a]) as i32);
    let d: [i32; 3] = std::array::from_fn(|a| dilation[a] as i32);
    Ok(build_pairs(input, input.coords(), &geom, |o, k| {
        Some([
            o[0],
            o[1] - half[0] + k[0] as i32 * d[0],
            o[2] - half[1] + k[1] as i32 * d[1],
            o[3] - half[2] + k[2] as i32 * d[2],
        ])
    }))
}

/// Output sites and map of a regular convolution (or pooling) with the given geometry.
pub fn build_regular(
    input: &CoordSet,
    geom: &ConvGeometry,
) -> Result<(Vec<Coord>, [usize; 3], KernelMap)> {
    let out_shape = geom.regular_output_shape(input.spatial_shape())?;
    if let Some((outputs, map)) = build_regular_dense(input, geom, out_shape) {
        return Ok((outputs, out_shape, map));
    }
    let (outputs, map) = build_regular_hashed(input, geom, out_shape);
    Ok((outputs, out_shape, map))
}

/// The output sites of a regular convolution on a sparse grid: the candidates of every input and
/// offset, sorted and deduplicated.
fn regular_outputs_hashed(
    input: &CoordSet,
    geom: &ConvGeometry,
    out_shape: [usize; 3],
) -> Vec<Coord> {
    let s: [i32; 3] = std::array::from_fn(|a| geom.stride[a] as i32);
    let p: [i32; 3] = std::array::from_fn(|a| geom.padding[a] as i32);
    let d: [i32; 3] = std::array::from_fn(|a| geom.dilation[a] as i32);
    let os: [i32; 3] = std::array::from_fn(|a| out_shape[a] as i32);
    let offsets = geom.offsets();
    // Every output o with o*s - p + k*d = i for an active i.
    let keys: Vec<u64> = input
        .coords()
        .par_chunks(CHUNK)
        .flat_map_iter(|chunk| {
            let mut v = Vec::with_capacity(chunk.len() * offsets.len());
            for &c in chunk {
                for k in &offsets {
                    if let Some(o) = regular_output_of(c, *k, s, p, d, os) {
                        v.push(pack(o));
                    }
                }
            }
            v
        })
        .collect();
    unique_sorted(keys)
}

/// Regular convolution on a sparse grid: candidate outputs of every input and offset, sorted and
/// deduplicated, then the pairs by probing the input's hash index from every output.
fn build_regular_hashed(
    input: &CoordSet,
    geom: &ConvGeometry,
    out_shape: [usize; 3],
) -> (Vec<Coord>, KernelMap) {
    let s: [i32; 3] = std::array::from_fn(|a| geom.stride[a] as i32);
    let p: [i32; 3] = std::array::from_fn(|a| geom.padding[a] as i32);
    let d: [i32; 3] = std::array::from_fn(|a| geom.dilation[a] as i32);
    let outputs = regular_outputs_hashed(input, geom, out_shape);
    let input_of = |o: Coord, k: [usize; 3]| {
        Some([
            o[0],
            o[1] * s[0] - p[0] + k[0] as i32 * d[0],
            o[2] * s[1] - p[1] + k[1] as i32 * d[1],
            o[3] * s[2] - p[2] + k[2] as i32 * d[2],
        ])
    };
    let pairs = build_pairs_with(&outputs, geom, input_of, |c| {
        input.find(c).map(|r| r as u32)
    });
    let map = KernelMap::eager(geom.volume(), input.len(), outputs.len(), pairs);
    (outputs, map)
}

/// The output sites of a transposed convolution: every `i · s - p + k · d` inside the output grid,
/// sorted and deduplicated.
fn transposed_outputs(input: &CoordSet, geom: &ConvGeometry, out_shape: [usize; 3]) -> Vec<Coord> {
    let s: [i32; 3] = std::array::from_fn(|a| geom.stride[a] as i32);
    let p: [i32; 3] = std::array::from_fn(|a| geom.padding[a] as i32);
    let d: [i32; 3] = std::array::from_fn(|a| geom.dilation[a] as i32);
    let os: [i32; 3] = std::array::from_fn(|a| out_shape[a] as i32);
    let offsets = geom.offsets();
    let keys: Vec<u64> = input
        .coords()
        .par_chunks(CHUNK)
        .flat_map_iter(|chunk| {
            let mut v = Vec::with_capacity(chunk.len() * offsets.len());
            for &c in chunk {
                'off: for k in &offsets {
                    let mut o = [c[0], 0, 0, 0];
                    for a in 0..3 {
                        let t = c[a + 1] * s[a] - p[a] + k[a] as i32 * d[a];
                        if t < 0 || t >= os[a] {
                            continue 'off;
                        }
                        o[a + 1] = t;
                    }
                    v.push(pack(o));
                }
            }
            v
        })
        .collect();
    unique_sorted(keys)
}

/// Output sites and map of a transposed convolution.
pub fn build_transposed(
    input: &CoordSet,
    geom: &ConvGeometry,
    output_padding: [usize; 3],
) -> Result<(Vec<Coord>, [usize; 3], KernelMap)> {
    let out_shape = geom.transposed_output_shape(input.spatial_shape(), output_padding)?;
    let outputs = transposed_outputs(input, geom, out_shape);
    let s: [i32; 3] = std::array::from_fn(|a| geom.stride[a] as i32);
    let p: [i32; 3] = std::array::from_fn(|a| geom.padding[a] as i32);
    let d: [i32; 3] = std::array::from_fn(|a| geom.dilation[a] as i32);
    let map = build_pairs(input, &outputs, geom, |o, k| {
        let mut i = [o[0], 0, 0, 0];
        for a in 0..3 {
            let t = o[a + 1] + p[a] - k[a] as i32 * d[a];
            if t < 0 || t % s[a] != 0 {
                return None;
            }
            i[a + 1] = t / s[a];
        }
        Some(i)
    });
    Ok((outputs, out_shape, map))
}

/// Looks up or builds (and caches) the map and output set of a convolution on `input`.
///
/// Returns the output set (the input itself for submanifold) and the map. A strided regular
/// convolution's output set records a link to `input`, used by [`inverse_of`].
pub fn conv_map(
    input: &Arc<CoordSet>,
    kind: MapKind,
    geometry: ConvGeometry,
) -> Result<(Arc<CoordSet>, Arc<KernelMap>)> {
    conv_map_with(input, kind, geometry, false)
}

/// [`conv_map`] for a backend that builds its tables on its own device: the output set is
/// computed on the host (a strided or transposed convolution's sites), the pairs are not; the
/// map holds its [`MapSource`] and builds host pairs only if something on the host asks for them
/// (the same pairs [`conv_map`] builds). A map already cached for this convolution is returned as
/// it is, deferred or not.
pub fn conv_map_deferred(
    input: &Arc<CoordSet>,
    kind: MapKind,
    geometry: ConvGeometry,
) -> Result<(Arc<CoordSet>, Arc<KernelMap>)> {
    conv_map_with(input, kind, geometry, true)
}

/// The output set and deferred map of a convolution (see [`conv_map_deferred`]).
fn deferred_map(
    input: &Arc<CoordSet>,
    kind: MapKind,
    geometry: ConvGeometry,
) -> Result<(Arc<CoordSet>, Arc<KernelMap>)> {
    let ts = input.tensor_stride();
    let (rule, geometry, output) = match kind {
        MapKind::Submanifold => (
            MapRule::Forward,
            submanifold_geometry(geometry.kernel, geometry.dilation)?,
            input.clone(),
        ),
        MapKind::Regular => {
            let shape = geometry.regular_output_shape(input.spatial_shape())?;
            let coords = match regular_outputs_dense(input, &geometry, shape) {
                Some((coords, _)) => coords,
                None => regular_outputs_hashed(input, &geometry, shape),
            };
            let stride = std::array::from_fn(|a| ts[a] * geometry.stride[a]);
            let out = CoordSet::from_valid_unique(coords, shape, input.batch_size(), stride);
            (MapRule::Forward, geometry, Arc::new(out))
        }
        MapKind::Transposed { output_padding } => {
            let shape = geometry.transposed_output_shape(input.spatial_shape(), output_padding)?;
            let coords = transposed_outputs(input, &geometry, shape);
            let stride = std::array::from_fn(|a| (ts[a] / geometry.stride[a]).max(1));
            let out = CoordSet::from_valid_unique(coords, shape, input.batch_size(), stride);
            (MapRule::Backward, geometry, Arc::new(out))
        }
    };
    let map = KernelMap::deferred(MapSource {
        rule,
        geometry,
        inputs: Sites::of(input),
        outputs: Sites::of(&output),
    });
    Ok((output, Arc::new(map)))
}

fn conv_map_with(
    input: &Arc<CoordSet>,
    kind: MapKind,
    geometry: ConvGeometry,
    deferred: bool,
) -> Result<(Arc<CoordSet>, Arc<KernelMap>)> {
    let key = KernelMapKey {
        kind,
        geometry,
        tensor_stride: input.tensor_stride(),
    };
    {
        let cache = input.cache.lock().unwrap_or_else(|e| e.into_inner());
        if let Some(entry) = cache.get(&key) {
            match &entry.output {
                None => return Ok((input.clone(), entry.map.clone())),
                Some(w) => {
                    if let Some(out) = w.upgrade() {
                        return Ok((out, entry.map.clone()));
                    }
                }
            }
        }
    }
    let ts = input.tensor_stride();
    let (output, map) = match kind {
        _ if deferred => deferred_map(input, kind, geometry)?,
        MapKind::Submanifold => {
            let map = Arc::new(build_submanifold(
                input,
                geometry.kernel,
                geometry.dilation,
            )?);
            (input.clone(), map)
        }
        MapKind::Regular => {
            let (coords, shape, map) = build_regular(input, &geometry)?;
            let stride = std::array::from_fn(|a| ts[a] * geometry.stride[a]);
            let out = Arc::new(CoordSet::from_valid_unique(
                coords,
                shape,
                input.batch_size(),
                stride,
            ));
            (out, Arc::new(map))
        }
        MapKind::Transposed { output_padding } => {
            let (coords, shape, map) = build_transposed(input, &geometry, output_padding)?;
            let stride = std::array::from_fn(|a| (ts[a] / geometry.stride[a]).max(1));
            let out = Arc::new(CoordSet::from_valid_unique(
                coords,
                shape,
                input.batch_size(),
                stride,
            ));
            (out, Arc::new(map))
        }
    };
    if kind == MapKind::Regular {
        output
            .parents
            .lock()
            .unwrap_or_else(|e| e.into_inner())
            .push(ParentLink {
                geometry,
                parent: input.clone(),
                map: map.clone(),
            });
    }
    let entry = ConvCacheEntry {
        output: if kind == MapKind::Submanifold {
            None
        } else {
            Some(Arc::downgrade(&output))
        },
        map: map.clone(),
    };
    input
        .cache
        .lock()
        .unwrap_or_else(|e| e.into_inner())
        .insert(key, entry);
    Ok((output, map))
}

/// The set and map that invert the regular convolution with `geometry` which produced `set`: the
/// returned map goes from `set` back to the parent set (the strided map transposed).
pub fn inverse_of(
    set: &Arc<CoordSet>,
    geometry: ConvGeometry,
) -> Result<(Arc<CoordSet>, Arc<KernelMap>)> {
    let parents = set.parents.lock().unwrap_or_else(|e| e.into_inner());
    parents
        .iter()
        .rev()
        .find(|l| l.geometry == geometry)
        .map(|l| (l.parent.clone(), l.map.transposed()))
        .ok_or_else(|| SparseError::NoInverseMap(format!("{geometry:?}")))
}

#[cfg(test)]
mod tests {
    use super::*;
    use rand::{Rng, SeedableRng};

    fn random_set(seed: u64, shape: [usize; 3], batch: usize, n: usize, sorted: bool) -> CoordSet {
        let mut r = rand_chacha::ChaCha8Rng::seed_from_u64(seed);
        let mut seen = std::collections::HashSet::new();
        let mut coords = Vec::new();
        while coords.len() < n {
            let c = [
                r.random_range(0..batch as i32),
                r.random_range(0..shape[0] as i32),
                r.random_range(0..shape[1] as i32),
                r.random_range(0..shape[2] as i32),
            ];
            if seen.insert(c) {
                coords.push(c);
            }
        }
        if sorted {
            coords.sort_by_key(|&c| pack(c));
        }
        CoordSet::new(coords, shape, batch).unwrap()
    }

    fn all_pairs(m: &KernelMap) -> Vec<Vec<(u32, u32)>> {
        (0..m.kernel_volume())
            .map(|k| {
                let (i, o) = m.pairs(k);
                i.iter().copied().zip(o.iter().copied()).collect()
            })
            .collect()
    }

    /// A geometry value beyond the largest grid axis (which `i32` site arithmetic would truncate
    /// or divide by zero with) and an output grid beyond it are errors naming the values; the
    /// largest values that fit still build.
    #[test]
    fn geometries_beyond_the_largest_axis_are_errors() {
        let set = Arc::new(random_set(3, [8, 8, 8], 1, 20, true));
        let big = MAX_AXIS_EXTENT + 1;
        let bad = [
            (
                MapKind::Regular,
                ConvGeometry::new([3; 3]).with_stride([1 << 40; 3]),
            ),
            (
                MapKind::Regular,
                ConvGeometry::new([3; 3]).with_stride([big, 1, 1]),
            ),
            (
                MapKind::Regular,
                ConvGeometry::new([3; 3]).with_padding([1 << 40; 3]),
            ),
            (
                MapKind::Regular,
                ConvGeometry::new([3; 3]).with_padding([0, 0, 20_000]),
            ),
            (
                MapKind::Regular,
                ConvGeometry::new([3; 3]).with_dilation([1 << 40; 3]),
            ),
            (
                MapKind::Submanifold,
                ConvGeometry::new([3; 3]).with_dilation([1 << 20; 3]),
            ),
            (
                MapKind::Transposed {
                    output_padding: [0; 3],
                },
                ConvGeometry::new([3; 3]).with_stride([1 << 20; 3]),
            ),
            (
                MapKind::Transposed {
                    output_padding: [1 << 63; 3],
                },
                ConvGeometry::new([3; 3]),
            ),
        ];
        for (kind, g) in bad {
            let e = conv_map(&set, kind, g).err();
            let msg = e.map(|e| e.to_string()).unwrap_or_default();
            assert!(
                msg.contains(&MAX_AXIS_EXTENT.to_string()),
                "{kind:?} {g:?}: {msg:?}"
            );
        }
        let fits = ConvGeometry::new([3; 3])
            .with_stride([MAX_AXIS_EXTENT; 3])
            .with_padding([1; 3]);
        let (out, _) = conv_map(&set, MapKind::Regular, fits).unwrap();
        assert_eq!(out.spatial_shape(), [1, 1, 1]);
    }

    /// The dense-table path and the hash path give the same outputs and the same pairs, in the same
    /// order (sorted by output row within each offset), for every geometry, sorted or shuffled inputs.
    #[test]
    fn dense_and_hashed_regular_maps_agree() {
        let geoms = [
            ConvGeometry::new([3, 3, 3]).with_padding([1, 1, 1]),
            ConvGeometry::new([3, 3, 3])
                .with_stride([2, 2, 2])
                .with_padding([1, 1, 1]),
            ConvGeometry::new([2, 2, 2]).with_stride([2, 2, 2]),
            ConvGeometry::new([3, 1, 3])
                .with_stride([2, 1, 1])
                .with_padding([0, 0, 1])
                .with_dilation([1, 1, 2]),
            ConvGeometry::new([5, 5, 1]).with_padding([2, 2, 0]),
        ];
        for (gi, g) in geoms.iter().enumerate() {
            for (si, sorted) in [true, false].into_iter().enumerate() {
                let set = random_set(7 + gi as u64 * 2 + si as u64, [12, 9, 6], 2, 300, sorted);
                let shape = g.regular_output_shape(set.spatial_shape()).unwrap();
                let (od, md) = build_regular_dense(&set, g, shape).expect("dense path");
                let (oh, mh) = build_regular_hashed(&set, g, shape);
                assert_eq!(od, oh, "geometry {gi}, sorted {sorted}");
                assert_eq!(
                    all_pairs(&md),
                    all_pairs(&mh),
                    "geometry {gi}, sorted {sorted}"
                );
                assert!(od.windows(2).all(|w| pack(w[0]) < pack(w[1])));
            }
        }
    }

    #[test]
    fn dense_table_only_where_it_pays_off() {
        let n = 32_768 / DENSE_VOXELS_PER_SITE;
        assert!(DenseRows::empty(1, [64, 64, 8], n, 0).is_some());
        assert!(DenseRows::empty(1, [64, 64, 8], n - 1, 0).is_none());
        assert!(DenseRows::empty(1, [64, 64, 8], 0, 0).is_none());
        assert!(DenseRows::empty(usize::MAX, [64, 64, 8], 1, 1).is_none());
        // A sparse grid gets the table when the lookups pay for it, up to a bounded size.
        let lookups = 32_768 / DENSE_VOXELS_PER_LOOKUP;
        assert!(DenseRows::empty(1, [64, 64, 8], 1, lookups).is_some());
        assert!(DenseRows::empty(1, [64, 64, 8], 1, lookups - 1).is_none());
        assert!(DenseRows::empty(1, [1024, 1024, 8], 1, usize::MAX).is_none());
        // Submanifold through the table equals submanifold through the hash.
        let set = random_set(3, [10, 10, 4], 1, 150, false);
        let g = ConvGeometry::new([3, 3, 3]);
        let half = |o: Coord, k: [usize; 3]| {
            Some([
                o[0],
                o[1] - 1 + k[0] as i32,
                o[2] - 1 + k[1] as i32,
                o[3] - 1 + k[2] as i32,
            ])
        };
        let t = DenseRows::of_set(&set, 0).expect("dense");
        let wrap = |p| KernelMap::eager(27, set.len(), set.len(), p);
        let a = wrap(build_pairs_with(set.coords(), &g, half, |c| t.get(c)));
        let b = wrap(build_pairs_with(set.coords(), &g, half, |c| {
            set.find(c).map(|r| r as u32)
        }));
        assert_eq!(all_pairs(&a), all_pairs(&b));
        assert!(a.num_pairs() > set.len());
    }

    /// A deferred map has the output set, pairs, transpose and inverse of the eagerly built one,
    /// for every kind, on sorted and shuffled, dense and sparse sets (both host lookups of
    /// [`MapSource`]), and builds no host pairs until asked.
    #[test]
    fn deferred_maps_equal_eager_maps() {
        let kinds = [
            (MapKind::Submanifold, ConvGeometry::new([3, 3, 3])),
            (
                MapKind::Submanifold,
                ConvGeometry::new([3, 1, 5]).with_dilation([1, 1, 2]),
            ),
            (
                MapKind::Regular,
                ConvGeometry::new([3, 3, 3]).with_padding([1, 1, 1]),
            ),
            (
                MapKind::Regular,
                ConvGeometry::new([3, 3, 3])
                    .with_stride([2, 2, 2])
                    .with_padding([1, 1, 1]),
            ),
            (
                MapKind::Transposed {
                    output_padding: [1, 0, 1],
                },
                ConvGeometry::new([3, 2, 3])
                    .with_stride([2, 2, 1])
                    .with_padding([1, 0, 1]),
            ),
        ];
        for (ki, (kind, g)) in kinds.into_iter().enumerate() {
            for (si, (shape, n, sorted)) in [
                ([12, 9, 6], 300, true),
                ([12, 9, 6], 300, false),
                ([120, 90, 40], 200, false),
            ]
            .into_iter()
            .enumerate()
            {
                let seed = 100 + (ki * 3 + si) as u64;
                let eager_set = Arc::new(random_set(seed, shape, 2, n, sorted));
                let lazy_set = Arc::new(random_set(seed, shape, 2, n, sorted));
                let (eo, em) = conv_map(&eager_set, kind, g).unwrap();
                let (lo, lm) = conv_map_deferred(&lazy_set, kind, g).unwrap();
                let what = format!("kind {ki}, set {si}");
                assert!(lm.source().is_some() && !lm.has_host_pairs(), "{what}");
                assert_eq!(eo.coords(), lo.coords(), "{what}");
                assert_eq!(
                    (eo.spatial_shape(), eo.tensor_stride()),
                    (lo.spatial_shape(), lo.tensor_stride()),
                    "{what}"
                );
                let lt = lm.transposed();
                assert!(!lt.has_host_pairs(), "{what}: the transpose stays deferred");
                assert_eq!(
                    all_pairs(&lt),
                    all_pairs(&em.transposed()),
                    "{what}: transpose"
                );
                assert_eq!(all_pairs(&lm), all_pairs(&em), "{what}");
                assert_eq!(lm.gather_table(), em.gather_table(), "{what}");
                assert_eq!(
                    conv_map_deferred(&lazy_set, kind, g).unwrap().1.n_out(),
                    lm.n_out()
                );
                if kind == MapKind::Regular && g.stride == [2, 2, 2] {
                    let (parent, inv) = inverse_of(&lo, g).unwrap();
                    assert!(Arc::ptr_eq(&parent, &lazy_set));
                    assert_eq!(
                        all_pairs(&inv),
                        all_pairs(&em.transposed()),
                        "{what}: inverse"
                    );
                }
            }
        }
    }

    /// The maps built on one set share its device copies: a submanifold map on it, the strided
    /// map out of it and that map's transpose see one upload of its sites, per device; another set
    /// with the same coordinates has its own.
    #[test]
    fn maps_of_one_set_share_its_device_sites() {
        let set = Arc::new(random_set(7, [16, 16, 8], 1, 200, false));
        let sub = conv_map_deferred(&set, MapKind::Submanifold, ConvGeometry::new([3, 3, 3]))
            .unwrap()
            .1;
        let g = ConvGeometry::new([3, 3, 3])
            .with_stride([2, 2, 2])
            .with_padding([1, 1, 1]);
        let (down_set, down) = conv_map_deferred(&set, MapKind::Regular, g).unwrap();
        let up = down.transposed();
        let uploads = std::sync::atomic::AtomicUsize::new(0);
        // A "device copy": (device id, row count), counting the uploads.
        let upload = |sites: &Sites, device: u8| {
            sites.device_table::<(u8, usize)>(
                |(d, _)| *d == device,
                || {
                    uploads.fetch_add(1, std::sync::atomic::Ordering::SeqCst);
                    (device, sites.coords().len())
                },
            )
        };
        let source = |m: &KernelMap| m.source().expect("deferred").clone();
        let n = set.len();
        assert_eq!(upload(&source(&sub).inputs, 0), (0, n));
        assert_eq!(upload(&source(&sub).outputs, 0), (0, n));
        assert_eq!(upload(&source(&down).inputs, 0), (0, n));
        assert_eq!(upload(&source(&up).outputs, 0), (0, n));
        assert_eq!(uploads.load(std::sync::atomic::Ordering::SeqCst), 1);
        assert_eq!(upload(&source(&up).inputs, 0), (0, down_set.len()));
        assert_eq!(upload(&source(&down).outputs, 0), (0, down_set.len()));
        assert_eq!(uploads.load(std::sync::atomic::Ordering::SeqCst), 2);
        assert_eq!(upload(&source(&sub).inputs, 1), (1, n), "another device");
        let twin = Arc::new(random_set(7, [16, 16, 8], 1, 200, false));
        let twin_map = conv_map_deferred(&twin, MapKind::Submanifold, ConvGeometry::new([3, 3, 3]))
            .unwrap()
            .1;
        upload(&source(&twin_map).inputs, 0);
        assert_eq!(uploads.load(std::sync::atomic::Ordering::SeqCst), 4);
    }
}
