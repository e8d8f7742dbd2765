//! Host (CPU) compute of sparse convolution: blocked gather -> GEMM -> scatter.
//!
//! Output rows are split into blocks processed in parallel (rayon); each block owns its output rows, so
//! there is no write conflict and no atomics. Inside a block, for every kernel offset, the input rows
//! paired with the block's outputs are gathered into a contiguous buffer, multiplied by that offset's
//! weight slice with a GEMM ([`HostFloat::gemm`], the `gemm` crate), and added into the block. The
//! weight is read in place through strides (no transposed copy).

use crate::kernel_map::{KernelMap, OutputPairs};
use rayon::prelude::*;
use std::mem::MaybeUninit;

/// Float types the host path computes in.
pub trait HostFloat: Copy + Send + Sync + Default + std::ops::AddAssign + 'static {
    /// `C = alpha * A B + beta * C` with arbitrary strides.
    ///
    /// # Safety
    /// Pointers and strides must describe valid `m x k`, `k x n`, `m x n` matrices.
    #[allow(clippy::too_many_arguments)]
    unsafe fn gemm(
        m: usize,
        k: usize,
        n: usize,
        a: *const Self,
        rsa: isize,
        csa: isize,
        b: *const Self,
        rsb: isize,
        csb: isize,
        beta: Self,
        c: *mut Self,
        rsc: isize,
        csc: isize,
    );
    /// Additive identity.
    fn zero() -> Self;
    /// Multiplicative identity.
    fn one() -> Self;
    /// The weight packed for [`HostFloat::fused_pairs`] (`[K][C_in][C_out]`) when the fused
    /// gather-multiply-scatter kernel exists for this type, these widths and this CPU.
    fn fused_plan(_w: &[Self], _wv: WeightView) -> Option<Vec<Self>> {
        None
    }
    /// `y[o - o0] += x[i] · wk` over the pairs (see [`crate::fused`]).
    ///
    /// # Safety
    /// Only after [`HostFloat::fused_plan`] returned `Some`; slices as documented on [`OffsetPairs`].
    unsafe fn fused_pairs(_pairs: &OffsetPairs<'_, Self>, _yblock: &mut [Self]) {
        unreachable!("no fused kernel for this type")
    }
    /// Writes every row of an output block, output-major (see [`crate::fused`]).
    ///
    /// # Safety
    /// Only after [`HostFloat::fused_plan`] returned `Some`; slices as documented on [`OutputRows`].
    unsafe fn fused_rows(_job: &OutputRows<'_, Self>, _yblock: &mut [MaybeUninit<Self>]) {
        unreachable!("no fused kernel for this type")
    }
}

impl HostFloat for f32 {
    unsafe fn gemm(
        m: usize,
        k: usize,
        n: usize,
        a: *const f32,
        rsa: isize,
        csa: isize,
        b: *const f32,
        rsb: isize,
        csb: isize,
        beta: f32,
        c: *mut f32,
        rsc: isize,
        csc: isize,
    ) {
        // SAFETY: forwarded contract.
        unsafe { gemm_strided(m, k, n, a, rsa, csa, b, rsb, csb, beta, c, rsc, csc) }
    }
    fn zero() -> Self {
        0.0
    }
    fn one() -> Self {
        1.0
    }
    fn fused_plan(w: &[f32], wv: WeightView) -> Option<Vec<f32>> {
        crate::fused::available(wv.cin(), wv.cout()).then(|| crate::fused::pack_weight(w, wv))
    }
    unsafe fn fused_pairs(pairs: &OffsetPairs<'_, f32>, yblock: &mut [f32]) {
        // SAFETY: forwarded contract.
        unsafe { crate::fused::pairs_into_block(pairs, yblock) }
    }
    unsafe fn fused_rows(job: &OutputRows<'_, f32>, yblock: &mut [MaybeUninit<f32>]) {
        // SAFETY: forwarded contract.
        unsafe { crate::fused::rows_by_output(job, yblock) }
    }
}

