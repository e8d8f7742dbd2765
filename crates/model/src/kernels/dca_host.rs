//! The sampling step of deformable cross attention ([`crate::kernels::dca`]) as host loops with their own
//! backward pass, for burn-ndarray with and without autodiff (the CPU training and inference paths).
//!
//! `out[q] = 1/|V_q| · Σ_{hits h of q} g_h · Σ_{m, l, j} w_{qmlj} · bilinear(values_l[img_h], ref_h/s_l + Δp_{qmlj})[head m]`
//!
//! This is the function [`crate::kernels::dca::sample_tensor_ops`] composes from `select`,
//! `grid_sample` and `select_assign` (zero padding, `align_corners = false`), computed the way
//! Deformable DETR's `MSDeformAttn` kernel does: one pass over the (hit, head, level, point) taps
//! forward, one pass backward that writes the gradients of the value maps (scattered over the four
//! bilinear corners), of the offsets (the derivative of the bilinear weights), of the attention
//! weights and of the per-hit gate. burn's generic `grid_sample` on `Autodiff<NdArray>` expands the
//! value maps per sample and scatters element by element in its backward; in the demo's training
//! step that and the surrounding copies were about half of the time (perf, 2-core machine).
//!
//! [`crate::kernels::ModelBackend`] runs [`sample_host`] on `NdArray` and [`sample_autodiff`] (the op
//! registered with burn's autodiff graph, [`Backward`]) on `Autodiff<NdArray>`, so the rest of the
//! model is unchanged; every other backend (CUDA) runs the tensor-op composition. The tests in
//! `tests/model_f64/pp_dca.rs` check values and every gradient against it.

use crate::kernels::dca::{DcaSample, ViewHits};
use crate::kernels::host_data::{from_ad, host_vec, to_ad, AdTensor, Elem, NdElem};
use burn::backend::autodiff::checkpoint::base::Checkpointer;
use burn::backend::autodiff::checkpoint::strategy::CheckpointStrategy;
use burn::backend::autodiff::grads::Gradients;
use burn::backend::autodiff::ops::{Backward, Ops, OpsKind};
use burn::backend::ndarray::{NdArrayTensor, SharedArray};
use burn::backend::{Autodiff, NdArray};
use burn::prelude::*;
use burn::tensor::ops::FloatTensorOps;
use burn::tensor::{DType, TensorData};
use occ_sparse::host::HostFloat;
use rayon::prelude::*;
use std::sync::Arc;

/// One image feature level: `h × w` feature pixels, `stride` input pixels per feature pixel, rows
/// `row0 .. row0 + num_images·h·w` of the flat value matrix.
#[derive(Clone, Copy, Debug)]
pub(crate) struct LevelGeom {
    pub h: usize,
    pub w: usize,
    pub stride: usize,
    pub row0: usize,
}

/// Everything about the taps that is not a tensor: sizes, levels, and the hits grouped by query.
#[derive(Clone, Debug)]
pub(crate) struct SampleLayout {
    /// Queries `N`.
    pub n: usize,
    /// Heads `M`, points per head and level `P`, width `D` (`D/M` per head).
    pub m: usize,
    pub p: usize,
    pub d: usize,
    pub levels: Vec<LevelGeom>,
    /// Rows of the flat value matrix `[R, D]` (all levels, all images).
    pub num_rows: usize,
    /// Hits of query `q`: `order[start[q]..start[q + 1]]` (indices into the hit arrays).
    pub start: Vec<usize>,
    pub order: Vec<usize>,
    /// Image index of each hit.
    pub image: Vec<u32>,
    /// Reference point of each hit, network-input pixels.
    pub uv: Vec<[f64; 2]>,
    /// Views that see each query.
    pub views: Vec<u32>,
}

impl SampleLayout {
    /// The layout of the taps of `s`.
    pub fn of<B: Backend>(s: &DcaSample<'_, B>) -> Self {
        let dims: Vec<(usize, usize, usize)> = s
            .values
            .levels
            .iter()
            .map(|&[bv, h, w]| (bv, h, w))
            .collect();
        let (m, p) = s.heads_points();
        Self::new(s.hits, &dims, s.strides, m, p, s.width())
    }

