//! Unit checks of the SparseOcc building blocks against brute-force references: LSS pooling, depth
//! targets, Hungarian assignment, masked attention, propagator active sets and gradients, pyramid
//! interpolation, label downsampling.

use crate::so_common;

use burn::backend::{Autodiff, NdArray};
use burn::module::{Module, ModuleVisitor, Param};
use burn::prelude::*;
use burn::tensor::TensorData;
use occ_geometry::mat4_inverse;
use occ_labels::downsample_mode;
use occ_model::loss::cross_entropy_weighted;
use occ_model::lss::{depth_targets, feature_pixel_center, LssConfig};
use occ_model::sparseocc::hungarian::hungarian;
use occ_model::sparseocc::mask_head::{
    attention_bias, DecoderLayer, MaskHeadConfig, PoolMap, MASKED_BIAS,
};
use occ_model::sparseocc::propagator::PropagatorConfig;
use occ_model::sparseocc::pyramid::{interpolate, interpolation_weights};
use occ_sparse::{Coord, SparseTensor};
use rand::Rng;
use so_common::*;
use std::collections::{BTreeMap, BTreeSet, HashSet};

type B64 = Autodiff<NdArray<f64>>;

// ---------------------------------------------------------------------------------------------
// LSS

#[test]
fn lss_pooling_matches_brute_force_scatter() {
    let device = Default::default();
    let mut r = rng(11);
    let dbound = [0.5, 7.5, 0.5];
    let stride = 4;
    let (h, w) = (IMG_H / stride, IMG_W / stride);
    let cams = vec![
        vec![camera([-0.5, 0.0, 0.0], 0.0), camera([-0.3, 0.4, 0.1], 0.3)],
        vec![
            camera([-0.8, -0.2, 0.0], -0.2),
            camera([0.5, 0.0, 0.3], 0.6),
        ],
    ];
    let batch = batch::<B64>(cams.clone(), false);
    let lss = LssConfig::new(8, 4)
        .with_mid_channels(8)
        .with_dbound(dbound)
        .init::<B64>(&device)
        .unwrap();
    let feats = random_tensor::<B64, 4>(&mut r, [4, 8, h, w]);
    let out = lss.forward(feats, stride, &batch).unwrap();
    let d = lss.num_bins();
    assert_eq!(d, 14);
    assert_eq!(out.depth_logits.dims(), [4, d, h, w]);
    let prob = to_vec_f64(out.depth_prob());
    let ctx = to_vec_f64(out.context.clone());
    let c = 4;

    // Brute force: host loop over all frustum points in f64.
    let grid = tiny_grid().downsampled(2);
    let mut expected: BTreeMap<Coord, Vec<f64>> = BTreeMap::new();
    for (b, cams_b) in cams.iter().enumerate().take(2) {
        for (v, cam) in cams_b.iter().enumerate().take(2) {
            let bv = b * 2 + v;
            let inv = mat4_inverse(&cam.img_from_lidar).unwrap();
            for k in 0..d {
                let depth = dbound[0] + k as f64 * dbound[2];
                for i in 0..h {
                    for j in 0..w {
                        let (u, vv) = (
                            feature_pixel_center(j, stride),
                            feature_pixel_center(i, stride),
                        );
                        let q = [u * depth, vv * depth, depth, 1.0];
                        let p: Vec<f64> = (0..3)
                            .map(|a| (0..4).map(|m| inv[a][m] * q[m]).sum::<f64>())
                            .collect();
                        let mut ijk = [0i32; 3];
                        let mut inside = true;
                        for a in 0..3 {
                            let f = ((p[a] - grid.origin_m[a]) / grid.voxel_size_m).floor();
                            inside &= f >= 0.0 && f < grid.dims[a] as f64;
                            ijk[a] = f as i32;
                        }
                        if !inside {
                            continue;
                        }
                        let e = expected
                            .entry([b as i32, ijk[0], ijk[1], ijk[2]])
                            .or_insert_with(|| vec![0.0; c]);
                        let pr = prob[((bv * d + k) * h + i) * w + j];
                        for ch in 0..c {
                            e[ch] += pr * ctx[((bv * c + ch) * h + i) * w + j];
                        }
                    }
                }
            }
        }
    }
    assert!(
        expected.len() > 20,
        "too few voxels hit: {}",
        expected.len()
    );

    let sparse = out.splat_sparse().unwrap();
    let got_coords: Vec<Coord> = sparse.coords().to_vec();
    let exp_coords: Vec<Coord> = expected.keys().copied().collect();
    assert_eq!(got_coords, exp_coords, "non-empty voxel set differs");
    let feats = to_vec_f64(sparse.feats().clone());
    for (n, (_, e)) in expected.iter().enumerate() {
        for ch in 0..c {
            let g = feats[n * c + ch];
            assert!(
                (g - e[ch]).abs() < 1e-9,
                "voxel {n} ch {ch}: {g} vs {}",
                e[ch]
            );
        }
    }

    // Dense splat agrees, and is zero elsewhere.
    let dense = to_vec_f64(out.splat_dense().unwrap());
    let [gx, gy, gz] = grid.dims;
    let mut nonzero_outside = 0;
    for b in 0..2 {
        for x in 0..gx {
            for y in 0..gy {
                for z in 0..gz {
                    let key = [b as i32, x as i32, y as i32, z as i32];
                    for ch in 0..c {
                        let v = dense[((((b * c + ch) * gx + x) * gy + y) * gz) + z];
                        match expected.get(&key) {
                            Some(e) => assert!((v - e[ch]).abs() < 1e-9),
                            None => nonzero_outside += (v != 0.0) as usize,
                        }
                    }
                }
            }
        }
    }
    assert_eq!(nonzero_outside, 0);
}

