//! Kernel-map properties, finite-difference gradient checks, host vs portable compute paths, pooling
//! gradients, structural ops and error handling.

mod common;

use burn::backend::NdArray;
use burn::prelude::*;
use burn::tensor::TensorData;
use common::*;
use occ_sparse::backend::{
    conv_forward_per_offset, conv_forward_portable, conv_forward_portable_chunked,
    conv_weight_grad_per_offset, conv_weight_grad_portable, conv_weight_grad_portable_chunked,
    RowBucket,
};
use occ_sparse::conv::sparse_conv3d;
use occ_sparse::kernel_map::{
    build_regular, build_submanifold, conv_map, inverse_of, KernelMap, MapKind,
};
use occ_sparse::{
    host, ops, ConvGeometry, ConvKind, CoordSet, SparseConv3dConfig, SparseError,
    SparseMaxPool3dConfig, SparseTensor,
};
use std::sync::Arc;

#[test]
fn submanifold_neighbour_counts_match_brute_force() {
    let mut r = rng(1);
    let coords = random_coords(&mut r, [12, 10, 6], 2, 300);
    let set = CoordSet::new(coords.clone(), [12, 10, 6], 2).unwrap();
    for k in [[3, 3, 3], [5, 5, 1], [3, 1, 3]] {
        let map = build_submanifold(&set, k, [1; 3]).unwrap();
        let counts = map.neighbour_counts();
        let lookup: std::collections::HashSet<_> = coords.iter().copied().collect();
        for (o, c) in coords.iter().enumerate() {
            let mut n = 0;
            for dx in -(k[0] as i32 / 2)..=(k[0] as i32 / 2) {
                for dy in -(k[1] as i32 / 2)..=(k[1] as i32 / 2) {
                    for dz in -(k[2] as i32 / 2)..=(k[2] as i32 / 2) {
                        if lookup.contains(&[c[0], c[1] + dx, c[2] + dy, c[3] + dz]) {
                            n += 1;
                        }
                    }
                }
            }
            assert_eq!(counts[o], n, "site {c:?} kernel {k:?}");
        }
        // Centre offset pairs every site with itself.
        let centre = map.kernel_volume() / 2;
        let (ins, outs) = map.pairs(centre);
        assert_eq!(ins, outs);
        assert_eq!(ins.len(), coords.len());
        // Symmetry: offset k and its mirror K-1-k are transposes of each other.
        for kk in 0..map.kernel_volume() {
            let (a_in, a_out) = map.pairs(kk);
            let (b_in, b_out) = map.pairs(map.kernel_volume() - 1 - kk);
            let mut a: Vec<_> = a_in.iter().zip(a_out).map(|(&i, &o)| (o, i)).collect();
            let mut b: Vec<_> = b_in.iter().zip(b_out).map(|(&i, &o)| (i, o)).collect();
            a.sort();
            b.sort();
            assert_eq!(a, b);
        }
    }
}

