//! Row-wise layers as host loops for inference on burn-ndarray: a linear layer (bias and optional
//! ReLU fused into the GEMM's output), layer normalisation and softmax over the last axis.
//!
//! burn composes these from whole-tensor ops: `matmul` then a broadcast bias add; LayerNorm as
//! mean, subtract, square, mean, add, sqrt, divide, multiply, add; softmax as max, subtract, exp,
//! sum, divide. On the CPU every op is a pass over the whole `[N, D]` tensor with a fresh output
//! buffer, so on SparseOcc++'s 83k-voxel DCA blocks these layers took several times what their
//! arithmetic needs (BENCHMARKS.md, "row-wise host kernels"). Here each row is read once, kept in
//! cache, and written once; rows run in parallel blocks.
//!
//! They compute what burn's layers compute (biased variance, `epsilon` added before the square root;
//! softmax shifted by the row maximum), with the row statistics accumulated in f64; the tests in
//! this file compare them with burn's `Linear`, `LayerNorm` and `softmax`.

use crate::kernels::host_data::{with_host_slice, Elem, NdElem};
use burn::backend::ndarray::{NdArrayTensor, SharedArray};
use burn::backend::NdArray;
use burn::nn::{LayerNorm, Linear};
use burn::tensor::{Tensor, TensorData};
use rayon::prelude::*;

/// Rows per parallel block of [`linear_rows`]: enough rows that the GEMM's packing of the weight
/// (at most `d_in · d_out` values) is small next to its work, and that each thread gets several
/// blocks.
const LINEAR_BLOCK_ROWS: usize = 512;

/// Rows per parallel block of the normalisations.
const NORM_BLOCK_ROWS: usize = 256;

/// `relu?(x · w + b)`: `x [rows, d_in]`, `w [d_in, d_out]` (burn's `Linear` layout), `b [d_out]`.
pub(crate) fn linear_rows<T: Elem>(
    x: &[T],
    d_in: usize,
    w: &[T],
    d_out: usize,
    b: Option<&[T]>,
    relu: bool,
) -> Vec<T> {
    let rows = x.len().checked_div(d_in).unwrap_or(0);
    let mut y = vec![T::zero(); rows * d_out];
    if rows == 0 || d_out == 0 {
        return y;
    }
    y.par_chunks_mut(LINEAR_BLOCK_ROWS * d_out)
        .enumerate()
        .for_each(|(bi, yb)| {
            let r = yb.len() / d_out;
            let xb = &x[bi * LINEAR_BLOCK_ROWS * d_in..][..r * d_in];
            let beta = match b {
                Some(b) => {
                    for row in yb.chunks_exact_mut(d_out) {
                        row.copy_from_slice(b);
                    }
                    T::one()
                }
                None => T::zero(),
            };
            if d_in > 0 {
                // SAFETY: xb is r x d_in, w is d_in x d_out, yb is r x d_out, all row-major.
                unsafe {
                    T::gemm(
                        r,
                        d_in,
                        d_out,
                        xb.as_ptr(),
                        d_in as isize,
                        1,
                        w.as_ptr(),
                        d_out as isize,
                        1,
                        beta,
                        yb.as_mut_ptr(),
                        d_out as isize,
                        1,
                    );
                }
            }
            if relu {
                for v in yb.iter_mut() {
                    if *v < T::zero() {
                        *v = T::zero();
                    }
                }
            }
        });
    y
}

/// `y [rows, d]` with `f(x_row, y_row)` run on every row of `x [rows, d]`, in parallel blocks.
fn map_rows<T: Elem>(x: &[T], d: usize, f: impl Fn(&[T], &mut [T]) + Sync) -> Vec<T> {
    let mut y = vec![T::zero(); x.len()];
    if d == 0 {
        return y;
    }
    y.par_chunks_mut(NORM_BLOCK_ROWS * d)
        .zip(x.par_chunks(NORM_BLOCK_ROWS * d))
        .for_each(|(yb, xb)| {
            for (yr, xr) in yb.chunks_exact_mut(d).zip(xb.chunks_exact(d)) {
                f(xr, yr);
            }
        });
    y
}

