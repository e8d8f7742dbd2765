//! Every layer against a dense conv3d / conv_transpose3d (burn, f64) evaluated at the active sites:
//! forward values, active sets, and gradients with respect to input features and weights.

mod common;

use burn::prelude::*;
use burn::tensor::module::{conv3d, conv_transpose3d};
use burn::tensor::ops::{ConvOptions, ConvTransposeOptions};
use common::*;
use occ_sparse::conv::sparse_conv3d;
use occ_sparse::{ConvGeometry, ConvKind, Coord, SparseTensor};

const SHAPE: [usize; 3] = [9, 8, 5];
const BATCH: usize = 2;
const CIN: usize = 3;
const COUT: usize = 4;

struct Case {
    kind: ConvKind,
    geom: ConvGeometry,
    output_padding: [usize; 3],
}

fn geom(k: [usize; 3], s: [usize; 3], p: [usize; 3], d: [usize; 3]) -> ConvGeometry {
    ConvGeometry::new(k)
        .with_stride(s)
        .with_padding(p)
        .with_dilation(d)
}

/// Dense output `[B, COUT, ...]` of the reference op plus its shape.
fn dense_reference(case: &Case, x: Tensor<B64, 5>, w: Tensor<B64, 5>) -> Tensor<B64, 5> {
    let g = case.geom;
    match case.kind {
        ConvKind::Submanifold => {
            let pad = std::array::from_fn(|a| (g.kernel[a] / 2) * g.dilation[a]);
            conv3d(
                x,
                w.permute([0, 4, 1, 2, 3]),
                None,
                ConvOptions::new([1; 3], pad, g.dilation, 1),
            )
        }
        ConvKind::Regular => conv3d(
            x,
            w.permute([0, 4, 1, 2, 3]),
            None,
            ConvOptions::new(g.stride, g.padding, g.dilation, 1),
        ),
        ConvKind::Transposed => conv_transpose3d(
            x,
            w.permute([4, 0, 1, 2, 3]),
            None,
            ConvTransposeOptions::new(g.stride, g.padding, case.output_padding, g.dilation, 1),
        ),
        ConvKind::Inverse => unreachable!("inverse has its own test"),
    }
}

fn support(coords: &[Coord], case: &Case, out_shape: [usize; 3]) -> Vec<Coord> {
    // Brute force: an output is active iff the dense op applied to the occupancy with a ones kernel is > 0.
    let occ = densify(coords, &vec![1.0; coords.len()], 1, SHAPE, BATCH);
    let ones = Tensor::<B64, 5>::ones(
        [
            1,
            case.geom.kernel[0],
            case.geom.kernel[1],
            case.geom.kernel[2],
            1,
        ],
        &Default::default(),
    );
    let d = dense_reference(
        case,
        t5(occ, [BATCH, 1, SHAPE[0], SHAPE[1], SHAPE[2]]),
        ones,
    );
    assert_eq!(d.dims()[2..], out_shape[..], "dense reference output shape");
    let v = to_vec(d);
    let mut out = Vec::new();
    for b in 0..BATCH {
        for x in 0..out_shape[0] {
            for y in 0..out_shape[1] {
                for z in 0..out_shape[2] {
                    let i = ((b * out_shape[0] + x) * out_shape[1] + y) * out_shape[2] + z;
                    if v[i] > 0.5 {
                        out.push([b as i32, x as i32, y as i32, z as i32]);
                    }
                }
            }
        }
    }
    out
}

