//! The sampling step of deformable cross attention ([`crate::sparseocc_pp::dca`]) as host loops with their own
//! backward pass, for burn-ndarray with and without autodiff (the CPU training and inference paths).
//!
//! `out[q] = 1/|V_q| · Σ_{hits h of q} g_h · Σ_{m, l, j} w_{qmlj} · bilinear(values_l[img_h], ref_h/s_l + Δp_{qmlj})[head m]`
//!
//! This is the function [`crate::sparseocc_pp::dca::DeformableCrossAttention::aggregate_tensor_ops`] composes from
//! `select`, `grid_sample` and `select_assign` (zero padding, `align_corners = false`), computed the
//! way Deformable DETR's `MSDeformAttn` kernel does: one pass over the (hit, head, level, point) taps
//! forward, one pass backward that writes the gradients of the value maps (scattered over the four
//! bilinear corners), of the offsets (the derivative of the bilinear weights), of the attention
//! weights and of the per-hit gate. burn's generic `grid_sample` on `Autodiff<NdArray>` expands the
//! value maps per sample and scatters element by element in its backward; in the demo's training
//! step that and the surrounding copies were about half of the time (perf, 2-core machine).
//!
//! On `Autodiff<NdArray<f32 | f64>>` the op is registered with burn's autodiff graph
//! ([`Backward`]), so the rest of the model is unchanged; on any other backend (CUDA) the tensor-op
//! composition is used. The tests in `dca.rs` check values and every gradient against it.

use crate::kernels::host_data::{from_ad, host_vec, to_ad, AdTensor, Elem};
use crate::sparseocc_pp::dca::ViewHits;
use burn::backend::autodiff::checkpoint::base::Checkpointer;
use burn::backend::autodiff::grads::Gradients;
use burn::backend::autodiff::ops::{Backward, Ops, OpsKind};
use burn::backend::ndarray::{FloatNdArrayElement, NdArrayTensor, SharedArray};
use burn::backend::{Autodiff, NdArray};
use burn::prelude::*;
use burn::tensor::ops::FloatTensorOps;
use burn::tensor::TensorData;
use rayon::prelude::*;
use std::any::TypeId;
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
    start: Vec<usize>,
    order: Vec<usize>,
    image: Vec<u32>,
    uv: Vec<[f64; 2]>,
    views: Vec<u32>,
}

impl SampleLayout {
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

    fn num_hits(&self) -> usize {
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

/// The sampling on `Autodiff<NdArray<f32 | f64>>` as one autodiff op; `None` on other backends.
///
/// # Shapes
/// - `values`: `[R, D]` (the value maps of all levels, channel-last rows, see [`LevelGeom`])
/// - `off`: `[N, M, L, P, 2]` feature pixels; `wts`: `[N, M, L, P]`; `gate`: `[num_hits]`
/// - returns `[N, D]`
pub(crate) fn sample_autodiff<B: Backend>(
    layout: SampleLayout,
    values: Tensor<B, 2>,
    off: Tensor<B, 5>,
    wts: Tensor<B, 4>,
    gate: Option<Tensor<B, 1>>,
) -> Option<Tensor<B, 2>> {
    if TypeId::of::<B>() == TypeId::of::<Autodiff<NdArray<f32>>>() {
        typed::<B, f32>(layout, values, off, wts, gate)
    } else if TypeId::of::<B>() == TypeId::of::<Autodiff<NdArray<f64>>>() {
        typed::<B, f64>(layout, values, off, wts, gate)
    } else {
        None
    }
}

fn typed<B: Backend, T: Elem + FloatNdArrayElement>(
    layout: SampleLayout,
    values: Tensor<B, 2>,
    off: Tensor<B, 5>,
    wts: Tensor<B, 4>,
    gate: Option<Tensor<B, 1>>,
) -> Option<Tensor<B, 2>>
where
    NdArrayTensor: From<SharedArray<T>>,
{
    let device = values.device();
    let gate = match gate {
        Some(g) => g,
        None => Tensor::<B, 1>::ones([layout.num_hits()], &device),
    };
    let (values, off, wts, gate) = (
        to_ad::<B, 2, T>(values)?,
        to_ad::<B, 5, T>(off)?,
        to_ad::<B, 4, T>(wts)?,
        to_ad::<B, 1, T>(gate)?,
    );
    let saved = Saved {
        values: host_vec(&values.primitive)?,
        off: host_vec(&off.primitive)?,
        wts: host_vec(&wts.primitive)?,
        gate: Some(host_vec(&gate.primitive)?),
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
    let result: AdTensor<T> = match DeformSampleBackward
        .prepare::<burn::backend::autodiff::checkpoint::strategy::NoCheckpointing>(nodes)
        .compute_bound()
        .stateful()
    {
        OpsKind::Tracked(prep) => prep.finish(Arc::new(saved), out_prim),
        OpsKind::UnTracked(prep) => prep.finish(out_prim),
    };
    from_ad(result)
}

/// The backward step of [`sample_autodiff`].
#[derive(Debug)]
struct DeformSampleBackward;

impl<T: Elem + FloatNdArrayElement> Backward<NdArray<T>, 4> for DeformSampleBackward
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
