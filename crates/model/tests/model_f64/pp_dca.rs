//! Deformable cross attention against a direct computation: projection, view exclusion, bilinear
//! sampling at `(u + 0.5)/stride - 0.5 + offset` feature pixels, softmax weights, view averaging.

use crate::pp_common;

use burn::module::Param;
use burn::prelude::*;
use occ_geometry::transform_point;
use occ_model::sparseocc_pp::dca::{
    project_column_bases, project_queries, DcaConfig, DcaInputs, DeformableCrossAttention,
    FeatureRows,
};
use pp_common::*;

type B64 = burn::backend::NdArray<f64>;

/// Bilinear sample of a `[h, w]` map at feature-pixel `(x, y)`, zero outside (align_corners = false
/// with pixel centres at integers).
fn bilinear(map: &[f64], h: usize, w: usize, x: f64, y: f64) -> f64 {
    let (x0, y0) = (x.floor(), y.floor());
    let (fx, fy) = (x - x0, y - y0);
    let mut acc = 0.0;
    for (dx, wx) in [(0.0, 1.0 - fx), (1.0, fx)] {
        for (dy, wy) in [(0.0, 1.0 - fy), (1.0, fy)] {
            let (xi, yi) = (x0 + dx, y0 + dy);
            if xi >= 0.0 && yi >= 0.0 && (xi as usize) < w && (yi as usize) < h {
                acc += wx * wy * map[yi as usize * w + xi as usize];
            }
        }
    }
    acc
}

/// Heads, levels, points per head and level, and channels of the DCA blocks below.
const DCA_SIZES: (usize, usize, usize, usize) = (2, 2, 3, 8);

/// A DCA block of [`DCA_SIZES`] over `FEAT_C` image channels whose offsets and attention weights
/// depend on the query (the init makes them constant): the two projections' weights drawn from
/// `seeds`, the offsets' scaled by `offset_scale`.
fn query_dependent_dca<Bk: occ_model::kernels::ModelBackend>(
    seeds: [u64; 2],
    offset_scale: f64,
    device: &Bk::Device,
) -> DeformableCrossAttention<Bk> {
    let (m, l, p, d) = DCA_SIZES;
    let mut dca = DcaConfig::new(d, FEAT_C)
        .with_num_levels(l)
        .with_num_heads(m)
        .with_num_points(p)
        .init::<Bk>(device);
    dca.sampling_offsets.weight =
        Param::from_tensor(randn([d, m * l * p * 2], seeds[0], device) * offset_scale);
    dca.attention_weights.weight = Param::from_tensor(randn([d, m * l * p], seeds[1], device));
    dca
}