    /// Layout of `hits` over levels of `dims[l] = (num_images, h, w)` with `strides[l]`.
    pub fn new(
        hits: &ViewHits,
        dims: &[(usize, usize, usize)],
        strides: &[usize],
        m: usize,
        p: usize,
        d: usize,
    ) -> Self {
        let n = hits.num_queries;
        let mut levels = Vec::with_capacity(dims.len());
        let mut row0 = 0;
        for (&(bv, h, w), &stride) in dims.iter().zip(strides) {
            levels.push(LevelGeom { h, w, stride, row0 });
            row0 += bv * h * w;
        }
        // Hits grouped by query (counting sort), so that each query owns its output row.
        let mut start = vec![0usize; n + 1];
        for &q in &hits.query {
            start[q as usize + 1] += 1;
        }
        for q in 0..n {
            start[q + 1] += start[q];
        }
        let mut order = vec![0usize; hits.len()];
        let mut fill = start.clone();
        for (hi, &q) in hits.query.iter().enumerate() {
            order[fill[q as usize]] = hi;
            fill[q as usize] += 1;
        }
        Self {
            n,
            m,
            p,
            d,
            levels,
            num_rows: row0,
            start,
            order,
            image: hits.image.clone(),
            uv: hits.uv.clone(),
            views: hits.views_per_query.clone(),
        }
    }

    pub fn num_hits(&self) -> usize {
        self.image.len()
    }

    /// Sampling taps per query and hit.
    fn taps_per_query(&self) -> usize {
        self.m * self.levels.len() * self.p
    }

    /// Calls `f(hit, k, head, row, c, c_dx, c_dy)` for every in-map bilinear corner of every tap of
    /// query `q`: `k` indexes the offsets / weights (`((q·M + head)·L + l)·P + j`), `row` the value
    /// matrix, `c` is the bilinear weight of the corner and `c_dx`, `c_dy` its derivatives with
    /// respect to the sampling position (feature pixels).
    #[inline]
    fn for_each_corner<T: Elem>(
        &self,
        q: usize,
        off: &[T],
        mut f: impl FnMut(usize, usize, usize, usize, f64, f64, f64),
    ) {
        let (m, p, nl) = (self.m, self.p, self.levels.len());
        for &hi in &self.order[self.start[q]..self.start[q + 1]] {
            let img = self.image[hi] as usize;
            let [u, v] = self.uv[hi];
            for (lvl, g) in self.levels.iter().enumerate() {
                let (h, w) = (g.h as i64, g.w as i64);
                let s = g.stride as f64;
                let (bx, by) = ((u + 0.5) / s - 0.5, (v + 0.5) / s - 0.5);
                for head in 0..m {
                    for j in 0..p {
                        let k = ((q * m + head) * nl + lvl) * p + j;
                        let x = bx + off[2 * k].to_f64();
                        let y = by + off[2 * k + 1].to_f64();
                        let (x0, y0) = (x.floor(), y.floor());
                        let (fx, fy) = (x - x0, y - y0);
                        let (x0, y0) = (x0 as i64, y0 as i64);
                        for (yy, wy, dwy) in [(y0, 1.0 - fy, -1.0), (y0 + 1, fy, 1.0)] {
                            if yy < 0 || yy >= h {
                                continue;
                            }
                            for (xx, wx, dwx) in [(x0, 1.0 - fx, -1.0), (x0 + 1, fx, 1.0)] {
                                if xx < 0 || xx >= w {
                                    continue;
                                }
                                let row = g.row0 + ((img as i64 * h + yy) * w + xx) as usize;
                                f(hi, k, head, row, wx * wy, dwx * wy, wx * dwy);
                            }
                        }
                    }
                }
            }
        }
    }

