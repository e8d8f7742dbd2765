//! `conv3d_arrays` (the plain-array entry point of the Python package) against a brute-force loop
//! over output sites and kernel offsets, in f64, on shuffled (unsorted) input rows.

mod common;

use common::*;
use occ_sparse::arrays::{conv3d_arrays, ArrayConvKind, ArrayConvSpec};
use occ_sparse::{Coord, SparseError};
use rand::seq::SliceRandom;
use std::collections::{BTreeMap, HashMap};

/// Brute force: out[o] = sum over offsets k and inputs i with `o·s - p + k·d = i` (regular /
/// submanifold) or `i·s - p + k·d = o` (transposed) of W[k]ᵀ x[i]. Submanifold keeps the input sites.
fn brute_force(
    coords: &[Coord],
    feats: &[f64],
    cin: usize,
    w: &[f64],
    cout: usize,
    spec: &ArrayConvSpec,
) -> BTreeMap<Coord, Vec<f64>> {
    let k = spec.kernel;
    let out_shape: [i64; 3] = std::array::from_fn(|a| {
        let (n, k, s, p, d) = (
            spec.spatial_shape[a] as i64,
            k[a] as i64,
            spec.stride[a] as i64,
            spec.padding[a] as i64,
            spec.dilation[a] as i64,
        );
        match spec.kind {
            ArrayConvKind::Submanifold => n,
            ArrayConvKind::Regular => (n + 2 * p - d * (k - 1) - 1) / s + 1,
            ArrayConvKind::Transposed => (n - 1) * s - 2 * p + d * (k - 1) + 1,
        }
    });
    let index: HashMap<Coord, usize> = coords.iter().enumerate().map(|(i, &c)| (c, i)).collect();
    let mut out: BTreeMap<Coord, Vec<f64>> = BTreeMap::new();
    let mut add = |o: Coord, i: usize, kidx: usize| {
        let row = out.entry(o).or_insert_with(|| vec![0.0; cout]);
        for (co, r) in row.iter_mut().enumerate() {
            let wrow = &w[(co * k.iter().product::<usize>() + kidx) * cin..][..cin];
            *r += wrow
                .iter()
                .zip(&feats[i * cin..(i + 1) * cin])
                .map(|(a, b)| a * b)
                .sum::<f64>();
        }
    };
    for (i, &c) in coords.iter().enumerate() {
        for kx in 0..k[0] {
            for ky in 0..k[1] {
                for kz in 0..k[2] {
                    let kk = [kx, ky, kz];
                    let kidx = (kx * k[1] + ky) * k[2] + kz;
                    let mut o = [c[0]; 4];
                    let mut ok = true;
                    for a in 0..3 {
                        let (s, p, d) = (
                            spec.stride[a] as i64,
                            spec.padding[a] as i64,
                            spec.dilation[a] as i64,
                        );
                        let x = c[a + 1] as i64;
                        let v = match spec.kind {
                            // Submanifold: centred kernel, stride 1.
                            ArrayConvKind::Submanifold => {
                                let half = (k[a] as i64 / 2) * d;
                                x + half - kk[a] as i64 * d
                            }
                            ArrayConvKind::Regular => {
                                let t = x + p - kk[a] as i64 * d;
                                if t % s != 0 {
                                    ok = false;
                                }
                                t.div_euclid(s)
                            }
                            ArrayConvKind::Transposed => x * s - p + kk[a] as i64 * d,
                        };
                        ok &= (0..out_shape[a]).contains(&v);
                        o[a + 1] = v as i32;
                    }
                    if !ok {
                        continue;
                    }
                    if spec.kind == ArrayConvKind::Submanifold && !index.contains_key(&o) {
                        continue;
                    }
                    add(o, i, kidx);
                }
            }
        }
    }
    out
}

fn check(spec: ArrayConvSpec, n: usize, cin: usize, cout: usize, seed: u64) {
    check_order(spec, n, cin, cout, seed, true)
}

/// [`check`] with the input rows shuffled or in (b, x, y, z) order.
fn check_order(spec: ArrayConvSpec, n: usize, cin: usize, cout: usize, seed: u64, shuffle: bool) {
    let mut r = rng(seed);
    let batch = spec.batch_size.unwrap_or(2);
    let mut coords = random_coords(&mut r, spec.spatial_shape, batch, n);
    if shuffle {
        coords.shuffle(&mut r);
    } else {
        coords.sort_unstable();
    }
    let kv: usize = spec.kernel.iter().product();
    let feats = random_vec(&mut r, coords.len() * cin);
    let w = random_vec(&mut r, cout * kv * cin);
    let f32s = |v: &[f64]| v.iter().map(|&x| x as f32).collect::<Vec<_>>();
    // The reference sees the f32-rounded inputs.
    let (feats_r, w_r): (Vec<f64>, Vec<f64>) = (
        f32s(&feats).iter().map(|&x| x as f64).collect(),
        f32s(&w).iter().map(|&x| x as f64).collect(),
    );
    let want = brute_force(&coords, &feats_r, cin, &w_r, cout, &spec);
    let got = conv3d_arrays(coords.clone(), &f32s(&feats), cin, &f32s(&w), cout, &spec)
        .expect("conv3d_arrays");
    assert_eq!(got.c_out, cout);
    let sites: Vec<Coord> = want.keys().copied().collect();
    assert_eq!(got.coords, sites, "{spec:?}: output sites (sorted)");
    let mut worst = 0.0f64;
    for (row, (_, w)) in want.iter().enumerate() {
        for (co, &v) in w.iter().enumerate() {
            let g = got.feats[row * cout + co] as f64;
            worst = worst.max((g - v).abs() / (1.0 + v.abs()));
        }
    }
    assert!(worst < 1e-5, "{spec:?}: worst relative error {worst}");
}