impl HostFloat for f64 {
    unsafe fn gemm(
        m: usize,
        k: usize,
        n: usize,
        a: *const f64,
        rsa: isize,
        csa: isize,
        b: *const f64,
        rsb: isize,
        csb: isize,
        beta: f64,
        c: *mut f64,
        rsc: isize,
        csc: isize,
    ) {
        // SAFETY: forwarded contract.
        unsafe { gemm_strided(m, k, n, a, rsa, csa, b, rsb, csb, beta, c, rsc, csc) }
    }
    fn zero() -> Self {
        0.0
    }
    fn one() -> Self {
        1.0
    }
}

/// `C = A B + beta C` through the `gemm` crate, for f32 and f64. Called from inside a rayon job
/// (the blocked host loops, one block per job) it runs on the calling thread; called from outside
/// (one large product, e.g. an image convolution's) it splits the product over rayon's pool.
///
/// Not `matrixmultiply`, measured on the 2-core development machine (BENCHMARKS.md, "host GEMM"):
/// its own thread pool competes with rayon's when called from rayon jobs (a `[512, 128] x
/// [128, 128]` block ran at 89 GFLOP/s, 133 with that pool off), and it packs every operand on
/// every call; `gemm` ran the same blocks at 174 GFLOP/s and a 2048³ product at 213 against 183.
///
/// # Safety
/// Pointers and strides must describe valid `m x k`, `k x n`, `m x n` matrices; `c` is not read
/// when `beta` is zero.
#[allow(clippy::too_many_arguments)]
unsafe fn gemm_strided<T: HostFloat + PartialEq>(
    m: usize,
    k: usize,
    n: usize,
    a: *const T,
    rsa: isize,
    csa: isize,
    b: *const T,
    rsb: isize,
    csb: isize,
    beta: T,
    c: *mut T,
    rsc: isize,
    csc: isize,
) {
    if m == 0 || n == 0 {
        return;
    }
    let parallelism = if rayon::current_thread_index().is_some() {
        gemm::Parallelism::None
    } else {
        gemm::Parallelism::Rayon(0)
    };
    // gemm's convention: dst = alpha·dst + beta·lhs·rhs, dst read only when asked; strides are
    // given column stride first.
    let read_dst = beta != T::zero();
    // SAFETY: forwarded contract (same matrices, strides in gemm's order).
    unsafe {
        gemm::gemm(
            m,
            n,
            k,
            c,
            csc,
            rsc,
            read_dst,
            a,
            csa,
            rsa,
            b,
            csb,
            rsb,
            beta,
            T::one(),
            false,
            false,
            false,
            parallelism,
        )
    }
}

/// One kernel offset's pairs inside an output block, as the fused kernel reads them.
#[derive(Clone, Copy, Debug)]
pub struct OffsetPairs<'a, F> {
    /// Input features `[n_in, cin]`, row-major, covering every index in `ins`.
    pub x: &'a [F],
    /// Input channels.
    pub cin: usize,
    /// The offset's weight slice `[cin, cout]`, row-major.
    pub wk: &'a [F],
    /// Output channels.
    pub cout: usize,
    /// Input row of each pair.
    pub ins: &'a [u32],
    /// Output row of each pair (`o - o0` indexes the block `[rows, cout]`).
    pub outs: &'a [u32],
    /// First output row of the block.
    pub o0: u32,
}

/// One block of output rows for the output-major kernel.
#[derive(Clone, Copy, Debug)]
pub struct OutputRows<'a, F> {
    /// Input features `[n_in, cin]`, row-major, covering every input row of `pairs`.
    pub x: &'a [F],
    /// Input channels.
    pub cin: usize,
    /// The weight packed `[K][cin][cout]` by [`HostFloat::fused_plan`].
    pub packed: &'a [F],
    /// Output channels.
    pub cout: usize,
    /// The map's pairs by output row; the block's rows are `o0..o0 + block.len() / cout`.
    pub pairs: &'a OutputPairs,
    /// First output row of the block.
    pub o0: usize,
}