/// Layer normalisation of every row of `x [rows, d]`: `(x - mean) / sqrt(var + eps) · gamma + beta`
/// with the biased variance, as burn's `LayerNorm`.
pub(crate) fn layer_norm_rows<T: Elem>(
    x: &[T],
    d: usize,
    gamma: &[T],
    beta: Option<&[T]>,
    eps: f64,
) -> Vec<T> {
    map_rows(x, d, |xr, yr| {
        let mean = xr.iter().map(|v| v.to_f64()).sum::<f64>() / d as f64;
        let var = xr
            .iter()
            .map(|v| {
                let c = v.to_f64() - mean;
                c * c
            })
            .sum::<f64>()
            / d as f64;
        let inv = 1.0 / (var + eps).sqrt();
        // (v - mean) · inv as v · inv + (-mean · inv)
        let (inv_t, shift_t) = (T::from_f64(inv), T::from_f64(-mean * inv));
        for (j, (o, &v)) in yr.iter_mut().zip(xr).enumerate() {
            let n = (v * inv_t + shift_t) * gamma[j];
            *o = match beta {
                Some(b) => n + b[j],
                None => n,
            };
        }
    })
}

/// Softmax over every row of `x [rows, d]`, shifted by the row maximum (as burn's `softmax`).
pub(crate) fn softmax_rows<T: Elem>(x: &[T], d: usize) -> Vec<T> {
    map_rows(x, d, |xr, yr| {
        let max = xr
            .iter()
            .map(|v| v.to_f64())
            .fold(f64::NEG_INFINITY, f64::max);
        let mut sum = 0.0f64;
        for (o, v) in yr.iter_mut().zip(xr) {
            let e = (v.to_f64() - max).exp();
            sum += e;
            *o = T::from_f64(e);
        }
        let inv = T::from_f64(1.0 / sum);
        for o in yr.iter_mut() {
            *o = *o * inv;
        }
    })
}

/// [`linear_rows`] on burn-ndarray tensors: `relu?(lin.forward(x))` for `x [..., d_in]`; `None`
/// where the tensors do not hold `T` (then the caller runs burn's layer).
pub(crate) fn linear_host<T: NdElem, const D: usize>(
    lin: &Linear<NdArray<T>>,
    x: &Tensor<NdArray<T>, D>,
    relu: bool,
) -> Option<Tensor<NdArray<T>, D>>
where
    NdArrayTensor: From<SharedArray<T>>,
{
    let [d_in, d_out] = lin.weight.dims();
    let mut dims = x.dims();
    if dims[D - 1] != d_in {
        return None;
    }
    let w = lin.weight.val();
    let b = lin.bias.as_ref().map(|b| b.val());
    let y = with_host_slice(x, |xs| {
        with_host_slice(&w, |ws| match &b {
            Some(b) => with_host_slice(b, |bs| linear_rows(xs, d_in, ws, d_out, Some(bs), relu)),
            None => Some(linear_rows(xs, d_in, ws, d_out, None, relu)),
        })
    })???;
    dims[D - 1] = d_out;
    Some(Tensor::from_data(TensorData::new(y, dims), &x.device()))
}

/// [`layer_norm_rows`] on burn-ndarray tensors, over the last axis; `None` as [`linear_host`].
pub(crate) fn layer_norm_host<T: NdElem, const D: usize>(
    ln: &LayerNorm<NdArray<T>>,
    x: &Tensor<NdArray<T>, D>,
    eps: f64,
) -> Option<Tensor<NdArray<T>, D>>
where
    NdArrayTensor: From<SharedArray<T>>,
{
    let dims = x.dims();
    let d = dims[D - 1];
    let gamma = ln.gamma.val();
    if gamma.dims()[0] != d {
        return None;
    }
    let beta = ln.beta.as_ref().map(|b| b.val());
    let y = with_host_slice(x, |xs| {
        with_host_slice(&gamma, |gs| match &beta {
            Some(b) => with_host_slice(b, |bs| layer_norm_rows(xs, d, gs, Some(bs), eps)),
            None => Some(layer_norm_rows(xs, d, gs, None, eps)),
        })
    })???;
    Some(Tensor::from_data(TensorData::new(y, dims), &x.device()))
}