#[test]
fn lss_pooling_is_differentiable() {
    let device = Default::default();
    let mut r = rng(12);
    let batch = batch::<B64>(vec![vec![camera([-0.5, 0.0, 0.0], 0.0)]], false);
    let lss = LssConfig::new(8, 4)
        .with_mid_channels(8)
        .with_dbound([0.5, 7.5, 0.5])
        .init::<B64>(&device)
        .unwrap();
    let feats = random_tensor::<B64, 4>(&mut r, [1, 8, 8, 16]).require_grad();
    let out = lss.forward(feats.clone(), 4, &batch).unwrap();
    let s = out.splat_sparse().unwrap();
    let loss = s.feats().clone().powf_scalar(2.0).sum();
    let grads = loss.backward();
    let g = to_vec_f64(feats.grad(&grads).unwrap());
    assert!(g.iter().any(|v| v.abs() > 0.0));
}

#[test]
fn depth_targets_take_the_patch_minimum() {
    let cam = camera([0.0, 0.0, 0.0], 0.0);
    let mut batch = batch::<B64>(vec![vec![cam.clone()]], false);
    // Two points on the optical axis (pixel (31.5, 15.5) rounds to (32, 16) -> patch (8/4.. ) at
    // stride 4: column 8, row 4) at 3.1 m and 2.0 m, one point behind the camera.
    batch.points = Some(vec![vec![
        [3.1, 0.0, 0.0],
        [2.0, 0.0, 0.0],
        [-1.0, 0.0, 0.0],
    ]]);
    let dbound = [0.5, 7.5, 0.25];
    let t = depth_targets(&batch, 8, 16, 4, dbound).unwrap().unwrap();
    assert_eq!(t.len(), 8 * 16);
    let hit: Vec<(usize, i64)> = t
        .iter()
        .copied()
        .enumerate()
        .filter(|(_, v)| *v >= 0)
        .collect();
    // min depth 2.0 -> bin (2.0 - 0.5)/0.25 = 6.
    assert_eq!(hit, vec![(4 * 16 + 8, 6)]);
    // Without points: no targets.
    batch.points = None;
    assert!(depth_targets(&batch, 8, 16, 4, dbound).unwrap().is_none());
}

