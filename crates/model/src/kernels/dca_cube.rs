//! The DCA sampling step ([`crate::kernels::dca`]) as `#[cube]` kernels for the cubecl backends
//! (CUDA, WebGPU) behind burn's fusion layer, forward and backward, registered through
//! occ-sparse's [`register_cube_op`]; tested against the NdArray reference by
//! `sparseocc check-backend` (lavapipe when there is no GPU).
//!
//! `out[q] = 1/|V_q| · Σ_{hits h of q} g_h · Σ_{m, l, j} w_{qmlj} · bilinear(values_l[img_h], ref_h/s_l + Δp_{qmlj})[head m]`
//!
//! The function is [`crate::kernels::dca_host`]'s (zero padding, `align_corners = false`), computed
//! without the portable path's padded sampling grids, per-level `grid_sample` and scatters:
//!
//! - forward: one unit per output value `(q, c)`, summing the four bilinear corners of every tap of
//!   its head over the query's hits, in a fixed order; channels are adjacent units, so the value
//!   reads of a corner are coalesced;
//! - offsets' and weights' gradients: one unit per tap `(q, m, l, j)` (dot products of the corner's
//!   value and output-gradient rows of its head); the gate's: one unit per hit;
//! - values' gradient without float atomics: the (hit, tap, corner) entries are bucketed by the
//!   value row and head they read (an integer count, a prefix sum, a fill), each bucket is sorted by
//!   entry index, and one unit per value `(row, c)` sums its bucket in that order. Integer atomics
//!   only place the entries; the sums follow the sorted order, so the result is the same in every
//!   run.
//!
//! All sizes are runtime values: the compiled kernels do not depend on the query or hit count.

use crate::kernels::dca::DcaSample;
use crate::kernels::dca_host::SampleLayout;
use burn::backend::autodiff::checkpoint::base::Checkpointer;
use burn::backend::autodiff::checkpoint::strategy::CheckpointStrategy;
use burn::backend::autodiff::grads::Gradients;
use burn::backend::autodiff::ops::{Backward, Ops, OpsKind};
use burn::backend::Autodiff;
use burn::tensor::ops::FloatTensor;
use burn::tensor::{DType, Shape, Tensor, TensorData, TensorPrimitive};
use burn_cubecl::fusion::FusionCubeRuntime;
use burn_cubecl::kernel::into_contiguous;
use burn_cubecl::ops::numeric::{empty_device_dtype, zeros_client};
use burn_cubecl::tensor::CubeTensor;
use burn_cubecl::{BoolElement, CubeBackend, CubeRuntime, FloatElement, IntElement};
use burn_fusion::{Fusion, FusionTensor};
use cubecl::{calculate_cube_count_elemwise, CubeCount, CubeDim};
use occ_sparse::backend::index_tensor;
use occ_sparse::cube::{address_type_of, inputs_of, register_cube_op};
use std::sync::Arc;

mod kernel {
    use cubecl::prelude::*;

    /// Sizes shared by the kernels (all runtime values).
    #[derive(CubeLaunch, CubeType)]
    pub struct DcaDims {
        /// Queries `N`.
        pub n: usize,
        /// Width `D` and per-head width `D / M`.
        pub d: usize,
        pub dh: usize,
        /// Heads `M`, levels `L`, points `P`.
        pub m: usize,
        pub nl: usize,
        pub p: usize,
        /// Hits `H`.
        pub hits: usize,
    }

    // The int layout tensor `lay`: `start [N + 1] | order [H] | image [H] | query [H] | (h, w,
    // row0) per level [3 L]`; the float `aux`: `1 / views [N] | (bx, by) per hit and level [2 H L]`
    // (the reference point in feature pixels of the level, pixel centres at integers).

    #[cube]
    fn o_order(dims: &DcaDims) -> usize {
        dims.n + 1
    }
    #[cube]
    fn o_image(dims: &DcaDims) -> usize {
        dims.n + 1 + dims.hits
    }
    #[cube]
    fn o_query(dims: &DcaDims) -> usize {
        dims.n + 1 + 2 * dims.hits
    }
    #[cube]
    fn o_geom(dims: &DcaDims) -> usize {
        dims.n + 1 + 3 * dims.hits
    }

    /// Sampling position `(x, y)` of tap `k` of hit `hi` at level `l`, feature pixels.
    #[cube]
    fn tap_position<F: Float>(
        aux: &Tensor<F>,
        off: &Tensor<F>,
        dims: &DcaDims,
        hi: usize,
        l: usize,
        k: usize,
    ) -> (F, F) {
        let b = dims.n + (hi * dims.nl + l) * 2;
        (aux[b] + off[2 * k], aux[b + 1] + off[2 * k + 1])
    }