#[test]
fn inverse_map_is_transpose_of_strided_map() {
    let mut r = rng(2);
    let coords = random_coords(&mut r, [16, 16, 8], 2, 400);
    let set = Arc::new(CoordSet::new(coords, [16, 16, 8], 2).unwrap());
    let g = ConvGeometry::new([3, 3, 3])
        .with_stride([2; 3])
        .with_padding([1; 3]);
    let (down, map) = conv_map(&set, MapKind::Regular, g).unwrap();
    assert_eq!(down.tensor_stride(), [2, 2, 2]);
    let (parent, inv) = inverse_of(&down, g).unwrap();
    assert!(Arc::ptr_eq(&parent, &set));
    assert_eq!((inv.n_in(), inv.n_out()), (map.n_out(), map.n_in()));
    for k in 0..map.kernel_volume() {
        let (i1, o1) = map.pairs(k);
        let (i2, o2) = inv.pairs(k);
        let mut a: Vec<_> = i1.iter().zip(o1).map(|(&i, &o)| (i, o)).collect();
        let mut b: Vec<_> = i2.iter().zip(o2).map(|(&i, &o)| (o, i)).collect();
        a.sort();
        b.sort();
        assert_eq!(a, b, "offset {k}");
        assert!(o2.windows(2).all(|w| w[0] <= w[1]), "sorted by output");
    }
    // The cache returns the same map and output set for the same typed key.
    let (down2, map2) = conv_map(&set, MapKind::Regular, g).unwrap();
    assert!(Arc::ptr_eq(&down, &down2) && Arc::ptr_eq(&map, &map2));
    // A different geometry has no inverse link.
    let g2 = ConvGeometry::new([2, 2, 2]).with_stride([2; 3]);
    assert!(matches!(
        inverse_of(&down, g2),
        Err(SparseError::NoInverseMap(_))
    ));
    // Every strided output is reached by at least one input, each input by at most 27 outputs.
    assert!(map
        .neighbour_counts()
        .iter()
        .all(|&c| (1..=27).contains(&c)));
    let (coords2, _, map3) = build_regular(&set, &g).unwrap();
    assert_eq!(coords2, down.coords());
    assert_eq!(map3.num_pairs(), map.num_pairs());
}

/// Central differences (step 1e-6) of `f` at every `every`-th entry of `v` against the analytic
/// gradient `grad`, to 1e-7.
fn check_central_differences(
    what: &str,
    v: &[f64],
    every: usize,
    grad: &[f64],
    f: &dyn Fn(&[f64]) -> f64,
) {
    let h = 1e-6;
    for i in (0..v.len()).step_by(every) {
        let (mut a, mut b) = (v.to_vec(), v.to_vec());
        a[i] += h;
        b[i] -= h;
        let fd = (f(&a) - f(&b)) / (2.0 * h);
        assert!(
            (fd - grad[i]).abs() < 1e-7,
            "{what}[{i}]: fd {fd} vs {}",
            grad[i]
        );
    }
}