/// [`softmax_rows`] on a burn-ndarray tensor, over the last axis; `None` as [`linear_host`].
pub(crate) fn softmax_host<T: NdElem, const D: usize>(
    x: &Tensor<NdArray<T>, D>,
) -> Option<Tensor<NdArray<T>, D>>
where
    NdArrayTensor: From<SharedArray<T>>,
{
    let dims = x.dims();
    let y = with_host_slice(x, |xs| softmax_rows(xs, dims[D - 1]))?;
    Some(Tensor::from_data(TensorData::new(y, dims), &x.device()))
}

#[cfg(test)]
mod tests {
    use super::*;
    use burn::nn::{LayerNormConfig, LinearConfig};
    use burn::tensor::activation::{relu, softmax};
    use burn::tensor::Distribution;

    type B = NdArray<f32>;

    fn max_abs_diff<const D: usize>(a: Tensor<B, D>, b: Tensor<B, D>) -> f32 {
        assert_eq!(a.dims(), b.dims());
        (a - b).abs().max().into_scalar()
    }

    fn input(rows: usize, d: usize, seed: u64) -> Tensor<B, 2> {
        let dev = Default::default();
        <B as burn::tensor::backend::Backend>::seed(&dev, seed);
        Tensor::random([rows, d], Distribution::Normal(0.3, 2.0), &dev)
    }

    #[test]
    fn linear_matches_burn_with_and_without_bias_and_relu() {
        let dev = Default::default();
        // 1,100 rows: more than two blocks, the last one partial
        let x = input(1100, 24, 1);
        for bias in [true, false] {
            let lin = LinearConfig::new(24, 40).with_bias(bias).init::<B>(&dev);
            for r in [false, true] {
                let want = if r {
                    relu(lin.forward(x.clone()))
                } else {
                    lin.forward(x.clone())
                };
                let got = linear_host(&lin, &x, r).expect("f32 tensors");
                assert!(max_abs_diff(got, want) < 1e-5, "bias {bias} relu {r}");
            }
        }
        // a rank-3 input: rows are everything but the last axis
        let lin = LinearConfig::new(24, 8).init::<B>(&dev);
        let x3 = input(60, 24, 2).reshape([5, 12, 24]);
        let got = linear_host(&lin, &x3, false).expect("f32 tensors");
        assert!(max_abs_diff(got, lin.forward(x3)) < 1e-5);
    }

    #[test]
    fn layer_norm_matches_burn() {
        let dev = Default::default();
        let x = input(700, 128, 3);
        for bias in [true, false] {
            let mut ln = LayerNormConfig::new(128).with_bias(bias).init::<B>(&dev);
            // non-trivial scale and shift
            ln.gamma = ln.gamma.map(|g| g.mul_scalar(1.5).add_scalar(0.25));
            if let Some(b) = ln.beta.take() {
                ln.beta = Some(b.map(|b| b.add_scalar(-0.75)));
            }
            let got = layer_norm_host(&ln, &x, 1e-5).expect("f32 tensors");
            assert!(
                max_abs_diff(got, ln.forward(x.clone())) < 1e-5,
                "bias {bias}"
            );
        }
        // a constant row: variance 0, output beta
        let ln = LayerNormConfig::new(4).init::<B>(&dev);
        let c = Tensor::<B, 2>::from_floats([[2.0, 2.0, 2.0, 2.0]], &dev);
        let got = layer_norm_host(&ln, &c, 1e-5).expect("f32 tensors");
        assert!(max_abs_diff(got, ln.forward(c)) < 1e-6);
    }

    #[test]
    fn softmax_matches_burn_over_the_last_axis() {
        // large logits: the shift by the row maximum keeps exp finite
        let x = input(500, 12, 4).mul_scalar(40.0).reshape([250, 2, 12]);
        let got = softmax_host(&x).expect("f32 tensors");
        assert!(max_abs_diff(got.clone(), softmax(x, 2)) < 1e-6);
        let sums = got.sum_dim(2);
        assert!(max_abs_diff(sums.clone(), sums.ones_like()) < 1e-5);
    }
}