    /// Corner `corner` (0..4: `y0 x0, y0 x1, y1 x0, y1 x1`) of the bilinear sample at `(x, y)` on
    /// a `fh x fw` map of image `img` at `row0`: whether it lies on the map, its value row, its
    /// weight and the weight's derivatives in `x` and `y`.
    #[cube]
    #[allow(clippy::too_many_arguments)]
    fn corner<F: Float>(
        x: F,
        y: F,
        corner: usize,
        img: usize,
        fh: usize,
        fw: usize,
        row0: usize,
    ) -> (bool, usize, F, F, F) {
        let x0f = x.floor();
        let y0f = y.floor();
        let fx = x - x0f;
        let fy = y - y0f;
        let one = F::new(1.0);
        let cx = corner % 2;
        let cy = corner / 2;
        let xx = i32::cast_from(x0f) + i32::cast_from(cx);
        let yy = i32::cast_from(y0f) + i32::cast_from(cy);
        let mut wx = one - fx;
        let mut dwx = -one;
        if cx == 1 {
            wx = fx;
            dwx = one;
        }
        let mut wy = one - fy;
        let mut dwy = -one;
        if cy == 1 {
            wy = fy;
            dwy = one;
        }
        let inside = xx >= 0 && yy >= 0 && xx < i32::cast_from(fw) && yy < i32::cast_from(fh);
        let mut row = 0usize;
        if inside {
            row = row0 + (img * fh + usize::cast_from(yy)) * fw + usize::cast_from(xx);
        }
        (inside, row, wx * wy, dwx * wy, wx * dwy)
    }

    /// The forward pass: one unit per output value `(q, c)`.
    #[cube(launch_unchecked, address_type = "dynamic")]
    #[allow(clippy::too_many_arguments)]
    pub fn dca_forward_kernel<F: Float, I: Numeric>(
        values: &Tensor<F>,
        off: &Tensor<F>,
        wts: &Tensor<F>,
        gate: &Tensor<F>,
        aux: &Tensor<F>,
        lay: &Tensor<I>,
        out: &mut Tensor<F>,
        dims: &DcaDims,
        #[define(F, I)] _dtypes: [StorageType; 2],
    ) {
        if ABSOLUTE_POS >= dims.n * dims.d {
            terminate!();
        }
        let q = ABSOLUTE_POS / dims.d;
        let c = ABSOLUTE_POS % dims.d;
        let head = c / dims.dh;
        let s0 = usize::cast_from(lay[q]);
        let s1 = usize::cast_from(lay[q + 1]);
        let mut acc = F::new(0.0);
        for s in s0..s1 {
            let hi = usize::cast_from(lay[o_order(dims) + s]);
            let img = usize::cast_from(lay[o_image(dims) + hi]);
            let mut acc_hit = F::new(0.0);
            for l in 0..dims.nl {
                let g = o_geom(dims) + 3 * l;
                let fh = usize::cast_from(lay[g]);
                let fw = usize::cast_from(lay[g + 1]);
                let row0 = usize::cast_from(lay[g + 2]);
                for j in 0..dims.p {
                    let k = ((q * dims.m + head) * dims.nl + l) * dims.p + j;
                    let (x, y) = tap_position::<F>(aux, off, dims, hi, l, k);
                    let mut sample = F::new(0.0);
                    for cn in 0..4usize {
                        let (inside, row, cw, _dx, _dy) = corner::<F>(x, y, cn, img, fh, fw, row0);
                        if inside {
                            sample += cw * values[row * dims.d + c];
                        }
                    }
                    acc_hit += gate[hi] * wts[k] * sample;
                }
            }
            acc += acc_hit;
        }
        out[ABSOLUTE_POS] = acc * aux[q];
    }

    /// `Σ_{i < D/M} values[row, head·D/M + i] · dout[q, head·D/M + i]`.
    #[cube]
    fn head_dot<F: Float>(
        values: &Tensor<F>,
        dout: &Tensor<F>,
        dims: &DcaDims,
        row: usize,
        q: usize,
        head: usize,
    ) -> F {
        let a = row * dims.d + head * dims.dh;
        let b = q * dims.d + head * dims.dh;
        let mut dot = F::new(0.0);
        for i in 0..dims.dh {
            dot += values[a + i] * dout[b + i];
        }
        dot
    }

    /// Gradients of the offsets and attention weights: one unit per tap `k = ((q·M + m)·L + l)·P + j`.
    #[cube(launch_unchecked, address_type = "dynamic")]
    #[allow(clippy::too_many_arguments)]
    pub fn dca_tap_grad_kernel<F: Float, I: Numeric>(
        values: &Tensor<F>,
        off: &Tensor<F>,
        wts: &Tensor<F>,
        gate: &Tensor<F>,
        aux: &Tensor<F>,
        lay: &Tensor<I>,
        dout: &Tensor<F>,
        d_off: &mut Tensor<F>,
        d_wts: &mut Tensor<F>,
        dims: &DcaDims,
        #[define(F, I)] _dtypes: [StorageType; 2],
    ) {
        let taps = dims.m * dims.nl * dims.p;
        if ABSOLUTE_POS >= dims.n * taps {
            terminate!();
        }
        let k = ABSOLUTE_POS;
        let q = k / taps;
        let head = (k % taps) / (dims.nl * dims.p);
        let l = (k / dims.p) % dims.nl;
        let g = o_geom(dims) + 3 * l;
        let fh = usize::cast_from(lay[g]);
        let fw = usize::cast_from(lay[g + 1]);
        let row0 = usize::cast_from(lay[g + 2]);
        let w = wts[k];
        let s0 = usize::cast_from(lay[q]);
        let s1 = usize::cast_from(lay[q + 1]);
        let mut d_w = F::new(0.0);
        let mut d_x = F::new(0.0);
        let mut d_y = F::new(0.0);
        for s in s0..s1 {
            let hi = usize::cast_from(lay[o_order(dims) + s]);
            let img = usize::cast_from(lay[o_image(dims) + hi]);
            let gh = gate[hi];
            let (x, y) = tap_position::<F>(aux, off, dims, hi, l, k);
            for cn in 0..4usize {
                let (inside, row, cw, cdx, cdy) = corner::<F>(x, y, cn, img, fh, fw, row0);
                if inside {
                    let dot = head_dot::<F>(values, dout, dims, row, q, head);
                    d_w += gh * cw * dot;
                    d_x += gh * w * cdx * dot;
                    d_y += gh * w * cdy * dot;
                }
            }
        }
        let inv = aux[q];
        d_wts[k] = d_w * inv;
        d_off[2 * k] = d_x * inv;
        d_off[2 * k + 1] = d_y * inv;
    }