// ---------------------------------------------------------------------------------------------
// Hungarian

fn brute_force_min(cost: &[f64], rows: usize, cols: usize) -> f64 {
    // Injective maps from the smaller side to the larger one.
    fn rec(
        cost: &[f64],
        rows: usize,
        cols: usize,
        i: usize,
        used: &mut Vec<bool>,
        acc: f64,
        best: &mut f64,
    ) {
        let n = rows.min(cols);
        if i == n {
            *best = best.min(acc);
            return;
        }
        let m = rows.max(cols);
        for j in 0..m {
            if !used[j] {
                used[j] = true;
                let c = if rows <= cols {
                    cost[i * cols + j]
                } else {
                    cost[j * cols + i]
                };
                rec(cost, rows, cols, i + 1, used, acc + c, best);
                used[j] = false;
            }
        }
    }
    let mut best = f64::INFINITY;
    rec(
        cost,
        rows,
        cols,
        0,
        &mut vec![false; rows.max(cols)],
        0.0,
        &mut best,
    );
    best
}

#[test]
fn hungarian_is_optimal_against_brute_force() {
    let mut r = rng(5);
    for trial in 0..300 {
        let rows = r.random_range(1..=6usize);
        let cols = r.random_range(1..=6usize);
        let integer = trial % 3 == 0; // many ties
        let cost: Vec<f64> = (0..rows * cols)
            .map(|_| {
                if integer {
                    r.random_range(0..4) as f64
                } else {
                    r.random_range(-5.0..5.0)
                }
            })
            .collect();
        let pairs = hungarian(&cost, rows, cols).unwrap();
        assert_eq!(pairs.len(), rows.min(cols));
        let rs: HashSet<usize> = pairs.iter().map(|p| p.0).collect();
        let cs: HashSet<usize> = pairs.iter().map(|p| p.1).collect();
        assert_eq!(rs.len(), pairs.len());
        assert_eq!(cs.len(), pairs.len());
        assert!(pairs.iter().all(|&(i, j)| i < rows && j < cols));
        let total: f64 = pairs.iter().map(|&(i, j)| cost[i * cols + j]).sum();
        let best = brute_force_min(&cost, rows, cols);
        assert!(
            (total - best).abs() < 1e-9,
            "{rows}x{cols}: {total} vs optimum {best}"
        );
    }
}

// ---------------------------------------------------------------------------------------------
// Masked attention

