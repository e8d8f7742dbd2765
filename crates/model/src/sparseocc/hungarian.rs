//! Hungarian (Kuhn-Munkres) assignment for the bipartite matching of the sparse transformer head
//! (paper Sec. 3.5, docs/reference_models.md §1 "matching": the official code calls scipy's
//! `linear_sum_assignment`).
//!
//! Shortest-augmenting-path formulation with row/column potentials, O(n²·m) for an `n x m` cost
//! matrix with `n <= m` (O(n³) when square). Rectangular matrices are allowed: every row of the
//! smaller side is assigned to a distinct column of the larger side, minimising the total cost.

use crate::error::ModelError;

/// Minimum-cost assignment on a row-major `rows x cols` cost matrix.
///
/// Returns `min(rows, cols)` pairs `(row, col)`, sorted by row, with distinct rows and distinct
/// columns, whose total cost is minimal. An empty matrix gives an empty assignment.
///
/// Errors: `cost.len() != rows * cols`, or a non-finite cost (NaN or infinite).
pub fn hungarian(
    cost: &[f64],
    rows: usize,
    cols: usize,
) -> Result<Vec<(usize, usize)>, ModelError> {
    if cost.len() != rows * cols {
        return Err(ModelError::Input(format!(
            "hungarian.rs: cost matrix has {} entries, expected {rows} x {cols}",
            cost.len()
        )));
    }
    if let Some(i) = cost.iter().position(|c| !c.is_finite()) {
        return Err(ModelError::Numerical(format!(
            "hungarian.rs: cost[{}, {}] = {} is not finite",
            i / cols.max(1),
            i % cols.max(1),
            cost[i]
        )));
    }
    if rows == 0 || cols == 0 {
        return Ok(Vec::new());
    }
    if rows <= cols {
        Ok(solve(|i, j| cost[i * cols + j], rows, cols))
    } else {
        // Transpose: assign every column to a row.
        let mut pairs: Vec<(usize, usize)> = solve(|i, j| cost[j * cols + i], cols, rows)
            .into_iter()
            .map(|(c, r)| (r, c))
            .collect();
        pairs.sort_unstable();
        Ok(pairs)
    }
}

/// Core solver for `n <= m` (1-based potentials `u`, `v`, column owner `p`).
fn solve(a: impl Fn(usize, usize) -> f64, n: usize, m: usize) -> Vec<(usize, usize)> {
    let inf = f64::INFINITY;
    let mut u = vec![0.0f64; n + 1];
    let mut v = vec![0.0f64; m + 1];
    // p[j] = row (1-based) assigned to column j (1-based); p[0] is the row being inserted.
    let mut p = vec![0usize; m + 1];
    let mut way = vec![0usize; m + 1];
    for i in 1..=n {
        p[0] = i;
        let mut j0 = 0usize;
        let mut minv = vec![inf; m + 1];
        let mut used = vec![false; m + 1];
        loop {
            used[j0] = true;
            let i0 = p[j0];
            let mut delta = inf;
            let mut j1 = 0usize;
            for j in 1..=m {
                if !used[j] {
                    let cur = a(i0 - 1, j - 1) - u[i0] - v[j];
                    if cur < minv[j] {
                        minv[j] = cur;
                        way[j] = j0;
                    }
                    if minv[j] < delta {
                        delta = minv[j];
                        j1 = j;
                    }
                }
            }
            for j in 0..=m {
                if used[j] {
                    u[p[j]] += delta;
                    v[j] -= delta;
                } else {
                    minv[j] -= delta;
                }
            }
            j0 = j1;
            if p[j0] == 0 {
                break;
            }
        }
        // Augment along the alternating path.
        loop {
            let j1 = way[j0];
            p[j0] = p[j1];
            j0 = j1;
            if j0 == 0 {
                break;
            }
        }
    }
    let mut pairs: Vec<(usize, usize)> = (1..=m)
        .filter(|&j| p[j] != 0)
        .map(|j| (p[j] - 1, j - 1))
        .collect();
    pairs.sort_unstable();
    pairs
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn textbook_square() {
        // Classic 3x3 example: optimum 5 (0->1, 1->0, 2->2).
        let c = [4.0, 1.0, 3.0, 2.0, 0.0, 5.0, 3.0, 2.0, 2.0];
        let a = hungarian(&c, 3, 3).unwrap();
        let total: f64 = a.iter().map(|&(i, j)| c[i * 3 + j]).sum();
        assert_eq!(total, 5.0);
        assert_eq!(a, vec![(0, 1), (1, 0), (2, 2)]);
    }

    #[test]
    fn rejects_bad_input() {
        assert!(hungarian(&[1.0, 2.0], 2, 2).is_err());
        assert!(hungarian(&[1.0, f64::NAN], 1, 2).is_err());
        assert!(hungarian(&[], 0, 3).unwrap().is_empty());
    }
}