fn spec(kind: ArrayConvKind, k: [usize; 3], s: [usize; 3], p: [usize; 3]) -> ArrayConvSpec {
    ArrayConvSpec {
        spatial_shape: [11, 9, 6],
        kernel: k,
        stride: s,
        padding: p,
        dilation: [1; 3],
        kind,
        batch_size: Some(2),
    }
}

#[test]
fn submanifold_matches_brute_force() {
    check(
        spec(ArrayConvKind::Submanifold, [3; 3], [1; 3], [0; 3]),
        150,
        5,
        7,
        1,
    );
    check(
        spec(ArrayConvKind::Submanifold, [3, 3, 1], [1; 3], [0; 3]),
        150,
        4,
        3,
        2,
    );
}

#[test]
fn regular_and_strided_match_brute_force() {
    check(
        spec(ArrayConvKind::Regular, [3; 3], [1; 3], [1; 3]),
        120,
        4,
        5,
        3,
    );
    check(
        spec(ArrayConvKind::Regular, [2; 3], [2; 3], [0; 3]),
        200,
        3,
        6,
        4,
    );
    check(
        spec(ArrayConvKind::Regular, [3; 3], [2; 3], [1, 1, 0]),
        200,
        6,
        2,
        5,
    );
    let mut dilated = spec(ArrayConvKind::Regular, [3; 3], [1; 3], [2; 3]);
    dilated.dilation = [2; 3];
    check(dilated, 100, 3, 3, 6);
}

/// Output widths of the fused f32 kernels (multiples of 16), on sparse grids (one or two pairs per
/// output: the output-major kernel) and a grid too large for a dense row table (the hash path),
/// with shuffled and sorted input rows.
#[test]
fn fused_widths_sparse_grids_and_sorted_inputs_match_brute_force() {
    let mut sparse = spec(ArrayConvKind::Regular, [3; 3], [1; 3], [1; 3]);
    sparse.spatial_shape = [40, 40, 12];
    let mut huge = spec(ArrayConvKind::Regular, [3; 3], [2; 3], [1; 3]);
    huge.spatial_shape = [600, 600, 20];
    let mut subm = spec(ArrayConvKind::Submanifold, [3; 3], [1; 3], [0; 3]);
    subm.spatial_shape = [40, 40, 12];
    for shuffle in [true, false] {
        check_order(sparse, 150, 8, 32, 21, shuffle);
        check_order(huge, 120, 5, 16, 22, shuffle);
        check_order(subm, 300, 16, 64, 23, shuffle);
    }
}

#[test]
fn transposed_matches_brute_force() {
    check(
        spec(ArrayConvKind::Transposed, [2; 3], [2; 3], [0; 3]),
        60,
        4,
        3,
        7,
    );
    check(
        spec(ArrayConvKind::Transposed, [3; 3], [2; 3], [1; 3]),
        60,
        3,
        4,
        8,
    );
}

#[test]
fn bad_arrays_are_errors_naming_the_problem() {
    let s = spec(ArrayConvKind::Submanifold, [3; 3], [1; 3], [0; 3]);
    let c = vec![[0, 1, 1, 1], [0, 2, 2, 2]];
    // Feature count.
    let e = conv3d_arrays(c.clone(), &[0.0; 5], 3, &[0.0; 27 * 3 * 2], 2, &s).unwrap_err();
    assert!(matches!(e, SparseError::Shape(_)), "{e}");
    // Weight length.
    let e = conv3d_arrays(c.clone(), &[0.0; 6], 3, &[0.0; 10], 2, &s).unwrap_err();
    assert!(matches!(e, SparseError::WeightLayout { .. }), "{e}");
    // A site outside the grid, a duplicate, a batch index past the batch size.
    for bad in [
        vec![[0, 11, 0, 0], [0, 0, 0, 0]],
        vec![[0, 1, 1, 1], [0, 1, 1, 1]],
        vec![[2, 1, 1, 1], [0, 0, 0, 0]],
        vec![[-1, 1, 1, 1], [0, 0, 0, 0]],
    ] {
        let e = conv3d_arrays(bad.clone(), &[0.0; 6], 3, &[0.0; 27 * 3 * 2], 2, &s);
        assert!(e.is_err(), "{bad:?} accepted");
    }
    // An even submanifold kernel.
    let even = spec(ArrayConvKind::Submanifold, [2; 3], [1; 3], [0; 3]);
    assert!(conv3d_arrays(c.clone(), &[0.0; 6], 3, &[0.0; 8 * 3 * 2], 2, &even).is_err());
    // Channel counts whose products wrap to the (empty) slices' lengths: 2 x 2^63 = 0 mod 2^64.
    let e = conv3d_arrays(c.clone(), &[], 1 << 63, &[], 2, &s).unwrap_err();
    assert!(matches!(e, SparseError::Shape(_)), "{e}");
    let e = conv3d_arrays(c, &[0.0; 6], 3, &[], 1 << 63, &s).unwrap_err();
    assert!(matches!(e, SparseError::WeightLayout { .. }), "{e}");
}