    /// Gradient of the per-hit gate: one unit per hit.
    #[cube(launch_unchecked, address_type = "dynamic")]
    #[allow(clippy::too_many_arguments)]
    pub fn dca_gate_grad_kernel<F: Float, I: Numeric>(
        values: &Tensor<F>,
        off: &Tensor<F>,
        wts: &Tensor<F>,
        aux: &Tensor<F>,
        lay: &Tensor<I>,
        dout: &Tensor<F>,
        d_gate: &mut Tensor<F>,
        dims: &DcaDims,
        #[define(F, I)] _dtypes: [StorageType; 2],
    ) {
        if ABSOLUTE_POS >= dims.hits {
            terminate!();
        }
        let hi = ABSOLUTE_POS;
        let q = usize::cast_from(lay[o_query(dims) + hi]);
        let img = usize::cast_from(lay[o_image(dims) + hi]);
        let mut acc = F::new(0.0);
        for head in 0..dims.m {
            for l in 0..dims.nl {
                let g = o_geom(dims) + 3 * l;
                let fh = usize::cast_from(lay[g]);
                let fw = usize::cast_from(lay[g + 1]);
                let row0 = usize::cast_from(lay[g + 2]);
                for j in 0..dims.p {
                    let k = ((q * dims.m + head) * dims.nl + l) * dims.p + j;
                    let (x, y) = tap_position::<F>(aux, off, dims, hi, l, k);
                    let mut sample = F::new(0.0);
                    for cn in 0..4usize {
                        let (inside, row, cw, _dx, _dy) = corner::<F>(x, y, cn, img, fh, fw, row0);
                        if inside {
                            sample += cw * head_dot::<F>(values, dout, dims, row, q, head);
                        }
                    }
                    acc += wts[k] * sample;
                }
            }
        }
        d_gate[hi] = acc * aux[q];
    }

    /// The entries of the values' gradient: for every (hit, tap) `u = ((hit·M + m)·L + l)·P + j`
    /// and each of its four corners on the map, entry `4u + corner` goes to bucket
    /// `row·M + m`. With `FILL = false` the bucket sizes are counted into `cursor`; with
    /// `FILL = true` each entry takes the next place of its bucket (`starts[bucket]` plus a
    /// fetched `cursor`) in `entries`.
    #[cube(launch_unchecked, address_type = "dynamic")]
    #[allow(clippy::too_many_arguments)]
    pub fn dca_bucket_kernel<F: Float, I: Numeric>(
        off: &Tensor<F>,
        aux: &Tensor<F>,
        lay: &Tensor<I>,
        cursor: &mut Tensor<Atomic<u32>>,
        starts: &Tensor<u32>,
        entries: &mut Tensor<u32>,
        dims: &DcaDims,
        #[comptime] fill: bool,
        #[define(F, I)] _dtypes: [StorageType; 2],
    ) {
        let taps = dims.m * dims.nl * dims.p;
        if ABSOLUTE_POS >= dims.hits * taps {
            terminate!();
        }
        let u = ABSOLUTE_POS;
        let hi = u / taps;
        let t = u % taps;
        let head = t / (dims.nl * dims.p);
        let l = (u / dims.p) % dims.nl;
        let q = usize::cast_from(lay[o_query(dims) + hi]);
        let img = usize::cast_from(lay[o_image(dims) + hi]);
        let g = o_geom(dims) + 3 * l;
        let fh = usize::cast_from(lay[g]);
        let fw = usize::cast_from(lay[g + 1]);
        let row0 = usize::cast_from(lay[g + 2]);
        let k = q * taps + t;
        let (x, y) = tap_position::<F>(aux, off, dims, hi, l, k);
        for cn in 0..4usize {
            let (inside, row, _cw, _dx, _dy) = corner::<F>(x, y, cn, img, fh, fw, row0);
            if inside {
                let bucket = row * dims.m + head;
                let place = cursor[bucket].fetch_add(1u32);
                if fill {
                    let at = starts[bucket] + place;
                    entries[usize::cast_from(at)] = u32::cast_from(u * 4 + cn);
                }
            }
        }
    }