fn run_case(case: Case, seed: u64) {
    let mut r = rng(seed);
    let coords = random_coords(&mut r, SHAPE, BATCH, 70);
    let n = coords.len();
    let k = case.geom.kernel;
    let xv = random_vec(&mut r, n * CIN);
    let wv = random_vec(&mut r, COUT * k[0] * k[1] * k[2] * CIN);

    // Sparse.
    let xs = t2(xv.clone(), [n, CIN]).require_grad();
    let ws = t5(wv.clone(), [COUT, k[0], k[1], k[2], CIN]).require_grad();
    let input = SparseTensor::new(coords.clone(), xs.clone(), SHAPE, BATCH).unwrap();
    let out = sparse_conv3d(
        input,
        ws.clone(),
        None,
        case.kind,
        case.geom,
        case.output_padding,
    )
    .unwrap();
    let out_coords = out.coords().to_vec();
    let out_shape = out.spatial_shape();
    let m = out.num_active();

    // Dense.
    let xd = t5(
        densify(&coords, &xv, CIN, SHAPE, BATCH),
        [BATCH, CIN, SHAPE[0], SHAPE[1], SHAPE[2]],
    )
    .require_grad();
    let wd = t5(wv, [COUT, k[0], k[1], k[2], CIN]).require_grad();
    let dense_out = dense_reference(&case, xd.clone(), wd.clone());
    assert_eq!(
        dense_out.dims()[2..],
        out_shape[..],
        "{:?} output shape",
        case.kind
    );

    // Active set.
    let expected_sites = match case.kind {
        ConvKind::Submanifold => coords.clone(),
        _ => support(&coords, &case, out_shape),
    };
    assert_eq!(
        out_coords, expected_sites,
        "{:?} {:?}: active set",
        case.kind, case.geom
    );

    // Forward values at the active sites.
    let sparse_vals = to_vec(out.feats().clone());
    let dense_vals = sample(&to_vec(dense_out.clone()), &out_coords, COUT, out_shape);
    let err = max_abs_diff(&sparse_vals, &dense_vals);
    assert!(
        err < 1e-10,
        "{:?} {:?}: forward max abs err {err}",
        case.kind,
        case.geom
    );

    // Gradients of sum(out * R) for a random R on the active sites.
    let rv = random_vec(&mut r, m * COUT);
    let loss_s = (out.feats().clone() * t2(rv.clone(), [m, COUT])).sum();
    let gs = loss_s.backward();
    let r_dense = densify(&out_coords, &rv, COUT, out_shape, BATCH);
    let loss_d = (dense_out
        * t5(
            r_dense,
            [BATCH, COUT, out_shape[0], out_shape[1], out_shape[2]],
        ))
    .sum();
    let gd = loss_d.backward();
    let gx_s = to_vec_inner(xs.grad(&gs).unwrap());
    let gx_d = sample(&to_vec_inner(xd.grad(&gd).unwrap()), &coords, CIN, SHAPE);
    let e = max_abs_diff(&gx_s, &gx_d);
    assert!(
        e < 1e-10,
        "{:?} {:?}: input grad err {e}",
        case.kind,
        case.geom
    );
    let gw_s = to_vec_inner(ws.grad(&gs).unwrap());
    let gw_d = to_vec_inner(wd.grad(&gd).unwrap());
    let e = max_abs_diff(&gw_s, &gw_d);
    assert!(
        e < 1e-10,
        "{:?} {:?}: weight grad err {e}",
        case.kind,
        case.geom
    );
}

#[test]
fn submanifold_matches_dense() {
    let one = [1; 3];
    for (i, (k, d)) in [
        ([3, 3, 3], one),
        ([3, 3, 1], one),
        ([3, 1, 3], one),
        ([1, 3, 3], one),
        ([5, 5, 1], one),
        ([1, 1, 1], one),
        ([3, 3, 3], [2, 2, 1]),
        ([3, 3, 1], [2, 1, 1]),
    ]
    .into_iter()
    .enumerate()
    {
        run_case(
            Case {
                kind: ConvKind::Submanifold,
                geom: geom(k, one, [0; 3], d),
                output_padding: [0; 3],
            },
            100 + i as u64,
        );
    }
}

#[test]
fn regular_matches_dense() {
    let one = [1; 3];
    for (i, (k, s, p, d)) in [
        ([3, 3, 3], one, [1, 1, 1], one),
        ([3, 3, 1], one, [1, 1, 0], one),
        ([3, 1, 3], one, [1, 0, 1], one),
        ([1, 3, 3], one, [0, 1, 1], one),
        ([3, 3, 3], [2, 2, 2], [1, 1, 1], one),
        ([2, 2, 2], [2, 2, 2], [0, 0, 0], one),
        ([3, 3, 3], [2, 2, 2], [0, 0, 0], one),
        ([3, 3, 1], [2, 2, 1], [1, 1, 0], one),
        ([3, 3, 3], one, [2, 2, 2], [2, 2, 2]),
        ([3, 3, 3], one, [0, 0, 0], one),
    ]
    .into_iter()
    .enumerate()
    {
        run_case(
            Case {
                kind: ConvKind::Regular,
                geom: geom(k, s, p, d),
                output_padding: [0; 3],
            },
            200 + i as u64,
        );
    }
}

