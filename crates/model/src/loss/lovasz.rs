//! Lovasz-softmax loss (Berman et al. 2018; docs/losses.md §3), `classes='present'`, `per_image=False`.

use super::{check_labels, host_tensor, select_rows, to_host, valid_rows, zero_loss};
use crate::error::ModelError;
use burn::prelude::*;
use rayon::prelude::*;

/// Gradient of the Lovasz extension of the Jaccard loss for binary ground truth `fg_sorted`
/// (sorted by decreasing error): with `G = Σ fg`, `inter = G − cumsum(fg)`,
/// `union = G + cumsum(1 − fg)`, `J = 1 − inter/union`, the result is `[J0, J1 − J0, …]`.
pub fn lovasz_grad(fg_sorted: &[f64]) -> Vec<f64> {
    let g_total: f64 = fg_sorted.iter().sum();
    let mut out = Vec::with_capacity(fg_sorted.len());
    let (mut cum_fg, mut cum_bg, mut prev) = (0.0, 0.0, 0.0);
    for &f in fg_sorted {
        cum_fg += f;
        cum_bg += 1.0 - f;
        let inter = g_total - cum_fg;
        let union = g_total + cum_bg;
        // union >= 1 after the first element unless everything is empty (then J = 0).
        let j = if union > 0.0 {
            1.0 - inter / union
        } else {
            0.0
        };
        out.push(j - prev);
        prev = j;
    }
    out
}

/// Lovasz-softmax on class probabilities `probs` `[N, C]` (softmax output) with labels (one class
/// index `< C` or `ignore` per row); docs/losses.md §3.
///
/// For every class `c` present among the non-ignored labels: `fg = (y == c)`,
/// `e = |fg − p_c|`, sorted by decreasing `e`; `loss_c = e_sorted · lovasz_grad(fg_sorted)`.
/// The result is the mean of `loss_c` over the present classes (0 when no row is left).
///
/// Implementation: the sort order is computed on the host (stable sort of the errors read back
/// once), and `lovasz_grad` is scattered back to the unsorted rows as a constant weight matrix `W`
/// `[N, C]`, so that `loss = Σ |F − P| ⊙ W / #present` on the device. This is the same function
/// and the same gradient as gathering `e` in sorted order (the Lovasz gradient is a constant in
/// the reference too); the gradient flows through `p`.
pub fn lovasz_softmax<B: Backend>(
    probs: Tensor<B, 2>,
    labels: &[u8],
    ignore: u8,
) -> Result<Tensor<B, 1>, ModelError> {
    check_labels(&probs, labels, ignore, "lovasz_softmax")?;
    let (rows, ys) = valid_rows(labels, ignore);
    if rows.is_empty() {
        return Ok(zero_loss(probs));
    }
    let [_, c] = probs.dims();
    let n = rows.len();
    let p = select_rows(probs, &rows);
    let p_host = to_host(p.clone(), "lovasz_softmax")?;
    if p_host.len() != n * c {
        return Err(ModelError::Numerical(format!(
            "lovasz_softmax: read {} values for [{n}, {c}]",
            p_host.len()
        )));
    }
    let mut present = vec![false; c];
    for &y in &ys {
        present[y as usize] = true;
    }
    let classes: Vec<usize> = (0..c).filter(|&k| present[k]).collect();
    // Per present class: the Lovasz gradient placed at the original row of each sorted element.
    let columns: Vec<(usize, Vec<f64>)> = classes
        .par_iter()
        .map(|&k| {
            let fg: Vec<f64> = ys
                .iter()
                .map(|&y| if y as usize == k { 1.0 } else { 0.0 })
                .collect();
            let err: Vec<f64> = (0..n).map(|i| (fg[i] - p_host[i * c + k]).abs()).collect();
            let mut order: Vec<usize> = (0..n).collect();
            order.sort_by(|&a, &b| err[b].total_cmp(&err[a]));
            let fg_sorted: Vec<f64> = order.iter().map(|&i| fg[i]).collect();
            let g = lovasz_grad(&fg_sorted);
            let mut col = vec![0.0; n];
            for (&i, gk) in order.iter().zip(g) {
                col[i] = gk;
            }
            (k, col)
        })
        .collect();
    let mut w = vec![0.0; n * c];
    for (k, col) in &columns {
        for (i, v) in col.iter().enumerate() {
            w[i * c + k] = *v;
        }
    }
    let mut onehot = vec![0.0; n * c];
    for (i, &y) in ys.iter().enumerate() {
        onehot[i * c + y as usize] = 1.0;
    }
    let w = host_tensor(w, [n, c], &p);
    let fg = host_tensor(onehot, [n, c], &p);
    let err = (fg - p).abs();
    Ok((err * w).sum().mul_scalar(1.0 / classes.len() as f64))
}