    /// Units of the one cube of [`dca_scan_kernel`].
    pub const SCAN_UNITS: usize = 256;

    /// `starts[b] = Σ_{b' < b} counts[b']` for `b` in `0..=buckets` (an exclusive prefix sum, in one
    /// cube of [`SCAN_UNITS`] units, each over a contiguous chunk), and `counts` set back to zero
    /// for the fill.
    #[cube(launch_unchecked, address_type = "dynamic")]
    pub fn dca_scan_kernel(
        counts: &mut Tensor<Atomic<u32>>,
        starts: &mut Tensor<u32>,
        buckets: usize,
    ) {
        let unit = UNIT_POS as usize;
        let chunk = buckets.div_ceil(SCAN_UNITS);
        let b0 = unit * chunk;
        let mut b1 = b0 + chunk;
        if b1 > buckets {
            b1 = buckets;
        }
        let mut partial = SharedMemory::<u32>::new(SCAN_UNITS);
        let mut sum = 0u32;
        let mut b = b0;
        while b < b1 {
            sum += counts[b].load();
            b += 1;
        }
        partial[unit] = sum;
        sync_cube();
        if unit == 0 {
            let mut run = 0u32;
            for i in 0..SCAN_UNITS {
                let v = partial[i];
                partial[i] = run;
                run += v;
            }
        }
        sync_cube();
        let mut run = partial[unit];
        let mut b = b0;
        while b < b1 {
            let v = counts[b].load();
            starts[b] = run;
            run += v;
            counts[b].store(0u32);
            b += 1;
        }
        if unit == SCAN_UNITS - 1 {
            starts[buckets] = run;
        }
    }

    /// Sorts each bucket's entries (insertion sort, one unit per bucket), so that the sums of
    /// [`dca_value_grad_kernel`] follow the entry order whatever order the fill placed them in.
    #[cube(launch_unchecked, address_type = "dynamic")]
    pub fn dca_sort_kernel(starts: &Tensor<u32>, entries: &mut Tensor<u32>, buckets: usize) {
        if ABSOLUTE_POS >= buckets {
            terminate!();
        }
        let s0 = usize::cast_from(starts[ABSOLUTE_POS]);
        let s1 = usize::cast_from(starts[ABSOLUTE_POS + 1]);
        let mut i = s0 + 1;
        while i < s1 {
            let v = entries[i];
            let mut j = i;
            while j > s0 && entries[j - 1] > v {
                entries[j] = entries[j - 1];
                j -= 1;
            }
            entries[j] = v;
            i += 1;
        }
    }

    /// Gradient of the values: one unit per value `(row, c)`, summing the entries of bucket
    /// `row·M + head(c)` in entry order.
    #[cube(launch_unchecked, address_type = "dynamic")]
    #[allow(clippy::too_many_arguments)]
    pub fn dca_value_grad_kernel<F: Float, I: Numeric>(
        off: &Tensor<F>,
        wts: &Tensor<F>,
        gate: &Tensor<F>,
        aux: &Tensor<F>,
        lay: &Tensor<I>,
        dout: &Tensor<F>,
        starts: &Tensor<u32>,
        entries: &Tensor<u32>,
        d_values: &mut Tensor<F>,
        rows: usize,
        dims: &DcaDims,
        #[define(F, I)] _dtypes: [StorageType; 2],
    ) {
        if ABSOLUTE_POS >= rows * dims.d {
            terminate!();
        }
        let row = ABSOLUTE_POS / dims.d;
        let c = ABSOLUTE_POS % dims.d;
        let head = c / dims.dh;
        let bucket = row * dims.m + head;
        let taps = dims.m * dims.nl * dims.p;
        let e0 = usize::cast_from(starts[bucket]);
        let e1 = usize::cast_from(starts[bucket + 1]);
        let mut acc = F::new(0.0);
        for e in e0..e1 {
            let id = usize::cast_from(entries[e]);
            let u = id / 4;
            let cn = id % 4;
            let hi = u / taps;
            let t = u % taps;
            let l = (u / dims.p) % dims.nl;
            let q = usize::cast_from(lay[o_query(dims) + hi]);
            let img = usize::cast_from(lay[o_image(dims) + hi]);
            let g = o_geom(dims) + 3 * l;
            let fh = usize::cast_from(lay[g]);
            let fw = usize::cast_from(lay[g + 1]);
            let row0 = usize::cast_from(lay[g + 2]);
            let k = q * taps + t;
            let (x, y) = tap_position::<F>(aux, off, dims, hi, l, k);
            let (_inside, _row, cw, _dx, _dy) = corner::<F>(x, y, cn, img, fh, fw, row0);
            acc += gate[hi] * wts[k] * cw * aux[q] * dout[q * dims.d + c];
        }
        d_values[ABSOLUTE_POS] = acc;
    }
}

/// Sizes of one DCA sampling call, as the kernels take them.
#[derive(Clone, Copy, Debug)]
struct Dims {
    n: usize,
    d: usize,
    m: usize,
    nl: usize,
    p: usize,
    hits: usize,
    /// Rows of the flat value matrix (all levels, all images).
    rows: usize,
}