/// Central finite differences of the host path (f64) for input features and weights.
#[test]
fn finite_difference_gradients() {
    type Inner = NdArray<f64>;
    let mut r = rng(3);
    let shape = [6, 6, 4];
    let coords = random_coords(&mut r, shape, 1, 40);
    let n = coords.len();
    let (cin, cout) = (2, 3);
    for (kind, g) in [
        (ConvKind::Submanifold, ConvGeometry::new([3, 3, 3])),
        (
            ConvKind::Regular,
            ConvGeometry::new([3, 3, 1])
                .with_stride([2, 2, 1])
                .with_padding([1, 1, 0]),
        ),
        (
            ConvKind::Transposed,
            ConvGeometry::new([2, 2, 2]).with_stride([2; 3]),
        ),
    ] {
        let k = g.kernel;
        let kv = k[0] * k[1] * k[2];
        let xv = random_vec(&mut r, n * cin);
        let wv = random_vec(&mut r, cout * kv * cin);
        let set = Arc::new(CoordSet::new(coords.clone(), shape, 1).unwrap());
        let map = match kind {
            ConvKind::Submanifold => conv_map(&set, MapKind::Submanifold, g).unwrap().1,
            ConvKind::Regular => conv_map(&set, MapKind::Regular, g).unwrap().1,
            _ => {
                conv_map(
                    &set,
                    MapKind::Transposed {
                        output_padding: [0; 3],
                    },
                    g,
                )
                .unwrap()
                .1
            }
        };
        let m = map.n_out();
        let rv = random_vec(&mut r, m * cout);
        let wview = host::WeightView {
            d0: cout,
            k: kv,
            d2: cin,
            transposed: false,
        };
        let loss = |x: &[f64], w: &[f64]| -> f64 {
            host::conv_forward(x, w, wview, &map)
                .iter()
                .zip(&rv)
                .map(|(a, b)| a * b)
                .sum()
        };
        // Analytic: dx via the transposed map, dw via the weight-grad kernel.
        let dx = host::conv_forward(
            &rv,
            &wv,
            host::WeightView {
                transposed: true,
                ..wview
            },
            &map.transposed(),
        );
        let dw = host::conv_weight_grad(&xv, &rv, wview, &map);
        check_central_differences(&format!("{kind:?} dx"), &xv, 3, &dx, &|a| loss(a, &wv));
        check_central_differences(&format!("{kind:?} dw"), &wv, 5, &dw, &|a| loss(&xv, a));
        // The portable burn-ops path (used on GPU backends) agrees with the host path.
        let dev = Default::default();
        let xt = Tensor::<Inner, 2>::from_data(TensorData::new(xv.clone(), [n, cin]), &dev);
        let wt = Tensor::<Inner, 3>::from_data(TensorData::new(wv.clone(), [cout, kv, cin]), &dev);
        // Both forms: the implicit GEMM (gather table) and the per-offset fallback.
        assert!(map.gather_table().is_some());
        let yh = host::conv_forward(&xv, &wv, wview, &map);
        let rt = Tensor::<Inner, 2>::from_data(TensorData::new(rv.clone(), [m, cout]), &dev);
        let ws = [cout, kv, cin];
        // In row chunks: 7 output rows per gathered block here.
        let lim = 7 * kv * cin;
        let checks: [(&str, Vec<f64>, &[f64]); 9] = [
            (
                "implicit GEMM forward",
                to_vec_inner(conv_forward_portable(xt.clone(), wt.clone(), &map, false)),
                &yh,
            ),
            (
                "per-offset forward",
                to_vec_inner(conv_forward_per_offset(xt.clone(), wt.clone(), &map, false)),
                &yh,
            ),
            (
                "implicit GEMM dw",
                to_vec_inner(conv_weight_grad_portable(
                    xt.clone(),
                    rt.clone(),
                    &map,
                    ws,
                    false,
                )),
                &dw,
            ),
            (
                "per-offset dw",
                to_vec_inner(conv_weight_grad_per_offset(
                    xt.clone(),
                    rt.clone(),
                    &map,
                    ws,
                    false,
                )),
                &dw,
            ),
            // dx through the transposed map and transposed weight view, as the autodiff backward
            // does.
            (
                "implicit GEMM dx",
                to_vec_inner(conv_forward_portable(
                    rt.clone(),
                    wt.clone(),
                    &map.transposed(),
                    true,
                )),
                &dx,
            ),
            (
                "chunked forward",
                to_vec_inner(conv_forward_portable_chunked(
                    xt.clone(),
                    wt.clone(),
                    &map,
                    false,
                    lim,
                    RowBucket::NONE,
                )),
                &yh,
            ),
            // Each block's rows padded (reading the zero row) and cut back: the same values.
            (
                "chunked forward, rows bucketed",
                to_vec_inner(conv_forward_portable_chunked(
                    xt.clone(),
                    wt.clone(),
                    &map,
                    false,
                    lim,
                    RowBucket {
                        multiple: 7,
                        min: 20,
                    },
                )),
                &yh,
            ),
            (
                "forward, rows bucketed as on the cubecl backends",
                to_vec_inner(conv_forward_portable_chunked(
                    xt.clone(),
                    wt,
                    &map,
                    false,
                    usize::MAX,
                    RowBucket::CUBECL,
                )),
                &yh,
            ),
            (
                "chunked dw",
                to_vec_inner(conv_weight_grad_portable_chunked(
                    xt, rt, &map, ws, false, lim,
                )),
                &dw,
            ),
        ];
        for (what, got, want) in checks {
            assert!(max_abs_diff(&got, want) < 1e-12, "{kind:?} {what}");
        }
    }
}