#[test]
fn transposed_matches_dense() {
    let one = [1; 3];
    for (i, (k, s, p, op)) in [
        ([2, 2, 2], [2, 2, 2], [0, 0, 0], [0, 0, 0]),
        ([3, 3, 3], [2, 2, 2], [1, 1, 1], [1, 1, 1]),
        ([2, 2, 3], [2, 2, 2], [0, 0, 1], [0, 0, 1]),
        ([3, 3, 3], one, [1, 1, 1], [0, 0, 0]),
    ]
    .into_iter()
    .enumerate()
    {
        run_case(
            Case {
                kind: ConvKind::Transposed,
                geom: geom(k, s, p, one),
                output_padding: op,
            },
            300 + i as u64,
        );
    }
}

/// Inverse convolution: conv_transpose3d(conv3d(x)) sampled at the input sites, forward and gradients.
#[test]
fn inverse_matches_dense() {
    for (seed, (k, s, p)) in [
        ([3, 3, 3], [2, 2, 2], [1, 1, 1]),
        ([2, 2, 2], [2, 2, 2], [0, 0, 0]),
    ]
    .into_iter()
    .enumerate()
    {
        let g = geom(k, s, p, [1; 3]);
        let mut r = rng(400 + seed as u64);
        let coords = random_coords(&mut r, SHAPE, BATCH, 70);
        let n = coords.len();
        let xv = random_vec(&mut r, n * CIN);
        let wdv = random_vec(&mut r, COUT * k[0] * k[1] * k[2] * CIN);
        let wuv = random_vec(&mut r, CIN * k[0] * k[1] * k[2] * COUT);
        let xs = t2(xv.clone(), [n, CIN]).require_grad();
        let wd_s = t5(wdv.clone(), [COUT, k[0], k[1], k[2], CIN]).require_grad();
        let wu_s = t5(wuv.clone(), [CIN, k[0], k[1], k[2], COUT]).require_grad();
        let input = SparseTensor::new(coords.clone(), xs.clone(), SHAPE, BATCH).unwrap();
        let mid = sparse_conv3d(input, wd_s.clone(), None, ConvKind::Regular, g, [0; 3]).unwrap();
        let mid_shape = mid.spatial_shape();
        let up = sparse_conv3d(mid, wu_s.clone(), None, ConvKind::Inverse, g, [0; 3]).unwrap();
        assert_eq!(up.coords(), &coords[..], "inverse restores the input sites");
        assert_eq!(up.spatial_shape(), SHAPE);

        let xd = t5(
            densify(&coords, &xv, CIN, SHAPE, BATCH),
            [BATCH, CIN, SHAPE[0], SHAPE[1], SHAPE[2]],
        )
        .require_grad();
        let wd_d = t5(wdv, [COUT, k[0], k[1], k[2], CIN]).require_grad();
        let wu_d = t5(wuv, [CIN, k[0], k[1], k[2], COUT]).require_grad();
        let mid_d = conv3d(
            xd.clone(),
            wd_d.clone().permute([0, 4, 1, 2, 3]),
            None,
            ConvOptions::new(s, p, [1; 3], 1),
        );
        let op: [usize; 3] =
            std::array::from_fn(|a| SHAPE[a] - ((mid_shape[a] - 1) * s[a] + k[a] - 2 * p[a]));
        let up_d = conv_transpose3d(
            mid_d,
            wu_d.clone().permute([4, 0, 1, 2, 3]),
            None,
            ConvTransposeOptions::new(s, p, op, [1; 3], 1),
        );
        let e = max_abs_diff(
            &to_vec(up.feats().clone()),
            &sample(&to_vec(up_d.clone()), &coords, CIN, SHAPE),
        );
        assert!(e < 1e-10, "inverse forward err {e}");

        let rv = random_vec(&mut r, n * CIN);
        let gs = (up.feats().clone() * t2(rv.clone(), [n, CIN]))
            .sum()
            .backward();
        let gd = (up_d
            * t5(
                densify(&coords, &rv, CIN, SHAPE, BATCH),
                [BATCH, CIN, SHAPE[0], SHAPE[1], SHAPE[2]],
            ))
        .sum()
        .backward();
        let e = max_abs_diff(
            &to_vec_inner(xs.grad(&gs).unwrap()),
            &sample(&to_vec_inner(xd.grad(&gd).unwrap()), &coords, CIN, SHAPE),
        );
        assert!(e < 1e-10, "inverse input grad err {e}");
        for (a, b) in [(&wd_s, &wd_d), (&wu_s, &wu_d)] {
            let e = max_abs_diff(
                &to_vec_inner(a.grad(&gs).unwrap()),
                &to_vec_inner(b.grad(&gd).unwrap()),
            );
            assert!(e < 1e-10, "inverse weight grad err {e}");
        }
    }
}