impl Dims {
    fn of(lay: &SampleLayout) -> Self {
        Self {
            n: lay.n,
            d: lay.d,
            m: lay.m,
            nl: lay.levels.len(),
            p: lay.p,
            hits: lay.num_hits(),
            rows: lay.num_rows,
        }
    }

    fn taps(&self) -> usize {
        self.m * self.nl * self.p
    }

    fn arg<R: CubeRuntime>(&self) -> kernel::DcaDimsLaunch<R> {
        kernel::DcaDimsLaunch::new(
            self.n,
            self.d,
            self.d / self.m.max(1),
            self.m,
            self.nl,
            self.p,
            self.hits,
        )
    }
}

/// The host-built layout inputs: `lay` (ints: hits by query, each hit's image and query, the
/// levels' geometry) and `aux` (floats: each query's `1 / views`, each hit's reference point per
/// level in feature pixels).
fn layout_data(lay: &SampleLayout, query: &[u32]) -> (Vec<u32>, Vec<f32>) {
    let mut ints = Vec::with_capacity(lay.n + 1 + 3 * lay.num_hits() + 3 * lay.levels.len());
    ints.extend(lay.start.iter().map(|&s| s as u32));
    ints.extend(lay.order.iter().map(|&h| h as u32));
    ints.extend_from_slice(&lay.image);
    ints.extend_from_slice(query);
    for g in &lay.levels {
        ints.extend([g.h as u32, g.w as u32, g.row0 as u32]);
    }
    let mut floats = Vec::with_capacity(lay.n + 2 * lay.num_hits() * lay.levels.len());
    floats.extend(
        lay.views
            .iter()
            .map(|&v| if v == 0 { 0.0 } else { 1.0 / v as f32 }),
    );
    for &[u, v] in &lay.uv {
        for g in &lay.levels {
            let s = g.stride as f64;
            floats.extend([((u + 0.5) / s - 0.5) as f32, ((v + 0.5) / s - 0.5) as f32]);
        }
    }
    (ints, floats)
}

fn elemwise<R: CubeRuntime>(t: &CubeTensor<R>, units: usize) -> (CubeCount, CubeDim) {
    let dim = CubeDim::new(&t.client, units);
    (calculate_cube_count_elemwise(&t.client, units, dim), dim)
}

fn empty_like<R: CubeRuntime>(t: &CubeTensor<R>, shape: Shape, dtype: DType) -> CubeTensor<R> {
    empty_device_dtype(t.client.clone(), t.device.clone(), shape, dtype)
}

/// The forward launcher: `[values, off, wts, gate, aux, lay]` -> `[N, D]`.
fn forward_launch<R: CubeRuntime>(t: Vec<CubeTensor<R>>, dims: Dims) -> CubeTensor<R> {
    let [values, off, wts, gate, aux, lay] = inputs_of(t).map(into_contiguous);
    let out = empty_like(&values, Shape::new([dims.n, dims.d]), values.dtype);
    let units = dims.n * dims.d;
    if units == 0 {
        return out;
    }
    let (count, dim) = elemwise(&values, units);
    let address = address_type_of(&[&values, &off, &wts, &gate, &aux, &lay, &out]);
    let dtypes = [values.dtype.into(), lay.dtype.into()];
    let client = values.client.clone();
    // SAFETY: `lay` is built by `layout_data` from a `SampleLayout` (hit and query indices in
    // range, level geometry matching the value rows); corners are read only inside their map;
    // the output position is bounds-checked.
    unsafe {
        kernel::dca_forward_kernel::launch_unchecked(
            &client,
            count,
            dim,
            address,
            values.into_tensor_arg(),
            off.into_tensor_arg(),
            wts.into_tensor_arg(),
            gate.into_tensor_arg(),
            aux.into_tensor_arg(),
            lay.into_tensor_arg(),
            out.clone().into_tensor_arg(),
            dims.arg(),
            dtypes,
        )
    };
    out
}