    /// The forward pass: `out [N, D]` from `values [R, D]`, `off [N·M·L·P·2]`, `wts [N·M·L·P]` and
    /// the per-hit `gate` (`None` = ones).
    pub fn forward<T: Elem>(
        &self,
        values: &[T],
        off: &[T],
        wts: &[T],
        gate: Option<&[T]>,
    ) -> Vec<T> {
        let (d, dh) = (self.d, self.d / self.m);
        let mut out = vec![T::zero(); self.n * d];
        out.par_chunks_mut(d).enumerate().for_each(|(q, acc)| {
            self.for_each_corner(q, off, |hi, k, head, row, c, _, _| {
                let g = gate.map_or(1.0, |g| g[hi].to_f64());
                if g == 0.0 {
                    return;
                }
                let c = T::from_f64(wts[k].to_f64() * g * c);
                let src = &values[row * d + head * dh..row * d + (head + 1) * dh];
                for (o, &val) in acc[head * dh..(head + 1) * dh].iter_mut().zip(src) {
                    *o += c * val;
                }
            });
            let views = self.views[q];
            if views > 1 {
                let inv = T::from_f64(1.0 / views as f64);
                acc.iter_mut().for_each(|o| *o = *o * inv);
            }
        });
        out
    }

    /// The backward pass of [`Self::forward`] for the output gradient `dout [N, D]`: the gradients
    /// of `values`, `off`, `wts` and `gate` (same layouts; the gate's is per hit).
    pub fn backward<T: Elem>(
        &self,
        saved: &Saved<T>,
        dout: &[T],
    ) -> (Vec<T>, Vec<T>, Vec<T>, Vec<T>) {
        let (d, dh, t) = (self.d, self.d / self.m, self.taps_per_query());
        let (values, off, wts) = (&saved.values[..], &saved.off[..], &saved.wts[..]);
        let gate = saved.gate.as_deref();
        let mut d_off = vec![T::zero(); self.n * t * 2];
        let mut d_wts = vec![T::zero(); self.n * t];
        // Few large chunks, each with its own value-gradient buffer. Their number does not depend on
        // the thread count and the buffers are summed in chunk order afterwards (not by rayon's
        // `reduce`, whose tree follows work stealing), so the gradient is bitwise the same in every
        // run and with any number of threads.
        let chunk = self.n.div_ceil(DVALUE_CHUNKS).max(64);
        let parts: Vec<ChunkGrads<T>> = d_off
            .par_chunks_mut(chunk * t * 2)
            .zip(d_wts.par_chunks_mut(chunk * t))
            .enumerate()
            .map(|(ci, (d_off, d_wts))| {
                let mut d_values = vec![T::zero(); self.num_rows * d];
                let mut d_gate: Vec<(usize, f64)> = Vec::new();
                let q0 = ci * chunk;
                for q in q0..(q0 + chunk).min(self.n) {
                    let views = self.views[q];
                    if views == 0 {
                        continue;
                    }
                    let inv = 1.0 / views as f64;
                    let dq = &dout[q * d..(q + 1) * d];
                    let mut last_hit = usize::MAX;
                    let mut g_acc = 0.0;
                    self.for_each_corner(q, off, |hi, k, head, row, c, c_dx, c_dy| {
                        if hi != last_hit {
                            if last_hit != usize::MAX {
                                d_gate.push((last_hit, g_acc));
                            }
                            last_hit = hi;
                            g_acc = 0.0;
                        }
                        let g = gate.map_or(1.0, |g| g[hi].to_f64());
                        let wk = wts[k].to_f64();
                        let src = &values[row * d + head * dh..row * d + (head + 1) * dh];
                        let dqh = &dq[head * dh..(head + 1) * dh];
                        let mut dot = 0.0f64;
                        for (&a, &b) in src.iter().zip(dqh) {
                            dot += (a * b).to_f64();
                        }
                        let dot = dot * inv;
                        let kl = k - q0 * t;
                        d_wts[kl] += T::from_f64(g * c * dot);
                        d_off[2 * kl] += T::from_f64(g * wk * c_dx * dot);
                        d_off[2 * kl + 1] += T::from_f64(g * wk * c_dy * dot);
                        g_acc += wk * c * dot;
                        if g != 0.0 {
                            let cv = T::from_f64(g * wk * c * inv);
                            let dst = &mut d_values[row * d + head * dh..row * d + (head + 1) * dh];
                            for (o, &b) in dst.iter_mut().zip(dqh) {
                                *o += cv * b;
                            }
                        }
                    });
                    if last_hit != usize::MAX {
                        d_gate.push((last_hit, g_acc));
                    }
                }
                (d_values, d_gate)
            })
            .collect();
        let mut parts = parts.into_iter();
        let (mut d_values, mut d_gate) = parts
            .next()
            .unwrap_or_else(|| (vec![T::zero(); self.num_rows * d], Vec::new()));
        for (b, gb) in parts {
            d_values.iter_mut().zip(&b).for_each(|(x, &y)| *x += y);
            d_gate.extend(gb);
        }
        let mut gate_grad = vec![0.0f64; self.num_hits()];
        for (hi, v) in d_gate {
            gate_grad[hi] += v;
        }
        let gate_grad = gate_grad.into_iter().map(T::from_f64).collect();
        (d_values, d_off, d_wts, gate_grad)
    }
}