/// A map with two inputs at the same (output row, offset) has no gather table; the portable path
/// then takes the per-offset form and still sums both.
#[test]
fn portable_path_without_gather_table() {
    type Inner = NdArray<f64>;
    let map =
        KernelMap::from_pairs(3, 2, vec![(vec![0, 1], vec![0, 0]), (vec![2], vec![1])]).unwrap();
    assert!(map.gather_table().is_none());
    let dev = Default::default();
    let x = Tensor::<Inner, 2>::from_data(TensorData::new(vec![1.0, 2.0, 4.0], [3, 1]), &dev);
    let w = Tensor::<Inner, 3>::from_data(TensorData::new(vec![10.0, 100.0], [1, 2, 1]), &dev);
    let y = to_vec_inner(conv_forward_portable(x.clone(), w, &map, false));
    assert_eq!(y, vec![30.0, 400.0]);
    let dy = Tensor::<Inner, 2>::from_data(TensorData::new(vec![1.0, 1.0], [2, 1]), &dev);
    let dw = to_vec_inner(conv_weight_grad_portable(x, dy, &map, [1, 2, 1], false));
    assert_eq!(dw, vec![3.0, 4.0]);
}

#[test]
fn max_pool_gradient_goes_to_winners() {
    let mut r = rng(4);
    let shape = [8, 8, 4];
    let coords = random_coords(&mut r, shape, 1, 60);
    let n = coords.len();
    let xv = random_vec(&mut r, n * 2);
    let x = t2(xv.clone(), [n, 2]).require_grad();
    let t = SparseTensor::new(coords.clone(), x.clone(), shape, 1).unwrap();
    let out = SparseMaxPool3dConfig::new([2, 2, 2])
        .init()
        .forward(t)
        .unwrap();
    let g = out.feats().clone().sum().backward();
    let gx = to_vec_inner(x.grad(&g).unwrap());
    // Each output channel's maximum receives gradient 1; every other input 0.
    let ov = to_vec(out.feats().clone());
    let mut expected = vec![0.0; n * 2];
    for (row, o) in out.coords().iter().enumerate() {
        for ch in 0..2 {
            let winner = coords
                .iter()
                .enumerate()
                .filter(|(_, c)| c[0] == o[0] && (0..3).all(|a| c[a + 1] / 2 == o[a + 1]))
                .max_by(|a, b| xv[a.0 * 2 + ch].total_cmp(&xv[b.0 * 2 + ch]))
                .unwrap()
                .0;
            assert_eq!(ov[row * 2 + ch], xv[winner * 2 + ch]);
            expected[winner * 2 + ch] += 1.0;
        }
    }
    assert_eq!(gx, expected);
}