#[test]
fn masked_cross_attention_ignores_masked_voxels() {
    let device = Default::default();
    let mut r = rng(21);
    let head = MaskHeadConfig::new(8, 4)
        .with_num_queries(5)
        .with_num_layers(1)
        .with_num_heads(2)
        .with_ffn_channels(16)
        .with_num_memory_levels(1)
        .with_norm_groups(4)
        .init::<B64>(&device)
        .unwrap();
    let layer: &DecoderLayer<B64> = &head.layers[0];
    let (nq, m, c) = (5, 12, 8);
    let q = random_tensor::<B64, 2>(&mut r, [nq, c]);
    let qp = random_tensor::<B64, 2>(&mut r, [nq, c]);
    let mem = random_tensor::<B64, 2>(&mut r, [m, c]);
    let pos = random_tensor::<B64, 2>(&mut r, [m, c]);
    // Keys 3, 7, 8 masked for every query; key 5 masked for queries 0 and 2 only.
    let mut bias = vec![0f64; nq * m];
    for qi in 0..nq {
        for k in [3, 7, 8] {
            bias[qi * m + k] = MASKED_BIAS;
        }
    }
    bias[5] = MASKED_BIAS;
    bias[2 * m + 5] = MASKED_BIAS;
    let bias_t = Tensor::<B64, 2>::from_data(TensorData::new(bias, [nq, m]), &device);
    let base = to_vec_f64(layer.forward(
        q.clone(),
        qp.clone(),
        mem.clone(),
        pos.clone(),
        Some(bias_t.clone()),
    ));

    // Change the features (and positions) of the keys masked for all queries: output unchanged.
    let mut mem2 = to_vec_f64(mem.clone());
    let mut pos2 = to_vec_f64(pos.clone());
    for k in [3, 7, 8] {
        for ch in 0..c {
            mem2[k * c + ch] += 10.0 * (ch as f64 + 1.0);
            pos2[k * c + ch] -= 3.0;
        }
    }
    let mem2 = Tensor::<B64, 2>::from_data(TensorData::new(mem2, [m, c]), &device);
    let pos2 = Tensor::<B64, 2>::from_data(TensorData::new(pos2, [m, c]), &device);
    let out2 = to_vec_f64(layer.forward(q.clone(), qp.clone(), mem2, pos2, Some(bias_t.clone())));
    let diff: f64 = base
        .iter()
        .zip(&out2)
        .map(|(a, b)| (a - b).abs())
        .fold(0.0, f64::max);
    assert!(diff < 1e-12, "masked keys changed the output by {diff}");

    // Key 5 is masked for queries 0 and 2 only: changing it changes the other queries, not 0 and 2
    // (self-attention mixes queries, so check the cross-attention block itself).
    let mut mem3 = to_vec_f64(mem.clone());
    for ch in 0..c {
        mem3[5 * c + ch] += 5.0;
    }
    let mem3 = Tensor::<B64, 2>::from_data(TensorData::new(mem3, [m, c]), &device);
    let ca = |mm: Tensor<B64, 2>| {
        to_vec_f64(layer.cross_attn.forward(
            q.clone() + qp.clone(),
            mm.clone() + pos.clone(),
            mm,
            Some(bias_t.clone()),
        ))
    };
    let a = ca(mem.clone());
    let b = ca(mem3);
    for qi in 0..nq {
        let d: f64 = (0..c)
            .map(|ch| (a[qi * c + ch] - b[qi * c + ch]).abs())
            .sum();
        if qi == 0 || qi == 2 {
            assert!(d < 1e-12, "query {qi} saw a masked key ({d})");
        } else {
            assert!(d > 1e-6, "query {qi} did not see an unmasked key");
        }
    }
}