/// How the weight `[D0, K, D2]` is applied.
///
/// * `transposed == false`: `y[o, d0] += sum_d2 x[i, d2] * w[d0, k, d2]` (x has D2 channels, y has D0).
/// * `transposed == true`:  `y[o, d2] += sum_d0 x[i, d0] * w[d0, k, d2]` (x has D0 channels, y has D2).
#[derive(Clone, Copy, Debug)]
pub struct WeightView {
    /// First weight dimension.
    pub d0: usize,
    /// Kernel volume.
    pub k: usize,
    /// Last weight dimension.
    pub d2: usize,
    /// Apply the transposed slices.
    pub transposed: bool,
}

impl WeightView {
    pub(crate) fn cin(&self) -> usize {
        if self.transposed {
            self.d0
        } else {
            self.d2
        }
    }
    pub(crate) fn cout(&self) -> usize {
        if self.transposed {
            self.d2
        } else {
            self.d0
        }
    }
    /// Pointer offset and (row, col) strides of offset `k`'s `[cin, cout]` matrix.
    pub(crate) fn slice(&self, k: usize) -> (usize, isize, isize) {
        let s0 = (self.k * self.d2) as isize; // stride of d0
        let s2 = 1isize; // stride of d2
        let base = k * self.d2;
        if self.transposed {
            (base, s0, s2) // rows over d0 (cin), cols over d2 (cout)
        } else {
            (base, s2, s0) // rows over d2 (cin), cols over d0 (cout)
        }
    }
}

fn block_rows(n_out: usize, cout: usize) -> usize {
    // Enough blocks for load balance, blocks big enough for efficient GEMMs, block output in L2.
    let by_cache = (256 * 1024 / 4 / cout.max(1)).max(64);
    let by_balance = n_out
        .div_ceil(4 * rayon::current_num_threads().max(1))
        .max(64);
    by_cache.min(by_balance).min(1024)
}

/// Maps with at most 2.5 pairs per output row on average (this fraction) take the output-major
/// kernel: their outputs have one or two pairs each (e.g. a regular convolution of scattered
/// sites), and the offset-major path's zeroing and per-pair read-modify-write of the output
/// dominate. Above it the offset-major kernel's weight reuse (four pairs of one offset per register
/// tile) wins. Measured on the spconv comparison's 18 cases (BENCHMARKS.md, 2026-12-02): at 1.0-2.5
/// pairs per row output-major was faster in 10 of 12 (up to 1.7x) and 1.1-1.4x slower in two with
/// `C_in > C_out`; at 3.5-9.9 it was 1.0-1.9x slower in all 6.
const BY_OUTPUT_MAX_PAIRS_PER_ROW: (usize, usize) = (5, 2);

/// Whether [`conv_forward`] runs `map` output-major (where the fused kernels exist).
fn by_output_pays(map: &KernelMap) -> bool {
    let (num, den) = BY_OUTPUT_MAX_PAIRS_PER_ROW;
    map.num_pairs().saturating_mul(den) <= map.n_out().saturating_mul(num)
}

/// `y = conv(x, w)` over `map` on the host. `x` is `[n_in, cin]` row-major; returns `[n_out, cout]`.
///
/// Where the fused kernels exist ([`crate::fused`]: f32, AVX2 + FMA, `C_out` a multiple of 16,
/// `C_in·C_out` ≤ 8192), a map with few pairs per output row runs output-major
/// ([`conv_forward_by_output`]), others offset-major with the fused gather-multiply-scatter kernel
/// for every offset whose pairs are not the identity; without them every offset goes through a
/// gathered buffer, a GEMM and a scatter-add ([`conv_forward_gemm`]).
pub fn conv_forward<F: HostFloat>(x: &[F], w: &[F], wv: WeightView, map: &KernelMap) -> Vec<F> {
    match F::fused_plan(w, wv) {
        Some(p) if by_output_pays(map) => forward_by_output(x, &p, wv, map),
        packed => conv_forward_impl(x, w, wv, map, packed),
    }
}