#[test]
fn dca_excludes_views_that_do_not_see_the_voxel() {
    let device = Default::default();
    let (m, l, p, d) = DCA_SIZES;
    let dca = query_dependent_dca::<B64>([11, 12], 2.0, &device);
    let g = grid();
    let cams = cameras(1);
    // A: behind camera 0, seen by camera 1. B: seen by both. C: seen by none.
    let coords = vec![[0, 5, 16, 4], [0, 25, 14, 5], [0, 0, 31, 4], [0, 9, 20, 2]];
    let hits = project_queries(&coords, &g, &cams, IMG_HW).unwrap();
    assert_eq!(hits.views_per_query, vec![1, 2, 0, 1]);
    let feats = features::<B64>(1, 7, &device);
    let query = randn::<B64, 2>([coords.len(), d], 13, &device);
    let got = to_f64(
        &dca.aggregate(query.clone(), &hits, &feats, &STRIDES)
            .unwrap(),
    );

    // Direct computation.
    let (off, wts) = dca.sampling(query);
    let (off, wts) = (to_f64(&off), to_f64(&wts));
    let dh = d / m;
    let values: Vec<(Vec<f64>, usize, usize)> = feats
        .iter()
        .map(|f| {
            let [_, _, h, w] = f.dims();
            (to_f64(&dca.project_values(f.clone())), h, w)
        })
        .collect();
    let mut checked_zero_pad = false;
    for (q, c) in coords.iter().enumerate() {
        let centre = g.voxel_center_m([c[1] as usize, c[2] as usize, c[3] as usize]);
        let mut expected = vec![0.0; d];
        let mut seen = 0;
        for (v, cam) in cams[0].iter().enumerate() {
            let t = transform_point(&cam.img_from_lidar, centre);
            if t[2] <= 1e-3 {
                continue;
            }
            let (u, vv) = (t[0] / t[2], t[1] / t[2]);
            if !(u >= 0.0 && vv >= 0.0 && u < IMG_HW.1 as f64 && vv < IMG_HW.0 as f64) {
                continue;
            }
            seen += 1;
            for head in 0..m {
                for (lvl, (vals, h, w)) in values.iter().enumerate() {
                    let s = STRIDES[lvl] as f64;
                    for j in 0..p {
                        let base = (((q * m + head) * l + lvl) * p + j) * 2;
                        let x = (u + 0.5) / s - 0.5 + off[base];
                        let y = (vv + 0.5) / s - 0.5 + off[base + 1];
                        if x < -1.0 || y < -1.0 || x > *w as f64 || y > *h as f64 {
                            checked_zero_pad = true;
                        }
                        let wgt = wts[((q * m + head) * l + lvl) * p + j];
                        for ch in 0..dh {
                            let img = v * m + head; // [B·V·M] with b = 0
                            let map = &vals[(img * dh + ch) * h * w..][..h * w];
                            expected[head * dh + ch] += wgt * bilinear(map, *h, *w, x, y);
                        }
                    }
                }
            }
        }
        assert_eq!(seen, hits.views_per_query[q]);
        for e in expected.iter_mut() {
            if seen > 0 {
                *e /= seen as f64;
            }
        }
        for ch in 0..d {
            let (a, b) = (got[q * d + ch], expected[ch]);
            assert!((a - b).abs() < 1e-9, "query {q} channel {ch}: {a} vs {b}");
        }
        if seen == 0 {
            assert!(got[q * d..(q + 1) * d].iter().all(|&v| v == 0.0));
        }
    }
    assert!(checked_zero_pad, "offsets never left the feature map");
    // Query A (behind camera 0) gives exactly what camera 1 alone gives: drop camera 0 and its images.
    let only_a = vec![coords[0], coords[3]];
    let cam1 = vec![vec![cams[0][1].clone()]];
    let hits_a = project_queries(&only_a, &g, &cam1, IMG_HW).unwrap();
    assert_eq!(hits_a.views_per_query, vec![1, 1]);
    let feats1: Vec<Tensor<B64, 4>> = feats.iter().map(|f| f.clone().narrow(0, 1, 1)).collect();
    let q_a = randn::<B64, 2>([coords.len(), d], 13, &device)
        .select(0, Tensor::<B64, 1, Int>::from_data([0i64, 3], &device));
    let alone = to_f64(&dca.aggregate(q_a, &hits_a, &feats1, &STRIDES).unwrap());
    for (i, q) in [0usize, 3].iter().enumerate() {
        for ch in 0..d {
            let (a, b) = (alone[i * d + ch], got[q * d + ch]);
            assert!((a - b).abs() < 1e-12, "query {q} channel {ch}: {a} vs {b}");
        }
    }
}