#[test]
fn attention_bias_matches_dense_max_pool() {
    let mut r = rng(31);
    let dims0 = [8usize, 8, 4];
    for trial in 0..20 {
        let stride = if trial % 2 == 0 { 2 } else { 4 };
        let mdims = dims0.map(|d| (d / stride).max(1));
        // Level-0 sites and a kept subset.
        let mut set = BTreeSet::new();
        while set.len() < 40 {
            set.insert([
                0,
                r.random_range(0..8),
                r.random_range(0..8),
                r.random_range(0..4),
            ]);
        }
        let level0: Vec<Coord> = set.into_iter().collect();
        let kept_rows: Vec<usize> = (0..level0.len()).filter(|_| r.random_bool(0.6)).collect();
        // Memory sites: all parents plus some random extra sites.
        let mut mset = BTreeSet::new();
        for c in &level0 {
            mset.insert([
                0,
                c[1] / stride as i32,
                c[2] / stride as i32,
                (c[3] / stride as i32).min(mdims[2] as i32 - 1),
            ]);
        }
        for _ in 0..3 {
            mset.insert([
                0,
                r.random_range(0..mdims[0] as i32),
                r.random_range(0..mdims[1] as i32),
                r.random_range(0..mdims[2] as i32),
            ]);
        }
        let memory: Vec<Coord> = mset.into_iter().collect();
        let nq = 6;
        let nk = kept_rows.len();
        let kept_logits: Vec<f32> = (0..nq * nk).map(|_| r.random_range(-2.0..1.0)).collect();
        let empty_logits: Vec<f32> = (0..nq).map(|_| r.random_range(-1.5..0.5)).collect();
        let map = PoolMap::new(&level0, dims0, &memory, stride, mdims);
        let (bias, all_masked) = attention_bias(&kept_logits, &kept_rows, &empty_logits, &map);

        // Brute force on the dense level-0 grid.
        let mut exp_all = 0;
        for q in 0..nq {
            let mut grid = vec![empty_logits[q]; dims0.iter().product()];
            for (j, &row) in kept_rows.iter().enumerate() {
                let c = level0[row];
                grid[((c[1] as usize * 8) + c[2] as usize) * 4 + c[3] as usize] =
                    kept_logits[q * nk + j];
            }
            let mut row_bias = vec![0f32; memory.len()];
            for (s, mc) in memory.iter().enumerate() {
                let mut mx = f32::NEG_INFINITY;
                for x in 0..8 {
                    for y in 0..8 {
                        for z in 0..4 {
                            let p = [
                                (x / stride) as i32,
                                (y / stride) as i32,
                                ((z / stride).min(mdims[2] - 1)) as i32,
                            ];
                            if p == [mc[1], mc[2], mc[3]] {
                                mx = mx.max(grid[(x * 8 + y) * 4 + z]);
                            }
                        }
                    }
                }
                row_bias[s] = if mx >= 0.0 { 0.0 } else { MASKED_BIAS as f32 };
            }
            if row_bias.iter().all(|&b| b != 0.0) {
                row_bias.iter_mut().for_each(|b| *b = 0.0);
                exp_all += 1;
            }
            assert_eq!(
                &bias[q * memory.len()..(q + 1) * memory.len()],
                &row_bias[..],
                "trial {trial} query {q}"
            );
        }
        assert_eq!(all_masked, exp_all);
    }
}

// ---------------------------------------------------------------------------------------------
// Propagator

fn dilate(set: &BTreeSet<Coord>, k: [usize; 3], shape: [usize; 3]) -> BTreeSet<Coord> {
    let mut out = BTreeSet::new();
    for c in set {
        for dx in 0..k[0] as i32 {
            for dy in 0..k[1] as i32 {
                for dz in 0..k[2] as i32 {
                    let o = [
                        c[0],
                        c[1] + dx - k[0] as i32 / 2,
                        c[2] + dy - k[1] as i32 / 2,
                        c[3] + dz - k[2] as i32 / 2,
                    ];
                    if (0..3).all(|a| o[a + 1] >= 0 && (o[a + 1] as usize) < shape[a]) {
                        out.insert(o);
                    }
                }
            }
        }
    }
    out
}

fn downsample_k3s2p1(set: &BTreeSet<Coord>, shape: [usize; 3]) -> (BTreeSet<Coord>, [usize; 3]) {
    let out_shape = shape.map(|s| (s + 2 - 3) / 2 + 1);
    let mut out = BTreeSet::new();
    for c in set {
        for k in 0..27 {
            let kk = [k / 9, (k / 3) % 3, k % 3];
            let mut o = [c[0], 0, 0, 0];
            let mut ok = true;
            for a in 0..3 {
                let num = c[a + 1] + 1 - kk[a];
                ok &= num >= 0 && num % 2 == 0 && ((num / 2) as usize) < out_shape[a];
                o[a + 1] = num / 2;
            }
            if ok {
                out.insert(o);
            }
        }
    }
    (out, out_shape)
}

#[derive(Default)]
struct GradCheck {
    total: usize,
    missing: Vec<String>,
    grads: Option<<B64 as burn::tensor::backend::AutodiffBackend>::Gradients>,
}