/// Query chunks of the backward pass (each carries a value-gradient buffer of the whole value map).
const DVALUE_CHUNKS: usize = 8;

/// One chunk's value gradient and its `(hit, gate gradient)` contributions.
type ChunkGrads<T> = (Vec<T>, Vec<(usize, f64)>);

/// Host copies of the forward inputs, kept for the backward pass.
#[derive(Debug)]
pub(crate) struct Saved<T> {
    layout: SampleLayout,
    values: Vec<T>,
    off: Vec<T>,
    wts: Vec<T>,
    gate: Option<Vec<T>>,
}

/// The float type the host loops can run `s` in: f32 or f64 when the values, offsets and weights
/// all hold it, else `None`.
pub(crate) fn host_dtype<B: Backend>(s: &DcaSample<'_, B>) -> Option<DType> {
    let dtype = s.offsets.dtype();
    let same = s.weights.dtype() == dtype && s.values.rows.dtype() == dtype;
    (same && matches!(dtype, DType::F32 | DType::F64)).then_some(dtype)
}

/// The sampling as one host loop (CPU inference; not differentiable), in the float type of the
/// tensors (f32 or f64; the gate is converted to it). The tensors go through `TensorData`: the
/// offsets, weights and value rows are freshly computed, unshared tensors, whose `into_data` hands
/// over their buffers without copying. `Err(s)` (the inputs back) when [`host_dtype`] is `None`.
///
/// # Shapes
/// see [`DcaSample`]; returns `[N, D]`
#[allow(clippy::result_large_err)]
pub(crate) fn sample_host<'a, B: Backend>(
    s: DcaSample<'a, B>,
) -> Result<Tensor<B, 2>, DcaSample<'a, B>> {
    match host_dtype(&s) {
        Some(DType::F32) => Ok(sample_host_typed::<B, f32>(s)),
        Some(DType::F64) => Ok(sample_host_typed::<B, f64>(s)),
        _ => Err(s),
    }
}

fn sample_host_typed<B: Backend, T: Elem>(s: DcaSample<'_, B>) -> Tensor<B, 2> {
    let device = s.offsets.device();
    let layout = SampleLayout::of(&s);
    let DcaSample {
        values,
        offsets,
        weights,
        gate,
        ..
    } = s;
    let vec = |d: TensorData| -> Vec<T> { d.into_vec().expect("dtype checked") };
    let gate: Option<Vec<T>> = gate.map(|g| vec(g.into_data().convert::<T>()));
    let off = vec(offsets.into_data());
    let wts = vec(weights.into_data());
    let values = vec(values.rows.into_data());
    let out = layout.forward(&values, &off, &wts, gate.as_deref());
    super::count(|c| c.dca += 1);
    Tensor::from_data(TensorData::new(out, [layout.n, layout.d]), &device)
}