/// The fused host loop (CPU inference) and the tensor-op composition (autodiff, CUDA) compute the
/// same attention, in f64 and in f32, including samples that leave the feature maps.
#[test]
fn dca_host_loop_equals_tensor_ops() {
    fn check<Bk: occ_model::kernels::ModelBackend>(tol: f64) {
        let device = Default::default();
        let d = DCA_SIZES.3;
        let dca = query_dependent_dca::<Bk>([21, 22], 3.0, &device);
        let g = grid();
        let coords: Vec<[i32; 4]> = (0..2)
            .flat_map(|b| (0..64).map(move |i| [b, (i * 5) % 32, (i * 11) % 32, i % 8]))
            .collect();
        let cams = cameras(2);
        let hits = project_queries(&coords, &g, &cams, IMG_HW).unwrap();
        assert!(hits.len() > 64, "{} hits", hits.len());
        let feats = features::<Bk>(2, 5, &device);
        let query = randn::<Bk, 2>([coords.len(), d], 23, &device);
        // Ungated, and with a per-hit gate in [0, 1] (a quarter of the hits shut).
        let gate_vals: Vec<f64> = (0..hits.len())
            .map(|i| {
                if i % 4 == 0 {
                    0.0
                } else {
                    0.2 + (i % 7) as f64 / 8.0
                }
            })
            .collect();
        let gate = Tensor::<Bk, 1>::from_data(
            TensorData::new(gate_vals, [hits.len()]).convert::<Bk::FloatElem>(),
            &device,
        );
        let mut outs = Vec::new();
        for g in [None, Some(gate)] {
            let rows = FeatureRows::from_nchw(&feats).unwrap();
            let inputs = |gate| DcaInputs {
                query: query.clone(),
                hits: &hits,
                feats: &rows,
                strides: &STRIDES,
                gate,
            };
            let host = to_f64(&dca.aggregate_host(inputs(g.clone())).unwrap());
            let ops = to_f64(&dca.aggregate_tensor_ops(inputs(g)).unwrap());
            assert_eq!(host.len(), ops.len());
            let mut nonzero = 0;
            for (i, (a, b)) in host.iter().zip(&ops).enumerate() {
                assert!(
                    (a - b).abs() < tol * (1.0 + b.abs()),
                    "entry {i}: {a} vs {b}"
                );
                nonzero += usize::from(*b != 0.0);
            }
            assert!(nonzero > host.len() / 3, "{nonzero} of {}", host.len());
            outs.push(ops);
        }
        // The gate changes the result.
        let diff: f64 = outs[0]
            .iter()
            .zip(&outs[1])
            .map(|(a, b)| (a - b).abs())
            .sum();
        assert!(diff > 1e-3, "{diff}");
    }
    check::<B64>(1e-10);
    check::<NB>(1e-4);
}