impl ModuleVisitor<B64> for GradCheck {
    fn visit_float<const D: usize>(&mut self, param: &Param<Tensor<B64, D>>) {
        // Running statistics (BatchNorm) are visited too but are not trainable.
        if !param.val().is_require_grad() {
            return;
        }
        self.total += 1;
        let g = param.val().grad(self.grads.as_ref().unwrap());
        let desc = match g {
            None => Some("none".to_string()),
            Some(g) => {
                let v = to_vec_f64(g);
                (!v.iter().any(|x| x.abs() > 0.0)).then(|| format!("zero {v:?}"))
            }
        };
        if let Some(d) = desc {
            self.missing.push(format!("{:?}: {d}", param.val().dims()));
        }
    }
}

#[test]
fn propagator_grows_active_set_and_trains_every_parameter() {
    let device = Default::default();
    let mut r = rng(41);
    let shape = [16usize, 16, 8];
    let input: Vec<Coord> = vec![[0, 3, 4, 2], [0, 10, 12, 5], [1, 7, 7, 7]];
    let c0 = 4;
    let feats = random_tensor::<B64, 2>(&mut r, [input.len(), c0]);
    let x = SparseTensor::new(input.clone(), feats, shape, 2).unwrap();
    let prop = PropagatorConfig::new(c0)
        .with_channels(vec![4, 6, 6, 8])
        .with_completion_layers(vec![2, 1, 1, 1])
        .init::<B64>(&device)
        .unwrap();
    let out = prop.forward(x).unwrap();
    assert_eq!(out.levels.len(), 4);

    // Expected active sets by host dilation.
    let mut set: BTreeSet<Coord> = input.into_iter().collect();
    let mut sh = shape;
    let layers = [2, 1, 1, 1];
    for l in 0..4 {
        let planar = l >= 2;
        for _ in 0..layers[l] {
            set = dilate(&set, [3, 3, 1], sh);
        }
        if !planar {
            set = dilate(&set, [3, 1, 3], sh);
            set = dilate(&set, [1, 3, 3], sh);
        }
        let got: BTreeSet<Coord> = out.levels[l].coords().iter().copied().collect();
        assert_eq!(out.levels[l].spatial_shape(), sh, "level {l} shape");
        assert_eq!(got, set, "level {l} active set");
        assert_eq!(out.levels[l].channels(), [4, 6, 6, 8][l]);
        if l < 3 {
            let (s, nsh) = downsample_k3s2p1(&set, sh);
            set = s;
            sh = nsh;
        }
    }
    // Completion grew the set: level 0 is larger than the input.
    assert!(out.levels[0].num_active() > 3 * 9);
    assert_eq!(out.stats[0].0, "prop.l0.completed");

    // Gradients reach every parameter.
    let loss = out
        .levels
        .iter()
        .map(|t| {
            t.feats()
                .clone()
                .powf_scalar(2.0)
                .sum()
                .mul_scalar(1.0 / t.num_active() as f64)
        })
        .reduce(|a, b| a + b)
        .unwrap();
    let mut check = GradCheck {
        grads: Some(loss.backward()),
        ..Default::default()
    };
    prop.visit(&mut check);
    assert!(check.total > 30, "only {} parameters", check.total);
    assert!(
        check.missing.is_empty(),
        "parameters without gradient: {:?}",
        check.missing
    );
}

// ---------------------------------------------------------------------------------------------
// Pyramid interpolation