#[test]
fn structural_ops() {
    let dev = Default::default();
    let a = SparseTensor::<B64>::new(
        vec![[0, 0, 0, 0], [0, 1, 1, 1]],
        t2(vec![1., 2., 3., 4.], [2, 2]),
        [4, 4, 4],
        1,
    )
    .unwrap();
    let b = SparseTensor::<B64>::new(
        vec![[0, 1, 1, 1], [0, 3, 3, 3]],
        t2(vec![10., 20., 30., 40.], [2, 2]),
        [4, 4, 4],
        1,
    )
    .unwrap();
    let s = ops::add(&a, &b).unwrap();
    assert_eq!(s.coords(), &[[0, 0, 0, 0], [0, 1, 1, 1], [0, 3, 3, 3]]);
    assert_eq!(to_vec(s.feats().clone()), vec![1., 2., 13., 24., 30., 40.]);
    let e = ops::extend_zero(&a, &[[0, 2, 2, 2], [0, 0, 0, 0]]).unwrap();
    assert_eq!(e.coords(), &[[0, 0, 0, 0], [0, 1, 1, 1], [0, 2, 2, 2]]);
    assert_eq!(to_vec(e.feats().clone()), vec![1., 2., 3., 4., 0., 0.]);
    assert!(ops::extend_zero(&a, &[[0, 4, 0, 0]]).is_err());
    let p = ops::prune(&s, &[true, false, true]).unwrap();
    assert_eq!(p.coords(), &[[0, 0, 0, 0], [0, 3, 3, 3]]);
    let scores = Tensor::<B64, 1>::from_data(TensorData::new(vec![0.1, 0.9, 0.5], [3]), &dev);
    let (top, idx) = ops::topk(&s, &scores, 2, false).unwrap();
    assert_eq!(idx, vec![1, 2]);
    assert_eq!(top.coords(), &[[0, 1, 1, 1], [0, 3, 3, 3]]);
    assert!(ops::gather(&s, &[0, 0]).is_err());
    assert!(ops::gather(&s, &[5]).is_err());
    // Dense round trip.
    let d = s.to_dense();
    assert_eq!(d.dims(), [1, 2, 4, 4, 4]);
    let back = SparseTensor::from_dense(d).unwrap();
    assert_eq!(back.coords(), s.coords());
    assert_eq!(to_vec(back.feats().clone()), to_vec(s.feats().clone()));
    let c = ops::cat_feats(&[s.clone(), s.clone()]).unwrap();
    assert_eq!(c.channels(), 4);
    // Different frames cannot be added.
    let other =
        SparseTensor::<B64>::new(vec![[0, 0, 0, 0]], t2(vec![1., 1.], [1, 2]), [5, 4, 4], 1)
            .unwrap();
    assert!(matches!(
        ops::add(&a, &other),
        Err(SparseError::Incompatible(_))
    ));
}

#[test]
fn bad_input_is_an_error_not_a_panic() {
    let x = t2(vec![0.0; 6], [2, 3]);
    // Row count mismatch.
    assert!(matches!(
        SparseTensor::<B64>::new(vec![[0, 0, 0, 0]], x.clone(), [4, 4, 4], 1),
        Err(SparseError::Shape(_))
    ));
    // Out of range and duplicates.
    assert!(matches!(
        SparseTensor::<B64>::new(vec![[0, 0, 0, 0], [0, 0, 0, 9]], x.clone(), [4, 4, 4], 1),
        Err(SparseError::OutOfRange { .. })
    ));
    assert!(matches!(
        SparseTensor::<B64>::new(vec![[0, 1, 0, 0], [0, 1, 0, 0]], x.clone(), [4, 4, 4], 1),
        Err(SparseError::Duplicate { .. })
    ));
    let t = SparseTensor::<B64>::new(vec![[0, 1, 0, 0], [0, 2, 0, 0]], x, [4, 4, 4], 1).unwrap();
    // Wrong weight layout (Cin in the wrong place) and wrong channel count.
    let submanifold_3 = |w| {
        sparse_conv3d(
            t.clone(),
            w,
            None,
            ConvKind::Submanifold,
            ConvGeometry::new([3, 3, 3]),
            [0; 3],
        )
    };
    let e = submanifold_3(t5(vec![0.0; 3 * 27 * 5], [3, 3, 3, 3, 5]));
    assert!(matches!(e, Err(SparseError::Shape(_))), "{e:?}");
    let e = submanifold_3(t5(vec![0.0; 5 * 9 * 3], [5, 3, 3, 1, 3]));
    assert!(matches!(e, Err(SparseError::WeightLayout { .. })), "{e:?}");
    // Even submanifold kernel, zero stride, kernel larger than the grid.
    let dev = Default::default();
    let config_error = |cfg: SparseConv3dConfig| {
        let conv = cfg.init::<B64>(&dev);
        matches!(conv.forward(t.clone()), Err(SparseError::Config(_)))
    };
    assert!(config_error(SparseConv3dConfig::new(3, 4, [2, 2, 2])));
    assert!(config_error(
        SparseConv3dConfig::new(3, 4, [3, 3, 3])
            .with_kind(ConvKind::Regular)
            .with_stride([0, 1, 1])
    ));
    assert!(config_error(
        SparseConv3dConfig::new(3, 4, [9, 1, 1]).with_kind(ConvKind::Regular)
    ));
    // Inverse without a matching strided conv.
    let conv = SparseConv3dConfig::new(3, 4, [3, 3, 3])
        .with_kind(ConvKind::Inverse)
        .init::<B64>(&dev);
    assert!(matches!(conv.forward(t), Err(SparseError::NoInverseMap(_))));
}