/// The backward launcher: `[values, off, wts, gate, aux, lay, dout]` -> `[d_values [R, D],
/// d_off [N·M·L·P·2], d_wts [N·M·L·P], d_gate [H]]`.
fn backward_launch<R: CubeRuntime>(t: Vec<CubeTensor<R>>, dims: Dims) -> Vec<CubeTensor<R>> {
    let [values, off, wts, gate, aux, lay, dout] = inputs_of(t).map(into_contiguous);
    let f = values.dtype;
    let client = values.client.clone();
    let taps = dims.taps();
    let d_off = empty_like(&values, Shape::new([dims.n * taps * 2]), f);
    let d_wts = empty_like(&values, Shape::new([dims.n * taps]), f);
    let d_gate = empty_like(&values, Shape::new([dims.hits]), f);
    let d_values = empty_like(&values, Shape::new([dims.rows, dims.d]), f);
    let address = address_type_of(&[&values, &off, &wts, &gate, &aux, &lay, &dout, &d_values]);
    let dtypes = [f.into(), lay.dtype.into()];
    if dims.n * taps > 0 {
        let (count, dim) = elemwise(&values, dims.n * taps);
        // SAFETY: as in `forward_launch`; each tap writes its own weight and two offset values.
        unsafe {
            kernel::dca_tap_grad_kernel::launch_unchecked(
                &client,
                count,
                dim,
                address,
                values.clone().into_tensor_arg(),
                off.clone().into_tensor_arg(),
                wts.clone().into_tensor_arg(),
                gate.clone().into_tensor_arg(),
                aux.clone().into_tensor_arg(),
                lay.clone().into_tensor_arg(),
                dout.clone().into_tensor_arg(),
                d_off.clone().into_tensor_arg(),
                d_wts.clone().into_tensor_arg(),
                dims.arg(),
                dtypes,
            )
        };
    }
    if dims.hits > 0 {
        let (count, dim) = elemwise(&values, dims.hits);
        // SAFETY: as in `forward_launch`; each hit writes its own gate gradient.
        unsafe {
            kernel::dca_gate_grad_kernel::launch_unchecked(
                &client,
                count,
                dim,
                address,
                values.clone().into_tensor_arg(),
                off.clone().into_tensor_arg(),
                wts.clone().into_tensor_arg(),
                aux.clone().into_tensor_arg(),
                lay.clone().into_tensor_arg(),
                dout.clone().into_tensor_arg(),
                d_gate.clone().into_tensor_arg(),
                dims.arg(),
                dtypes,
            )
        };
    }
    let buckets = dims.rows * dims.m;
    let entries_max = dims.hits * taps * 4;
    let cursor = zeros_client(
        client.clone(),
        values.device.clone(),
        Shape::new([buckets.max(1)]),
        DType::U32,
    );
    let starts = empty_like(&values, Shape::new([buckets + 1]), DType::U32);
    let entries = empty_like(&values, Shape::new([entries_max.max(1)]), DType::U32);
    let (bcount, bdim) = elemwise(&values, (dims.hits * taps).max(1));
    for fill in [false, true] {
        if fill {
            // SAFETY: `cursor` and `starts` hold `buckets` and `buckets + 1` values; one cube.
            unsafe {
                kernel::dca_scan_kernel::launch_unchecked(
                    &client,
                    CubeCount::Static(1, 1, 1),
                    CubeDim::new_1d(kernel::SCAN_UNITS as u32),
                    address,
                    cursor.clone().into_tensor_arg(),
                    starts.clone().into_tensor_arg(),
                    buckets,
                )
            };
        }
        if dims.hits * taps > 0 {
            // SAFETY: as in `forward_launch`; buckets `row·M + m < buckets` for rows on the map;
            // a fill place is below its bucket's count, so `starts[b] + place < entries_max`.
            unsafe {
                kernel::dca_bucket_kernel::launch_unchecked(
                    &client,
                    bcount.clone(),
                    bdim,
                    address,
                    off.clone().into_tensor_arg(),
                    aux.clone().into_tensor_arg(),
                    lay.clone().into_tensor_arg(),
                    cursor.clone().into_tensor_arg(),
                    starts.clone().into_tensor_arg(),
                    entries.clone().into_tensor_arg(),
                    dims.arg(),
                    fill,
                    dtypes,
                )
            };
        }
    }
    if buckets > 0 {
        let (count, dim) = elemwise(&values, buckets);
        // SAFETY: `starts` is non-decreasing up to the entry count; one unit per bucket.
        unsafe {
            kernel::dca_sort_kernel::launch_unchecked(
                &client,
                count,
                dim,
                address,
                starts.clone().into_tensor_arg(),
                entries.clone().into_tensor_arg(),
                buckets,
            )
        };
        let (count, dim) = elemwise(&values, dims.rows * dims.d);
        // SAFETY: entries decode to (hit, tap, corner) of the layout, each corner on its map.
        unsafe {
            kernel::dca_value_grad_kernel::launch_unchecked(
                &client,
                count,
                dim,
                address,
                off.into_tensor_arg(),
                wts.into_tensor_arg(),
                gate.into_tensor_arg(),
                aux.into_tensor_arg(),
                lay.into_tensor_arg(),
                dout.into_tensor_arg(),
                starts.into_tensor_arg(),
                entries.into_tensor_arg(),
                d_values.clone().into_tensor_arg(),
                dims.rows,
                dims.arg(),
                dtypes,
            )
        };
    }
    vec![d_values, d_off, d_wts, d_gate]
}

type Fused<R, F, I, BT> = Fusion<CubeBackend<R, F, I, BT>>;
type Ad<R, F, I, BT, C> = Autodiff<Fused<R, F, I, BT>, C>;
type FusedTensor<R> = FusionTensor<FusionCubeRuntime<R>>;

occ_sparse::env_switch! {
    /// Which DCA sampling the cubecl backends run.
    pub enum CubeDca: "SPARSEOCC_CUBE_DCA" {
        /// `cube` (the default): these kernels in inference and training (forward and backward).
        InferenceAndTraining = "cube",
        /// `cube-infer`: these kernels in inference; training through the portable tensor-op
        /// composition ([`crate::kernels::dca::sample_tensor_ops`]).
        Inference = "cube-infer",
        /// `tensor-ops`: the portable composition everywhere.
        TensorOps = "tensor-ops",
    }
}