#[test]
fn interpolation_reproduces_linear_fields_and_block_means() {
    let device = Default::default();
    // Coarse source: dense 4x4x2 at stride 2 with a linear field f = x + 2y - z (in level-0 units
    // of the voxel centres).
    let centre = |o: i32, s: i32| (o as f64 + 0.5) * s as f64 - 0.5;
    let field = |p: [f64; 3]| p[0] + 2.0 * p[1] - p[2];
    let mut coarse = Vec::new();
    let mut vals = Vec::new();
    for x in 0..4 {
        for y in 0..4 {
            for z in 0..2 {
                coarse.push([0, x, y, z]);
                vals.push(field([centre(x, 2), centre(y, 2), centre(z, 2)]));
            }
        }
    }
    let n = coarse.len();
    let src = SparseTensor::new(
        coarse,
        Tensor::<B64, 2>::from_data(TensorData::new(vals.clone(), [n, 1]), &device),
        [4, 4, 2],
        1,
    )
    .unwrap();
    // Fine destinations strictly inside the coarse centres' hull.
    let fine: Vec<Coord> = vec![[0, 1, 1, 1], [0, 2, 3, 2], [0, 5, 4, 1], [0, 3, 6, 2]];
    let dst = SparseTensor::new(
        fine.clone(),
        Tensor::<B64, 2>::zeros([4, 1], &device),
        [8, 8, 4],
        1,
    )
    .unwrap();
    let got = to_vec_f64(interpolate(&src, 2, &dst, 1).unwrap());
    for (k, c) in fine.iter().enumerate() {
        let e = field([c[1] as f64, c[2] as f64, c[3] as f64]);
        assert!((got[k] - e).abs() < 1e-9, "{c:?}: {} vs {e}", got[k]);
    }
    // Normalisation: a fine site near only one active coarse site copies it.
    let lone = SparseTensor::new(
        vec![[0, 0, 0, 0]],
        Tensor::<B64, 2>::ones([1, 1], &device).mul_scalar(7.0),
        [4, 4, 2],
        1,
    )
    .unwrap();
    let got = to_vec_f64(interpolate(&lone, 2, &dst, 1).unwrap());
    assert!((got[0] - 7.0).abs() < 1e-12);
    assert_eq!(got[2], 0.0, "a site with no active neighbour gets zero");

    // Finer source: block mean.
    let fine_src: Vec<Coord> = vec![[0, 0, 0, 0], [0, 1, 1, 1], [0, 2, 0, 0], [0, 7, 7, 3]];
    let fv = vec![1.0, 3.0, 10.0, 4.0];
    let fsrc = SparseTensor::new(
        fine_src,
        Tensor::<B64, 2>::from_data(TensorData::new(fv, [4, 1]), &device),
        [8, 8, 4],
        1,
    )
    .unwrap();
    let cdst = SparseTensor::new(
        vec![[0, 0, 0, 0], [0, 1, 0, 0], [0, 3, 3, 1], [0, 2, 2, 1]],
        Tensor::<B64, 2>::zeros([4, 1], &device),
        [4, 4, 2],
        1,
    )
    .unwrap();
    let got = to_vec_f64(interpolate(&fsrc, 1, &cdst, 2).unwrap());
    assert_eq!(got, vec![2.0, 10.0, 4.0, 0.0]);
    let w = interpolation_weights(&fsrc, 1, &cdst, 2);
    assert_eq!(w.len(), 4);
}

// ---------------------------------------------------------------------------------------------
// Labels and cross-entropy

#[test]
fn mode_downsampling_follows_the_official_rule() {
    let dims = [2, 2, 2];
    let ds = |v: [u8; 8]| downsample_mode(&v, dims, 2).unwrap()[0];
    assert_eq!(ds([0; 8]), 0);
    assert_eq!(
        ds([0, 0, 0, 0, 0, 0, 0, 5]),
        255,
        "single label with zeros: a negative wins the tie"
    );
    assert_eq!(ds([0, 0, 0, 0, 0, 0, 5, 5]), 5);
    assert_eq!(
        ds([3, 3, 3, 3, 1, 1, 1, 1]),
        1,
        "ties go to the smaller label"
    );
    assert_eq!(ds([255, 255, 255, 0, 0, 0, 0, 0]), 255);
    assert_eq!(
        ds([7, 4, 9, 2, 5, 6, 8, 3]),
        2,
        "all distinct, no zero: smallest"
    );
    assert_eq!(ds([0, 0, 0, 0, 0, 4, 4, 255]), 4);
    // Larger grid: blocks independent, C order.
    let mut l = vec![0u8; 4 * 2 * 2];
    l[(2 * 2) * 2] = 3; // x = 2 -> block 1
    l[(2 * 2 + 1) * 2] = 3;
    assert_eq!(downsample_mode(&l, [4, 2, 2], 2).unwrap(), vec![0, 3]);
    assert!(downsample_mode(&l, [4, 2, 3], 2).is_err());
}