/// On `Autodiff<NdArray>` (CPU training) the sampling is one autodiff op with its own backward
/// (`dca_host.rs`); it gives the same output and the same gradients as the tensor-op composition
/// (`grid_sample`, which `tests/grid_sample_fixture.rs` checks against PyTorch) for the query (through
/// the offsets and the attention weights), the image features, every DCA parameter and the gate.
#[test]
fn dca_host_autodiff_equals_tensor_ops_with_gradients() {
    let device = Default::default();
    let d = DCA_SIZES.3;
    let dca = query_dependent_dca::<AD>([31, 32], 3.0, &device);
    let g = grid();
    // Two batch items of two cameras: queries seen by 0, 1 or 2 views.
    let coords: Vec<[i32; 4]> = (0..2)
        .flat_map(|b| (0..48).map(move |i| [b, (i * 7) % 32, (i * 13) % 32, i % 8]))
        .collect();
    let cams = cameras(2);
    let hits = project_queries(&coords, &g, &cams, IMG_HW).unwrap();
    assert!(hits.views_per_query.contains(&2));
    assert!(hits.views_per_query.contains(&0));
    let feats0 = features::<AD>(2, 33, &device);
    let query0 = randn::<AD, 2>([coords.len(), d], 34, &device);
    let weight0 = randn::<AD, 2>([coords.len(), d], 35, &device);
    let gate_vals: Vec<f64> = (0..hits.len())
        .map(|i| {
            if i % 5 == 0 {
                0.0
            } else {
                0.3 + (i % 7) as f64 / 9.0
            }
        })
        .collect();
    let gate0 = Tensor::<AD, 1>::from_data(TensorData::new(gate_vals, [hits.len()]), &device);
    for gated in [false, true] {
        let mut results = Vec::new();
        for host in [true, false] {
            let feats: Vec<Tensor<AD, 4>> =
                feats0.iter().map(|f| f.clone().require_grad()).collect();
            let query = query0.clone().require_grad();
            let gate = gated.then(|| gate0.clone().require_grad());
            let rows = FeatureRows::from_nchw(&feats).unwrap();
            let inputs = DcaInputs {
                query: query.clone(),
                hits: &hits,
                feats: &rows,
                strides: &STRIDES,
                gate: gate.clone(),
            };
            // The backend's kernel (on `Autodiff<NdArray>` the host op, checked by
            // `cpu_backends_take_the_host_kernels`) or the tensor-op composition.
            let out = if host {
                dca.aggregate_gated(inputs)
            } else {
                dca.aggregate_tensor_ops(inputs)
            }
            .unwrap();
            let grads = (out.clone() * weight0.clone()).sum().backward();
            let mut got = vec![("out".to_string(), to_f64(&out))];
            got.push(("query".into(), to_f64(&query.grad(&grads).unwrap())));
            for (i, f) in feats.iter().enumerate() {
                got.push((format!("feats[{i}]"), to_f64(&f.grad(&grads).unwrap())));
            }
            if let Some(gate) = &gate {
                got.push(("gate".into(), to_f64(&gate.grad(&grads).unwrap())));
            }
            for (name, w) in [
                ("value_proj", &dca.value_proj.weight),
                ("sampling_offsets", &dca.sampling_offsets.weight),
                ("attention_weights", &dca.attention_weights.weight),
            ] {
                got.push((name.into(), to_f64(&w.val().grad(&grads).unwrap())));
            }
            results.push(got);
        }
        for ((name, a), (_, b)) in results[0].iter().zip(&results[1]) {
            assert_eq!(a.len(), b.len(), "{name}");
            let scale = b.iter().fold(0.0f64, |s, v| s.max(v.abs()));
            assert!(scale > 0.0, "{name} is all zero");
            for (i, (x, y)) in a.iter().zip(b).enumerate() {
                assert!(
                    (x - y).abs() <= 1e-9 * (1.0 + scale),
                    "gated {gated}, {name}[{i}]: host {x} vs tensor ops {y}"
                );
            }
        }
    }
}

#[test]
fn dca_block_shapes_and_bad_inputs() {
    let device = Default::default();
    let dca = DcaConfig::new(8, FEAT_C)
        .with_num_levels(2)
        .with_num_heads(2)
        .init::<NB>(&device);
    let g = grid();
    let coords: Vec<[i32; 4]> = (0..2)
        .flat_map(|b| (0..32).map(move |x| [b, x, (x * 7) % 32, x % 8]))
        .collect();
    let hits = project_queries(&coords, &g, &cameras(2), IMG_HW).unwrap();
    assert_eq!(hits.num_images, 4);
    assert!(hits.image.windows(2).all(|w| w[0] <= w[1]));
    let feats = features::<NB>(2, 1, &device);
    let f = randn::<NB, 2>([coords.len(), 8], 2, &device);
    let pos = randn::<NB, 2>([coords.len(), 8], 3, &device);
    let rows = |maps: &[Tensor<NB, 4>]| FeatureRows::from_nchw(maps).unwrap();
    let out = dca
        .forward(f.clone(), pos.clone(), &hits, &rows(&feats), &STRIDES)
        .unwrap();
    assert_eq!(out.dims(), [coords.len(), 8]);
    assert!(to_f64(&out).iter().all(|v| v.is_finite()));
    // Wrong number of levels, levels that disagree, wrong channels, wrong number of images, voxel
    // outside the grid, batch index without cameras.
    assert!(dca
        .forward(
            f.clone(),
            pos.clone(),
            &hits,
            &rows(&feats[..1]),
            &STRIDES[..1]
        )
        .is_err());
    let narrow = |maps: &[Tensor<NB, 4>], dim: usize, len: usize| -> Vec<Tensor<NB, 4>> {
        maps.iter().map(|m| m.clone().narrow(dim, 0, len)).collect()
    };
    assert!(FeatureRows::from_nchw(&[narrow(&feats, 1, 4)[0].clone(), feats[1].clone()]).is_err());
    assert!(FeatureRows::<NB>::from_nchw(&[]).is_err());
    let few_channels = rows(&narrow(&feats, 1, 4));
    assert!(dca
        .forward(f.clone(), pos.clone(), &hits, &few_channels, &STRIDES)
        .is_err());
    let few_images = rows(&narrow(&feats, 0, 2));
    assert!(dca.forward(f, pos, &hits, &few_images, &STRIDES).is_err());
    assert!(project_queries(&[[0, 32, 0, 0]], &g, &cameras(1), IMG_HW).is_err());
    assert!(project_queries(&[[1, 0, 0, 0]], &g, &cameras(1), IMG_HW).is_err());
    assert!(DcaConfig::new(8, 4).with_num_heads(3).validate().is_err());
}