/// The layout tensors of a call on `device`: `lay` (int) and `aux` (float).
fn layout_tensors<B: burn::tensor::backend::Backend>(
    lay: &SampleLayout,
    query: &[u32],
    device: &B::Device,
) -> (Tensor<B, 1, burn::tensor::Int>, Tensor<B, 1>) {
    let (ints, floats) = layout_data(lay, query);
    let n = floats.len();
    (
        index_tensor::<B>(&ints, device),
        Tensor::from_data(TensorData::new(floats, [n]), device),
    )
}

/// The sampling on a fused cubecl backend (inference).
///
/// # Shapes
/// see [`DcaSample`]; returns `[N, D]`
pub fn sample<R, F, I, BT>(s: DcaSample<'_, Fused<R, F, I, BT>>) -> Tensor<Fused<R, F, I, BT>, 2>
where
    R: CubeRuntime,
    F: FloatElement,
    I: IntElement,
    BT: BoolElement,
{
    let layout = SampleLayout::of(&s);
    let dims = Dims::of(&layout);
    let device = s.offsets.device();
    if dims.hits == 0 {
        // No view sees any query: every output is zero (and no buffer is empty).
        return Tensor::zeros([dims.n, dims.d], &device);
    }
    let (lay, aux) = layout_tensors::<Fused<R, F, I, BT>>(&layout, &s.hits.query, &device);
    let (lay, aux) = (lay.into_primitive(), aux.into_primitive().tensor());
    let gate = s.gate.unwrap_or_else(|| Tensor::ones([dims.hits], &device));
    let flat = |t: Tensor<Fused<R, F, I, BT>, 1>| t.into_primitive().tensor();
    let inputs = vec![
        s.values.rows.into_primitive().tensor(),
        flat(s.offsets.reshape([dims.n * dims.taps() * 2])),
        flat(s.weights.reshape([dims.n * dims.taps()])),
        flat(gate),
        aux,
        lay,
    ];
    let dtype = inputs[0].dtype;
    let out = register_cube_op::<R, F, I, BT>(
        "occ_model::dca_sample",
        inputs,
        &[(Shape::new([dims.n, dims.d]), dtype)],
        Arc::new(move |t| vec![forward_launch(t, dims)]),
    )
    .pop()
    .expect("one output");
    Tensor::from_primitive(TensorPrimitive::Float(out))
}

/// What the backward pass of [`sample_autodiff`] keeps: the forward's inputs (inner backend) and
/// sizes.
#[derive(Debug)]
struct Saved<R: CubeRuntime> {
    inputs: Vec<FusedTensor<R>>,
    dims: Dims,
}

impl<R: CubeRuntime> Clone for Saved<R> {
    fn clone(&self) -> Self {
        Self {
            inputs: self.inputs.clone(),
            dims: self.dims,
        }
    }
}

/// The sampling on `Autodiff<Fusion<CubeBackend>>` (training on CUDA / WebGPU): one autodiff op
/// whose backward runs the gradient kernels.
///
/// # Shapes
/// see [`DcaSample`]; returns `[N, D]`
pub fn sample_autodiff<R, F, I, BT, C>(
    s: DcaSample<'_, Autodiff<Fused<R, F, I, BT>, C>>,
) -> Tensor<Autodiff<Fused<R, F, I, BT>, C>, 2>
where
    R: CubeRuntime,
    F: FloatElement,
    I: IntElement,
    BT: BoolElement,
    C: CheckpointStrategy,
{
    let layout = SampleLayout::of(&s);
    let dims = Dims::of(&layout);
    let device = s.offsets.device();
    if dims.hits == 0 {
        // No view sees any query: the output is zero and so is every gradient through it.
        return Tensor::zeros([dims.n, dims.d], &device);
    }
    let (lay, aux) = layout_tensors::<Ad<R, F, I, BT, C>>(&layout, &s.hits.query, &device);
    // The layout is no parent of the op: its inner tensors go in as they are.
    let (lay, aux) = (
        lay.into_primitive(),
        aux.into_primitive().tensor().primitive,
    );
    let gate = s.gate.unwrap_or_else(|| Tensor::ones([dims.hits], &device));
    let flat = |t: Tensor<Ad<R, F, I, BT, C>, 1>| t.into_primitive().tensor();
    let parents = [
        s.values.rows.into_primitive().tensor(),
        flat(s.offsets.reshape([dims.n * dims.taps() * 2])),
        flat(s.weights.reshape([dims.n * dims.taps()])),
        flat(gate),
    ];
    let mut inputs: Vec<FusedTensor<R>> = parents.iter().map(|t| t.primitive.clone()).collect();
    inputs.extend([aux, lay]);
    let dtype = inputs[0].dtype;
    let out = register_cube_op::<R, F, I, BT>(
        "occ_model::dca_sample",
        inputs.clone(),
        &[(Shape::new([dims.n, dims.d]), dtype)],
        Arc::new(move |t| vec![forward_launch(t, dims)]),
    )
    .pop()
    .expect("one output");
    let nodes = parents.map(|t| t.node.clone());
    let result: FloatTensor<Ad<R, F, I, BT, C>> = match DcaCubeBackward
        .prepare::<C>(nodes)
        .compute_bound()
        .stateful()
    {
        OpsKind::Tracked(prep) => prep.finish(Saved { inputs, dims }, out),
        OpsKind::UnTracked(prep) => prep.finish(out),
    };
    Tensor::from_primitive(TensorPrimitive::Float(result))
}

/// The backward step of [`sample_autodiff`].
#[derive(Debug)]
struct DcaCubeBackward;

impl<R, F, I, BT> Backward<Fused<R, F, I, BT>, 4> for DcaCubeBackward
where
    R: CubeRuntime,
    F: FloatElement,
    I: IntElement,
    BT: BoolElement,
{
    type State = Saved<R>;

    fn backward(
        self,
        ops: Ops<Self::State, 4>,
        grads: &mut Gradients,
        _checkpointer: &mut Checkpointer,
    ) {
        let Ops {
            parents,
            node,
            state: Saved { mut inputs, dims },
        } = ops;
        let dout = grads.consume::<Fused<R, F, I, BT>>(&node);
        inputs.push(dout);
        let dtype = inputs[0].dtype;
        let taps = dims.taps();
        let shapes = [
            (Shape::new([dims.rows, dims.d]), dtype),
            (Shape::new([dims.n * taps * 2]), dtype),
            (Shape::new([dims.n * taps]), dtype),
            (Shape::new([dims.hits]), dtype),
        ];
        let outs = register_cube_op::<R, F, I, BT>(
            "occ_model::dca_sample_backward",
            inputs,
            &shapes,
            Arc::new(move |t| backward_launch(t, dims)),
        );
        for (parent, grad) in parents.into_iter().zip(outs) {
            if let Some(parent) = parent {
                grads.register::<Fused<R, F, I, BT>>(parent.id, grad);
            }
        }
    }
}

/// This file's text, for `check-cuda-source` to find every launchable kernel declared here in
/// [`cuda_source_kernels`] (`occ_sparse::cuda_source::launchable_kernels`).
#[cfg(feature = "cuda-source")]
pub const KERNEL_SOURCE: &str = include_str!("dca_cube.rs");

/// Every configuration of this file's kernels that a CUDA launch can compile, for
/// `sparseocc check-cuda-source` (`occ_sparse::cuda_source`): each kernel with the backend's
/// element types `float` / `int`, both address types, both passes of the bucket fill, and the
/// cube shapes of its launcher (`CubeDim::new` for one unit per value, one `SCAN_UNITS` cube for
/// the scan).
#[cfg(feature = "cuda-source")]
pub fn cuda_source_kernels(
    client: &cubecl::prelude::ComputeClient<occ_sparse::cuda_source::OfflineCuda>,
    float: cubecl::ir::StorageType,
    int: cubecl::ir::StorageType,
) -> Vec<Box<dyn cubecl::prelude::CubeKernel>> {
    use cubecl::prelude::{CubeKernel, TensorCompilationArg};
    use kernel::*;
    use occ_sparse::cuda_source::{elementwise_cube_dims, launch_settings, OfflineCuda as R};
    let t = || TensorCompilationArg { inplace: None };
    let dims = || DcaDimsCompilationArg {
        n: (),
        d: (),
        dh: (),
        m: (),
        nl: (),
        p: (),
        hits: (),
    };
    let c = || client.clone();
    let ft = [float, int];
    let mut k: Vec<Box<dyn CubeKernel>> = Vec::new();
    for s in launch_settings(&elementwise_cube_dims(client)) {
        let s = || s.clone();
        k.push(Box::new(dca_forward_kernel::DcaForwardKernel::<R>::new(
            s(),
            c(),
            t(),
            t(),
            t(),
            t(),
            t(),
            t(),
            t(),
            dims(),
            ft,
        )));
        k.push(Box::new(dca_tap_grad_kernel::DcaTapGradKernel::<R>::new(
            s(),
            c(),
            t(),
            t(),
            t(),
            t(),
            t(),
            t(),
            t(),
            t(),
            t(),
            dims(),
            ft,
        )));
        k.push(Box::new(dca_gate_grad_kernel::DcaGateGradKernel::<R>::new(
            s(),
            c(),
            t(),
            t(),
            t(),
            t(),
            t(),
            t(),
            t(),
            dims(),
            ft,
        )));
        for fill in [false, true] {
            k.push(Box::new(dca_bucket_kernel::DcaBucketKernel::<R>::new(
                s(),
                c(),
                t(),
                t(),
                t(),
                t(),
                t(),
                t(),
                dims(),
                fill,
                ft,
            )));
        }
        k.push(Box::new(dca_sort_kernel::DcaSortKernel::<R>::new(
            s(),
            c(),
            t(),
            t(),
            (),
        )));
        k.push(Box::new(
            dca_value_grad_kernel::DcaValueGradKernel::<R>::new(
                s(),
                c(),
                t(),
                t(),
                t(),
                t(),
                t(),
                t(),
                t(),
                t(),
                t(),
                (),
                dims(),
                ft,
            ),
        ));
    }
    for s in launch_settings(&[CubeDim::new_1d(SCAN_UNITS as u32)]) {
        k.push(Box::new(dca_scan_kernel::DcaScanKernel::<R>::new(
            s,
            c(),
            t(),
            t(),
            (),
        )));
    }
    k
}