#[test]
fn weighted_cross_entropy_matches_formula() {
    let device = Default::default();
    let logits = vec![1.0, 2.0, 0.5, -1.0, 0.0, 3.0, 0.2, 0.2, 0.2];
    let labels = [1u8, 255, 2];
    let w = [0.5, 2.0, 1.5];
    let t = Tensor::<B64, 2>::from_data(TensorData::new(logits.clone(), [3, 3]), &device);
    let got = to_vec_f64(cross_entropy_weighted(t, &labels, &w, 255).unwrap())[0];
    let nll = |row: &[f64], y: usize| {
        let m = row.iter().cloned().fold(f64::NEG_INFINITY, f64::max);
        let lse = m + row.iter().map(|v| (v - m).exp()).sum::<f64>().ln();
        lse - row[y]
    };
    let e = (2.0 * nll(&logits[0..3], 1) + 1.5 * nll(&logits[6..9], 2)) / 3.5;
    assert!((got - e).abs() < 1e-12);
}

// ---------------------------------------------------------------------------------------------
// Dense baseline

/// The dense baseline's encoder layer (a submanifold convolution over a grid whose every voxel is
/// active) equals burn's dense `conv3d` with zero padding 1, forward and input gradient.
#[test]
fn dense_baseline_conv_is_a_dense_conv3d() {
    use burn::tensor::module::conv3d;
    use burn::tensor::ops::ConvOptions;
    use occ_model::dense::dense_conv_config;
    use occ_sparse::full_grid_coords;
    let device = Default::default();
    let mut r = rng(31);
    let (b, cin, cout, dims) = (2usize, 3usize, 4usize, [5usize, 4, 3]);
    let n = b * dims.iter().product::<usize>();
    let x0 = random_tensor::<B64, 5>(&mut r, [b, cin, dims[0], dims[1], dims[2]]);
    let (x, xd) = (
        x0.clone().detach().require_grad(),
        x0.detach().require_grad(),
    );
    let layer = dense_conv_config(cin, cout).init::<B64>(&device);
    // Sparse path, as in DenseBaseline::forward.
    let feats = x.clone().permute([0, 2, 3, 4, 1]).reshape([n, cin]);
    let t = SparseTensor::new(full_grid_coords(b, dims), feats, dims, b).unwrap();
    let y = layer.forward(t).unwrap().into_feats();
    // Dense reference: weight [Cout, kx, ky, kz, Cin] -> [Cout, Cin, kx, ky, kz].
    let w = layer.weight.val().permute([0, 4, 1, 2, 3]);
    let y_ref = conv3d(
        xd.clone(),
        w,
        None,
        ConvOptions::new([1, 1, 1], [1, 1, 1], [1, 1, 1], 1),
    )
    .permute([0, 2, 3, 4, 1])
    .reshape([n, cout]);
    let max_err = |a: Vec<f64>, e: Vec<f64>| {
        assert_eq!(a.len(), e.len());
        a.iter()
            .zip(&e)
            .map(|(p, q)| (p - q).abs())
            .fold(0.0, f64::max)
    };
    let err = max_err(to_vec_f64(y.clone()), to_vec_f64(y_ref.clone()));
    assert!(err < 1e-10, "forward max error {err}");
    // Input gradients of a random linear functional.
    let g = random_tensor::<B64, 2>(&mut r, [n, cout]);
    let ga = x.grad(&(y * g.clone()).sum().backward()).unwrap();
    let gb = xd.grad(&(y_ref * g).sum().backward()).unwrap();
    let err = max_err(to_vec_f64(ga), to_vec_f64(gb));
    assert!(err < 1e-10, "input-gradient max error {err}");
}