/// [`conv_forward`] without the fused kernel: gather, GEMM, scatter-add for every offset (for
/// tests and A/B benchmarks of the two paths).
pub fn conv_forward_gemm<F: HostFloat>(
    x: &[F],
    w: &[F],
    wv: WeightView,
    map: &KernelMap,
) -> Vec<F> {
    conv_forward_impl(x, w, wv, map, None)
}

/// [`conv_forward`] output-major whatever the map (for tests and A/B benchmarks): each output row
/// summed over its pairs ([`KernelMap::by_output`]) in registers and written once. `None` where
/// the fused kernels do not exist for this type, these widths or this CPU.
pub fn conv_forward_by_output<F: HostFloat>(
    x: &[F],
    w: &[F],
    wv: WeightView,
    map: &KernelMap,
) -> Option<Vec<F>> {
    F::fused_plan(w, wv).map(|p| forward_by_output(x, &p, wv, map))
}

/// [`conv_forward`] offset-major whatever the map (for tests and A/B benchmarks).
pub fn conv_forward_by_offset<F: HostFloat>(
    x: &[F],
    w: &[F],
    wv: WeightView,
    map: &KernelMap,
) -> Vec<F> {
    conv_forward_impl(x, w, wv, map, F::fused_plan(w, wv))
}

fn forward_by_output<F: HostFloat>(
    x: &[F],
    packed: &[F],
    wv: WeightView,
    map: &KernelMap,
) -> Vec<F> {
    let (cin, cout) = (wv.cin(), wv.cout());
    let n_out = map.n_out();
    let len = n_out * cout;
    let mut y: Vec<F> = Vec::with_capacity(len);
    if len == 0 {
        return y;
    }
    let pairs = map.by_output();
    let rows = block_rows(n_out, cout);
    y.spare_capacity_mut()[..len]
        .par_chunks_mut(rows * cout)
        .enumerate()
        .for_each(|(bi, block)| {
            let job = OutputRows {
                x,
                cin,
                packed,
                cout,
                pairs,
                o0: bi * rows,
            };
            // SAFETY: `fused_plan` returned Some; every pair indexes x, the block holds whole rows.
            unsafe { F::fused_rows(&job, block) };
        });
    // SAFETY: every block wrote all of its values.
    unsafe { y.set_len(len) };
    y
}

fn conv_forward_impl<F: HostFloat>(
    x: &[F],
    w: &[F],
    wv: WeightView,
    map: &KernelMap,
    packed: Option<Vec<F>>,
) -> Vec<F> {
    let (cin, cout) = (wv.cin(), wv.cout());
    let n_out = map.n_out();
    let mut y = vec![F::zero(); n_out * cout];
    if n_out == 0 || cout == 0 {
        return y;
    }
    let rows = block_rows(n_out, cout);
    y.par_chunks_mut(rows * cout).enumerate().for_each_init(
        || (Vec::<F>::new(), Vec::<F>::new()),
        |(gbuf, tbuf), (bi, yblock)| {
            let o0 = (bi * rows) as u32;
            let o1 = o0 + (yblock.len() / cout) as u32;
            for k in 0..map.kernel_volume() {
                let (ins, outs) = map.pairs(k);
                let lo = outs.partition_point(|&o| o < o0);
                let hi = outs.partition_point(|&o| o < o1);
                let m = hi - lo;
                if m == 0 {
                    continue;
                }
                let (woff, rsb, csb) = wv.slice(k);
                let ins = &ins[lo..hi];
                let outs = &outs[lo..hi];
                // Identity pairs (centre of a submanifold kernel): multiply straight into the block.
                let identity = m == (o1 - o0) as usize
                    && ins[0] == o0
                    && ins[m - 1] == o1 - 1
                    && outs[0] == o0
                    && ins.iter().zip(outs).all(|(a, b)| a == b);
                if identity {
                    unsafe {
                        F::gemm(
                            m,
                            cin,
                            cout,
                            x.as_ptr().add(o0 as usize * cin),
                            cin as isize,
                            1,
                            w.as_ptr().add(woff),
                            rsb,
                            csb,
                            F::one(),
                            yblock.as_mut_ptr(),
                            cout as isize,
                            1,
                        );
                    }
                    continue;
                }
                if let Some(p) = &packed {
                    let pairs = OffsetPairs {
                        x,
                        cin,
                        wk: &p[k * cin * cout..(k + 1) * cin * cout],
                        cout,
                        ins,
                        outs,
                        o0,
                    };
                    // SAFETY: `fused_plan` returned Some; every pair indexes x and the block.
                    unsafe { F::fused_pairs(&pairs, yblock) };
                    continue;
                }
                gbuf.clear();
                gbuf.reserve(m * cin);
                for &i in ins {
                    let i = i as usize * cin;
                    gbuf.extend_from_slice(&x[i..i + cin]);
                }
                tbuf.clear();
                tbuf.resize(m * cout, F::zero());
                unsafe {
                    F::gemm(
                        m,
                        cin,
                        cout,
                        gbuf.as_ptr(),
                        cin as isize,
                        1,
                        w.as_ptr().add(woff),
                        rsb,
                        csb,
                        F::zero(),
                        tbuf.as_mut_ptr(),
                        cout as isize,
                        1,
                    );
                }
                for (j, &o) in outs.iter().enumerate() {
                    let dst = &mut yblock[(o - o0) as usize * cout..][..cout];
                    let src = &tbuf[j * cout..][..cout];
                    for (d, s) in dst.iter_mut().zip(src) {
                        *d += *s;
                    }
                }
            }
        },
    );
    y
}