/// The sampling on `Autodiff<NdArray<T>, C>` (CPU training) as one autodiff op with its own backward
/// pass; `Err(s)` (the inputs back) when a tensor holds another float type than `T` (burn 0.21 fixes
/// a device's float dtype at the first tensor of the process).
///
/// # Shapes
/// see [`DcaSample`]; the value rows are `[R, D]`, all levels (see [`LevelGeom`]); returns `[N, D]`
#[allow(clippy::result_large_err, clippy::type_complexity)]
pub(crate) fn sample_autodiff<'a, T, C>(
    s: DcaSample<'a, Autodiff<NdArray<T>, C>>,
) -> Result<Tensor<Autodiff<NdArray<T>, C>, 2>, DcaSample<'a, Autodiff<NdArray<T>, C>>>
where
    T: NdElem,
    C: CheckpointStrategy,
    NdArrayTensor: From<SharedArray<T>>,
{
    let gate_ok = s.gate.as_ref().is_none_or(|g| g.dtype() == T::dtype());
    if host_dtype(&s) != Some(T::dtype()) || !gate_ok {
        return Err(s);
    }
    let layout = SampleLayout::of(&s);
    let device = s.offsets.device();
    let DcaSample {
        values,
        offsets,
        weights,
        gate,
        ..
    } = s;
    let gate = match gate {
        Some(g) => g,
        None => Tensor::from_data(
            TensorData::new(
                vec![<T as HostFloat>::one(); layout.num_hits()],
                [layout.num_hits()],
            ),
            &device,
        ),
    };
    let (values, off, wts, gate) = (
        to_ad(values.rows),
        to_ad(offsets),
        to_ad(weights),
        to_ad(gate),
    );
    let host = |t: &AdTensor<T, C>| host_vec::<T>(&t.primitive).expect("dtype checked");
    let saved = Saved {
        values: host(&values),
        off: host(&off),
        wts: host(&wts),
        gate: Some(host(&gate)),
        layout,
    };
    let out = saved
        .layout
        .forward(&saved.values, &saved.off, &saved.wts, saved.gate.as_deref());
    let shape = [saved.layout.n, saved.layout.d];
    let out_prim = NdArray::<T>::float_from_data(TensorData::new(out, shape), &Default::default());
    let nodes = [
        values.node.clone(),
        off.node.clone(),
        wts.node.clone(),
        gate.node.clone(),
    ];
    let result: AdTensor<T, C> = match DeformSampleBackward
        .prepare::<C>(nodes)
        .compute_bound()
        .stateful()
    {
        OpsKind::Tracked(prep) => prep.finish(Arc::new(saved), out_prim),
        OpsKind::UnTracked(prep) => prep.finish(out_prim),
    };
    super::count(|c| c.dca_autodiff += 1);
    Ok(from_ad(result))
}

/// The backward step of [`sample_autodiff`].
#[derive(Debug)]
struct DeformSampleBackward;

impl<T: NdElem> Backward<NdArray<T>, 4> for DeformSampleBackward
where
    NdArrayTensor: From<SharedArray<T>>,
{
    type State = Arc<Saved<T>>;

    fn backward(
        self,
        ops: Ops<Self::State, 4>,
        grads: &mut Gradients,
        _checkpointer: &mut Checkpointer,
    ) {
        let Ops {
            parents,
            node,
            state: saved,
        } = ops;
        let dout = grads.consume::<NdArray<T>>(&node);
        let lay = &saved.layout;
        let dout: Vec<T> = host_vec(&dout).expect("the output gradient of an NdArray<T> op");
        let (d_values, d_off, d_wts, d_gate) = lay.backward(&saved, &dout);
        let nl = lay.levels.len();
        let outs = [
            (d_values, vec![lay.num_rows, lay.d]),
            (d_off, vec![lay.n, lay.m, nl, lay.p, 2]),
            (d_wts, vec![lay.n, lay.m, nl, lay.p]),
            (d_gate, vec![lay.num_hits()]),
        ];
        for (parent, (v, shape)) in parents.into_iter().zip(outs) {
            if let Some(parent) = parent {
                let t =
                    NdArray::<T>::float_from_data(TensorData::new(v, shape), &Default::default());
                grads.register::<NdArray<T>>(parent.id, t);
            }
        }
    }
}