/// `dca_column_base` (not in the paper): every voxel of one vertical column gets the reference point
/// and depth of the column's base `(x, y, floor)`, projected like a voxel centre; a base outside the
/// image drops the view even when the voxel itself is seen; a non-finite floor is refused.
#[test]
fn column_bases_project_the_point_under_each_voxel() {
    let g = grid();
    let cams = cameras(1);
    let floor = g.origin_m[2] + 0.5 * g.voxel_size_m;
    // One column (x 25, y 14) at three heights, and one voxel near camera 1.
    let coords = vec![
        [0, 25, 14, 0],
        [0, 25, 14, 4],
        [0, 25, 14, 7],
        [0, 9, 20, 2],
    ];
    let hits = project_column_bases(&coords, &g, &cams, IMG_HW, floor).unwrap();
    let own = project_queries(&coords, &g, &cams, IMG_HW).unwrap();
    let mut by_query: Vec<Vec<(u32, [f64; 2], f64)>> = vec![Vec::new(); coords.len()];
    for h in 0..hits.len() {
        by_query[hits.query[h] as usize].push((hits.image[h], hits.uv[h], hits.depth_m[h]));
    }
    for (q, c) in coords.iter().enumerate() {
        let centre = g.voxel_center_m([c[1] as usize, c[2] as usize, c[3] as usize]);
        let base = [centre[0], centre[1], floor];
        let mut expected = Vec::new();
        for (v, cam) in cams[0].iter().enumerate() {
            let t = transform_point(&cam.img_from_lidar, base);
            if t[2] <= 1e-3 {
                continue;
            }
            let (u, vv) = (t[0] / t[2], t[1] / t[2]);
            if u >= 0.0 && vv >= 0.0 && u < IMG_HW.1 as f64 && vv < IMG_HW.0 as f64 {
                expected.push((v as u32, [u, vv], t[2]));
            }
        }
        assert_eq!(by_query[q].len(), expected.len(), "voxel {q}");
        for (got, want) in by_query[q].iter().zip(&expected) {
            assert_eq!(got.0, want.0, "voxel {q}");
            for k in 0..2 {
                assert!(
                    (got.1[k] - want.1[k]).abs() < 1e-9,
                    "voxel {q}: {got:?} {want:?}"
                );
            }
            assert!((got.2 - want.2).abs() < 1e-9);
        }
        assert_eq!(hits.views_per_query[q] as usize, expected.len());
    }
    // The three voxels of the column share one reference point per view; their own pixels differ.
    assert_eq!(by_query[0], by_query[1]);
    assert_eq!(by_query[1], by_query[2]);
    let own_uv = |q: u32| {
        (0..own.len())
            .find(|&h| own.query[h] == q && own.image[h] == 0)
            .map(|h| own.uv[h])
    };
    assert_ne!(own_uv(0), own_uv(2));
    // A floor far below the cameras moves every base out of the 32-pixel-high image.
    let low = project_column_bases(&coords, &g, &cams, IMG_HW, -100.0).unwrap();
    assert!(low.is_empty());
    assert!(!own.is_empty());
    assert!(project_column_bases(&coords, &g, &cams, IMG_HW, f64::NAN).is_err());
}