#[test]
fn layer_with_bias_and_empty_input() {
    let dev = Default::default();
    let conv = SparseConv3dConfig::new(2, 3, [3, 3, 3])
        .with_bias(true)
        .init::<B64>(&dev);
    let t = SparseTensor::<B64>::new(vec![], t2(vec![], [0, 2]), [4, 4, 4], 1).unwrap();
    let out = conv.forward(t).unwrap();
    assert_eq!(out.num_active(), 0);
    assert_eq!(out.channels(), 3);
    let t = SparseTensor::<B64>::new(vec![[0, 1, 1, 1]], t2(vec![0.0, 0.0], [1, 2]), [4, 4, 4], 1)
        .unwrap();
    let out = conv.forward(t).unwrap();
    let b = to_vec(conv.bias.as_ref().unwrap().val());
    assert_eq!(to_vec(out.feats().clone()), b, "zero input gives the bias");
}

/// The fused f32 kernels (AVX2 + FMA, `C_out` a multiple of 16: offset-major gather-multiply-scatter
/// and output-major rows) and the gather/GEMM/scatter path give the f64 result to f32 accuracy on
/// every map kind, for the weight applied as is (forward) and transposed (input gradient), with
/// remainder pairs (not a multiple of the 4-pair tile), C_in not a multiple of the split, and every
/// output tile width (16, 32, 64).
#[test]
fn fused_kernel_equals_gemm_path_f32() {
    let mut r = rng(11);
    let shape = [12, 10, 6];
    let coords = random_coords(&mut r, shape, 2, 300);
    let set = Arc::new(CoordSet::new(coords, shape, 2).unwrap());
    let g3 = ConvGeometry::new([3, 3, 3]).with_padding([1; 3]);
    for (kind, g) in [
        (MapKind::Submanifold, g3),
        (MapKind::Regular, g3),
        (MapKind::Regular, g3.with_stride([2; 3])),
        (
            MapKind::Transposed {
                output_padding: [0; 3],
            },
            ConvGeometry::new([2, 2, 2]).with_stride([2; 3]),
        ),
    ] {
        let map = conv_map(&set, kind, g).unwrap().1;
        let kv = g.kernel.iter().product::<usize>();
        for (cin, cout, transposed) in [
            (20, 32, false),
            (32, 48, false),
            (16, 20, true),
            (7, 64, false),
            (24, 16, true),
        ] {
            // Weight [d0, K, d2]: not transposed d0 = cout, d2 = cin; transposed d0 = cin, d2 = cout.
            let (d0, d2) = if transposed { (cin, cout) } else { (cout, cin) };
            let wview = host::WeightView {
                d0,
                k: kv,
                d2,
                transposed,
            };
            let x64 = random_vec(&mut r, set.len() * cin);
            let w64 = random_vec(&mut r, d0 * kv * d2);
            let want = host::conv_forward::<f64>(&x64, &w64, wview, &map);
            let x32: Vec<f32> = x64.iter().map(|&v| v as f32).collect();
            let w32: Vec<f32> = w64.iter().map(|&v| v as f32).collect();
            let by_output = host::conv_forward_by_output::<f32>(&x32, &w32, wview, &map);
            #[cfg(target_arch = "x86_64")]
            if cout % 16 == 0
                && std::arch::is_x86_feature_detected!("avx2")
                && std::arch::is_x86_feature_detected!("fma")
            {
                assert!(
                    by_output.is_some(),
                    "cout {cout}: the fused kernels run here"
                );
            }
            for got in [
                host::conv_forward::<f32>(&x32, &w32, wview, &map),
                host::conv_forward_gemm::<f32>(&x32, &w32, wview, &map),
                host::conv_forward_by_offset::<f32>(&x32, &w32, wview, &map),
            ]
            .into_iter()
            .chain(by_output)
            {
                let got: Vec<f64> = got.iter().map(|&v| v as f64).collect();
                let err = max_abs_diff(&got, &want);
                assert!(
                    err < 1e-4,
                    "{kind:?} cin {cin} cout {cout}: max |diff| {err}"
                );
            }
        }
    }
}