/// Weight gradient: `dw[d0, k, d2] = sum over pairs (i, o) of offset k` of
/// `dy[o, d0] * x[i, d2]` (not transposed) or `x[i, d0] * dy[o, d2]` (transposed).
pub fn conv_weight_grad<F: HostFloat>(
    x: &[F],
    dy: &[F],
    wv: WeightView,
    map: &KernelMap,
) -> Vec<F> {
    let (cin, cout) = (wv.cin(), wv.cout());
    const CH: usize = 4096;
    let per_k: Vec<Vec<F>> = (0..wv.k)
        .into_par_iter()
        .map(|k| {
            // acc is [cout, cin] when not transposed (d0 = cout), [cin, cout] when transposed (d0 = cin):
            // always [d0, d2].
            let mut acc = vec![F::zero(); wv.d0 * wv.d2];
            let (ins, outs) = map.pairs(k);
            let mut gx = Vec::<F>::new();
            let mut gy = Vec::<F>::new();
            for (ic, oc) in ins.chunks(CH).zip(outs.chunks(CH)) {
                let m = ic.len();
                gx.clear();
                gy.clear();
                for &i in ic {
                    let i = i as usize * cin;
                    gx.extend_from_slice(&x[i..i + cin]);
                }
                for &o in oc {
                    let o = o as usize * cout;
                    gy.extend_from_slice(&dy[o..o + cout]);
                }
                // (first)^T (second), first has d0 columns, second has d2 columns.
                let (first, c0, second, c2) = if wv.transposed {
                    (&gx, cin, &gy, cout)
                } else {
                    (&gy, cout, &gx, cin)
                };
                unsafe {
                    F::gemm(
                        c0,
                        m,
                        c2,
                        first.as_ptr(),
                        1,
                        c0 as isize,
                        second.as_ptr(),
                        c2 as isize,
                        1,
                        F::one(),
                        acc.as_mut_ptr(),
                        c2 as isize,
                        1,
                    );
                }
            }
            acc
        })
        .collect();
    let mut dw = vec![F::zero(); wv.d0 * wv.k * wv.d2];
    for (k, acc) in per_k.into_iter().enumerate() {
        for a in 0..wv.d0 {
            dw[(a * wv.k + k) * wv.d2..][..wv.d2].copy_from_slice(&acc[a * wv.d2..][..wv.d2]);
        }
    }
    dw
}
