//! Fused gather → multiply → scatter-add for one kernel offset, f32 on x86-64 with AVX2 + FMA.
//!
//! The blocked path of [`crate::host::conv_forward`] copies the input rows of each offset's pairs into
//! a buffer, multiplies it with a GEMM, and adds the product rows into the output block: two
//! extra passes over `pairs × C` values and GEMM calls of a few dozen rows each. Here a register
//! tile of 4 pairs × 16 output channels is accumulated straight from the input rows (read in place
//! through the pair indices) against the offset's weight slice packed `[C_in, C_out]` (16 KB at
//! C = 64, resident in L1), and added into the 4 output rows: no buffers, one pass.
//!
//! Used for f32 when the CPU has AVX2 and FMA (checked at run time), `C_out` is a multiple of 16 and
//! the weight slice fits the L1 cache ([`available`]); otherwise the blocked GEMM path runs. Both
//! compute the same sums (in a different order).

use crate::host::{OffsetPairs, OutputRows};
use std::mem::MaybeUninit;

/// Weight slices packed per kernel offset as `[K][C_in][C_out]` (row-major over `C_out`).
pub(crate) fn pack_weight(w: &[f32], wv: crate::host::WeightView) -> Vec<f32> {
    let (cin, cout) = (wv.cin(), wv.cout());
    let mut packed = vec![0.0f32; wv.k * cin * cout];
    for k in 0..wv.k {
        let (base, rs, cs) = wv.slice(k);
        for c in 0..cin {
            for o in 0..cout {
                packed[(k * cin + c) * cout + o] =
                    w[(base as isize + c as isize * rs + o as isize * cs) as usize];
            }
        }
    }
    packed
}

/// Largest weight slice `C_in × C_out` (f32 values) the fused kernel takes: 32 KB, one L1 data cache.
/// Measured on the 52,774-voxel benchmark input (submanifold 3x3x3, 2 threads, fused vs GEMM path):
/// C = 32 54 vs 47 GFLOP/s, C = 64 70 vs 59, C = 96 62 vs 72, C = 128 73 vs 74, C = 256 54 vs 70 —
/// past the L1 the GEMM path's packing wins.
const MAX_SLICE: usize = 8 * 1024;

/// Whether [`pairs_into_block`] is used for these widths on this CPU.
pub(crate) fn available(cin: usize, cout: usize) -> bool {
    #[cfg(target_arch = "x86_64")]
    {
        cin > 0
            && cout > 0
            && cin * cout <= MAX_SLICE
            && cout.is_multiple_of(16)
            && std::arch::is_x86_feature_detected!("avx2")
            && std::arch::is_x86_feature_detected!("fma")
    }
    #[cfg(not(target_arch = "x86_64"))]
    {
        let _ = (cin, cout);
        false
    }
}

/// `y[o - o0] += x[i] · wk` for every pair `(i, o)` of the offset.
///
/// # Safety
/// [`available`]`(cin, cout)` must hold; the slices as documented on [`OffsetPairs`].
pub(crate) unsafe fn pairs_into_block(pairs: &OffsetPairs<'_, f32>, yblock: &mut [f32]) {
    #[cfg(target_arch = "x86_64")]
    // SAFETY: the caller checked the CPU features through `available`.
    unsafe {
        pairs_avx2::<4, 16>(pairs, yblock)
    }
    #[cfg(not(target_arch = "x86_64"))]
    {
        let _ = (pairs, yblock);
        unreachable!("fused::available is false off x86-64")
    }
}