/// The pairs grouped by output row hold every pair once, in ascending offset within a row; the
/// output-major kernel writes zeros on rows without a pair (the output is not pre-zeroed).
#[test]
fn pairs_by_output_and_rows_without_pairs() {
    // 6 outputs, rows 1 and 4 without a pair; 3 offsets.
    let pairs = vec![
        (vec![0, 2], vec![0, 3]),
        (vec![1], vec![5]),
        (vec![2, 0, 1], vec![0, 2, 5]),
    ];
    let map = KernelMap::from_pairs(3, 6, pairs).unwrap();
    let by = map.by_output();
    assert_eq!(by.start, vec![0, 2, 2, 3, 4, 4, 6]);
    assert_eq!(by.ins, vec![0, 2, 0, 2, 1, 1]);
    assert_eq!(by.offsets, vec![0, 2, 2, 0, 1, 2]);
    let (cin, cout) = (3, 16);
    let wview = host::WeightView {
        d0: cout,
        k: 3,
        d2: cin,
        transposed: false,
    };
    let mut r = rng(5);
    let x: Vec<f32> = random_vec(&mut r, 3 * cin)
        .iter()
        .map(|&v| v as f32)
        .collect();
    let w: Vec<f32> = random_vec(&mut r, cout * 3 * cin)
        .iter()
        .map(|&v| v as f32)
        .collect();
    let want = host::conv_forward_gemm::<f32>(&x, &w, wview, &map);
    let Some(got) = host::conv_forward_by_output::<f32>(&x, &w, wview, &map) else {
        return; // no AVX2 + FMA here: the fused kernels do not run
    };
    for o in [1, 4] {
        assert!(got[o * cout..(o + 1) * cout].iter().all(|&v| v == 0.0));
    }
    let err = want
        .iter()
        .zip(&got)
        .map(|(a, b)| (a - b).abs())
        .fold(0.0f32, f32::max);
    assert!(err < 1e-5, "max |diff| {err}");
}

/// The padded row counts: none on the CPU, at least one padding row and the bucket's multiple and
/// minimum otherwise.
#[test]
fn row_bucket_padding() {
    assert_eq!(RowBucket::NONE.padded(5), 5);
    assert_eq!(RowBucket::NONE.padded(0), 0);
    let b = RowBucket::CUBECL;
    assert_eq!(b.padded(0), 1536);
    assert_eq!(b.padded(1535), 1536);
    assert_eq!(b.padded(1536), 2048);
    assert_eq!(b.padded(2047), 2048);
    assert_eq!(b.padded(32_697), 32_768);
    let odd = RowBucket {
        multiple: 7,
        min: 20,
    };
    assert_eq!(odd.padded(3), 20);
    assert_eq!(odd.padded(20), 21);
    let dev = Default::default();
    let x =
        Tensor::<NdArray<f64>, 2>::from_data(TensorData::new(vec![1.0, 2.0, 3.0], [3, 1]), &dev);
    let y = odd.map(x.clone(), |p| {
        assert_eq!(p.dims(), [20, 1]);
        p * 2.0
    });
    assert_eq!(y.into_data().to_vec::<f64>().unwrap(), vec![2.0, 4.0, 6.0]);
    assert_eq!(odd.pad(x).dims(), [20, 1]);
}