/// `R` pairs × `T` output channels per register tile: 8 accumulator vectors; 4 × 16 measured faster
/// than 2 × 32, 3 × 32 (equal), 6 × 16 and 4 × 32 (register spills) on the C = 64 benchmark case.
#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx2,fma")]
unsafe fn pairs_avx2<const R: usize, const T: usize>(
    pairs: &OffsetPairs<'_, f32>,
    yblock: &mut [f32],
) {
    let OffsetPairs {
        x,
        cin,
        wk,
        cout,
        ins,
        outs,
        o0,
    } = *pairs;
    let m = ins.len().min(outs.len());
    let row = |i: u32| &x[i as usize * cin..(i as usize + 1) * cin];
    let mut p = 0;
    while p + R <= m {
        let xr: [&[f32]; R] = std::array::from_fn(|r| row(ins[p + r]));
        for ct in (0..cout).step_by(T) {
            let mut acc = [[0.0f32; T]; R];
            for c in 0..cin {
                let wrow: &[f32; T] = wk[c * cout + ct..c * cout + ct + T]
                    .try_into()
                    .expect("tile of T");
                for r in 0..R {
                    let xv = xr[r][c];
                    for j in 0..T {
                        acc[r][j] = xv.mul_add(wrow[j], acc[r][j]);
                    }
                }
            }
            for r in 0..R {
                let o = (outs[p + r] - o0) as usize * cout + ct;
                let dst: &mut [f32; T] = (&mut yblock[o..o + T]).try_into().expect("tile of T");
                for j in 0..T {
                    dst[j] += acc[r][j];
                }
            }
        }
        p += R;
    }
    while p < m {
        let xr = row(ins[p]);
        for ct in (0..cout).step_by(T) {
            let mut acc = [0.0f32; T];
            for (c, &xv) in xr.iter().enumerate() {
                let wrow: &[f32; T] = wk[c * cout + ct..c * cout + ct + T]
                    .try_into()
                    .expect("tile of T");
                for j in 0..T {
                    acc[j] = xv.mul_add(wrow[j], acc[j]);
                }
            }
            let o = (outs[p] - o0) as usize * cout + ct;
            let dst: &mut [f32; T] = (&mut yblock[o..o + T]).try_into().expect("tile of T");
            for j in 0..T {
                dst[j] += acc[j];
            }
        }
        p += 1;
    }
}

/// `y[o] = Σ x[i] · w_k` over the pairs `(i, k)` of each output row `o` of one block, output-major:
/// each row is summed in registers and written once (zeros where a row has no pair), so the output
/// needs no zeroing and no read-modify-write per pair (see [`crate::host::conv_forward`]).
///
/// # Safety
/// [`available`]`(cin, cout)` must hold; the slices as documented on [`OutputRows`].
pub(crate) unsafe fn rows_by_output(job: &OutputRows<'_, f32>, yblock: &mut [MaybeUninit<f32>]) {
    #[cfg(target_arch = "x86_64")]
    // SAFETY: the caller checked the CPU features through `available`; `cout` is a multiple of 16.
    unsafe {
        if job.cout.is_multiple_of(64) {
            rows_avx2::<64, 1>(job, yblock)
        } else if job.cout.is_multiple_of(32) {
            rows_avx2::<32, 2>(job, yblock)
        } else {
            rows_avx2::<16, 4>(job, yblock)
        }
    }
    #[cfg(not(target_arch = "x86_64"))]
    {
        let _ = (job, yblock);
        unreachable!("fused::available is false off x86-64")
    }
}

/// `T` output channels per tile, the input channels split `U` ways: `T / 8 · U` = 8 independent
/// accumulator vectors, enough to hide the FMA latency at every tile width.
#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx2,fma")]
unsafe fn rows_avx2<const T: usize, const U: usize>(
    job: &OutputRows<'_, f32>,
    yblock: &mut [MaybeUninit<f32>],
) {
    let OutputRows {
        x,
        cin,
        packed,
        cout,
        pairs,
        o0,
    } = *job;
    let rows = yblock.len() / cout;
    for r in 0..rows {
        let o = o0 + r;
        let (s, e) = (pairs.start[o] as usize, pairs.start[o + 1] as usize);
        for ct in (0..cout).step_by(T) {
            let mut tot = [0.0f32; T];
            for p in s..e {
                let i = pairs.ins[p] as usize;
                let xr = &x[i * cin..(i + 1) * cin];
                let wk = &packed[pairs.offsets[p] as usize * cin * cout..][..cin * cout];
                let mut acc = [[0.0f32; T]; U];
                let mut c = 0;
                while c + U <= cin {
                    for (u, acc) in acc.iter_mut().enumerate() {
                        let xv = xr[c + u];
                        let w: &[f32; T] = wk[(c + u) * cout + ct..][..T]
                            .try_into()
                            .expect("tile of T");
                        for j in 0..T {
                            acc[j] = xv.mul_add(w[j], acc[j]);
                        }
                    }
                    c += U;
                }
                while c < cin {
                    let xv = xr[c];
                    let w: &[f32; T] = wk[c * cout + ct..][..T].try_into().expect("tile of T");
                    for j in 0..T {
                        acc[0][j] = xv.mul_add(w[j], acc[0][j]);
                    }
                    c += 1;
                }
                for a in &acc {
                    for j in 0..T {
                        tot[j] += a[j];
                    }
                }
            }
            for (d, v) in yblock[r * cout + ct..][..T].iter_mut().zip(tot) {
                d.write(v);
            }
        }
    }
}
