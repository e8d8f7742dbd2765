//! SparseOcc++ end to end on a tiny configuration: shapes at every stage, gradients to every parameter
//! group, the ablation switches, and the propagation inside the model against Algorithm 1.

use crate::pp_common;

use burn::module::Param;
use burn::prelude::*;
use burn::tensor::TensorData;
use occ_model::loss::LossKey;
use occ_model::sparseocc_pp::anchors::{chain_anchor_count, occupancy_score, AnchorMode};
use occ_model::sparseocc_pp::scf_head::{ScfDecomposition, ScfLearning};
use occ_model::sparseocc_pp::{OutputResolution, PPOutput, SparseOccPP, SparseOccPPConfig};
use pp_common::*;

fn tiny_config() -> SparseOccPPConfig {
    SparseOccPPConfig::new(6, 8, FEAT_C, FULL_DIMS)
        .with_num_feature_levels(2)
        .with_dca_heads(2)
        .with_dca_points(2)
        .with_s_max_planar(4)
        .with_s_max_vertical(2)
}

fn run<B: occ_model::ModelBackend>(
    cfg: &SparseOccPPConfig,
    bsz: usize,
    seed: u64,
) -> (SparseOccPP<B>, PPOutput<B>) {
    let device = Default::default();
    let model: SparseOccPP<B> = cfg.try_init(&device).expect("valid config");
    let batch = batch::<B>(bsz, seed, &device);
    let feats = features::<B>(bsz, seed + 100, &device);
    let out = model.forward(&feats, &STRIDES, &batch).expect("forward");
    (model, out)
}

fn sum_all<B: Backend>(out: &PPOutput<B>) -> Tensor<B, 1> {
    let mut loss = out.out.logits.clone().sum();
    for l in &out.anchor_levels {
        loss = loss + l.logits.clone().sum();
    }
    if let Some(s) = &out.scf {
        loss = loss + s.planar.clone().sum();
        if let Some(v) = &s.vertical {
            loss = loss + v.clone().sum();
        }
    }
    loss
}

#[test]
fn shapes_at_every_stage() {
    let cfg = tiny_config();
    let bsz = 2;
    let (_, out) = run::<NB>(&cfg, bsz, 1);
    // Anchor levels: 1/8 (4x4x1, dense), 1/4, 1/2.
    assert_eq!(out.anchor_levels.len(), 3);
    let dims = [[4, 4, 1], [8, 8, 2], [16, 16, 4]];
    let mut candidates = 16;
    for (r, lvl) in out.anchor_levels.iter().enumerate() {
        assert_eq!(lvl.dims, dims[r]);
        assert_eq!(lvl.factor, [8, 4, 2][r]);
        assert_eq!(lvl.coords.len(), bsz * candidates, "level {r}");
        assert_eq!(lvl.logits.dims(), [bsz * candidates, 6]);
        let k = occ_model::sparseocc_pp::anchors::keep_count(candidates, cfg.keep_ratios[r]);
        assert_eq!(lvl.kept.len(), bsz * k);
        for c in &lvl.coords {
            assert!((0..3).all(|a| c[a + 1] >= 0 && (c[a + 1] as usize) < lvl.dims[a]));
        }
        candidates = 8 * k;
    }
    let n_anchor = bsz * chain_anchor_count(16, &cfg.keep_ratios);
    let scf = out.scf.as_ref().expect("propagation on");
    assert_eq!(scf.coords.len(), n_anchor);
    assert_eq!(scf.dims, [16, 16, 4]);
    assert_eq!(scf.planar.dims(), [n_anchor, 9]);
    assert_eq!(scf.vertical.as_ref().unwrap().dims(), [n_anchor, 5]);
    assert_eq!(scf.s_planar.len(), n_anchor);
    assert!(scf.s_planar.iter().all(|s| s.abs() <= 4));
    assert!(scf.s_vertical.iter().all(|s| s.abs() <= 2));
    // Final output on 1/2 res: anchors ⊂ final, logits per voxel.
    let n = out.out.coords.len();
    assert!(n >= n_anchor);
    assert_eq!(out.out.logits.dims(), [n, 6]);
    assert_eq!(out.out.out_dims, [16, 16, 4]);
    assert_eq!(out.out.upsample, 2);
    assert!(out.out.losses.is_empty());
    let stat = |k: &str| out.out.stats.iter().find(|(n, _)| n == k).map(|s| s.1);
    assert_eq!(stat("anchors"), Some(n_anchor));
    assert_eq!(stat("final"), Some(n));
    assert_eq!(stat("completed"), Some(n));
    assert_eq!(stat("propagated_new"), Some(n - n_anchor));
    for a in &scf.coords {
        assert!(out.out.coords.contains(a));
    }
    assert!(to_f64(&out.out.logits).iter().all(|v| v.is_finite()));
    let dense = out.out.dense_prediction(bsz, FULL_DIMS);
    assert_eq!(dense.len(), bsz);
}

#[test]
fn gradients_reach_every_parameter() {
    let cfg = tiny_config();
    let (model, out) = run::<AD>(&cfg, 2, 2);
    let grads = sum_all(&out).backward();
    let n = assert_all_grads(&model, &grads);
    assert!(n > 50, "only {n} parameters visited");
}

/// `dca_column_base` (not in the paper): a column-base DCA block follows each of the four DCAs, and the
/// gradient reaches every parameter, the new blocks' included.
#[test]
fn column_base_dca_is_built_at_every_dca_and_trained() {
    let cfg = tiny_config().with_dca_column_base(true);
    let (model, out) = run::<AD>(&cfg, 1, 21);
    assert!(model.base_dca.is_some());
    assert!(model.anchors.stages.iter().all(|s| s.base_dca.is_some()));
    let plain = tiny_config();
    let (plain_model, _) = run::<AD>(&plain, 1, 21);
    assert!(plain_model.base_dca.is_none());
    assert!(plain_model
        .anchors
        .stages
        .iter()
        .all(|s| s.base_dca.is_none()));
    assert!(model.num_params() > plain_model.num_params());
    let grads = sum_all(&out).backward();
    let n = assert_all_grads(&model, &grads);
    let n_plain = {
        let (m, o) = run::<AD>(&plain, 1, 21);
        assert_all_grads(&m, &sum_all(&o).backward())
    };
    assert!(
        n > n_plain,
        "{n} parameters visited, {n_plain} without the option"
    );
}

/// The scan oracle (a diagnostic) adds a learned embedding of each voxel's scan evidence to its
/// query at every anchor level and at the final stage: with returns in the batch the outputs change
/// and the embeddings get gradients; without points the model runs as without the option.
#[test]
fn scan_oracle_embeds_the_scan_evidence_and_trains() {
    let cfg = tiny_config().with_scan_oracle(true);
    let device = Default::default();
    let model: SparseOccPP<AD> = cfg.try_init(&device).expect("valid config");
    assert!(model.scan_embed.is_some() && model.anchors.scan_embed.is_some());
    let mut b = batch::<AD>(1, 31, &device);
    let feats = features::<AD>(1, 131, &device);
    let without = model.forward(&feats, &STRIDES, &b).expect("forward");
    // A wall of returns across the grid at x = 4.1 m, seen by the camera at x = -1.
    let points: Vec<[f32; 3]> = (0..32)
        .flat_map(|j| (0..8).map(move |k| [4.1, -3.1 + 0.2 * j as f32, -0.7 + 0.2 * k as f32]))
        .collect();
    b.points = Some(vec![points]);
    let with = model.forward(&feats, &STRIDES, &b).expect("forward");
    let (l0, l0_without) = (
        to_f64(&with.anchor_levels[0].logits),
        to_f64(&without.anchor_levels[0].logits),
    );
    assert_eq!(l0.len(), l0_without.len());
    assert!(l0
        .iter()
        .zip(&l0_without)
        .any(|(a, b)| (a - b).abs() > 1e-6));
    let grads = sum_all(&with).backward();
    let n = assert_all_grads(&model, &grads);
    assert!(n > 50, "only {n} parameters visited");
}

#[test]
fn ablations_run_and_train() {
    let variants = [
        tiny_config().with_anchor_mode(AnchorMode::Uniform),
        tiny_config().with_scf_decomposition(ScfDecomposition::Scalar),
        tiny_config().with_scf_learning(ScfLearning::Regression),
        tiny_config().with_propagation(false),
    ];
    for (i, cfg) in variants.iter().enumerate() {
        let (model, out) = run::<AD>(cfg, 1, 10 + i as u64);
        match i {
            0 => {
                assert_eq!(out.anchor_levels.len(), 1);
                assert_eq!(
                    out.anchor_levels[0].coords.len(),
                    chain_anchor_count(16, &cfg.keep_ratios)
                );
            }
            1 => {
                let s = out.scf.as_ref().unwrap();
                assert!(s.vertical.is_none() && s.s_vertical.is_empty());
                assert_eq!(s.planar.dims()[1], 9);
            }
            2 => {
                let s = out.scf.as_ref().unwrap();
                assert_eq!(s.planar.dims()[1], 1);
                assert_eq!(s.vertical.as_ref().unwrap().dims()[1], 1);
            }
            _ => {
                assert!(out.scf.is_none());
                let anchors = out.anchor_levels[2].kept.len();
                assert_eq!(out.out.coords.len(), anchors);
            }
        }
        let grads = sum_all(&out).backward();
        assert_all_grads(&model, &grads);
    }
}

#[test]
fn subvoxel_output_predicts_the_children_at_full_resolution() {
    let half = tiny_config();
    let full = tiny_config().with_output(OutputResolution::SubVoxel);
    let (_, h) = run::<NB>(&half, 2, 7);
    let (model, out) = run::<AD>(&full, 2, 7);
    assert_eq!(out.out.upsample, 1);
    assert_eq!(out.out.out_dims, FULL_DIMS);
    let parents = h.out.coords.len();
    let stat = |k: &str| out.out.stats.iter().find(|(n, _)| n == k).map(|s| s.1);
    let n_final = stat("final").expect("final stat");
    assert_eq!(out.out.coords.len(), 8 * n_final);
    assert_eq!(stat("final_full_res"), Some(8 * n_final));
    assert_eq!(out.out.logits.dims(), [8 * n_final, 6]);
    assert!(parents > 0 && n_final > 0);
    // Rows 8i..8i+8 are the children of one 1/2-res voxel, in split order 4dx + 2dy + dz, and all
    // of them lie inside the full grid.
    for (i, ch) in out.out.coords.chunks(8).enumerate() {
        let p = [ch[0][0], ch[0][1] / 2, ch[0][2] / 2, ch[0][3] / 2];
        for (j, c) in ch.iter().enumerate() {
            let (dx, dy, dz) = ((j >> 2) & 1, (j >> 1) & 1, j & 1);
            assert_eq!(
                *c,
                [
                    p[0],
                    2 * p[1] + dx as i32,
                    2 * p[2] + dy as i32,
                    2 * p[3] + dz as i32
                ],
                "row {i}"
            );
            assert!((0..3).all(|a| (c[a + 1] as usize) < FULL_DIMS[a]));
        }
    }
    // The loss is taken at full resolution: the final labels are the full-resolution labels.
    let device = Default::default();
    let batch = batch::<AD>(2, 7, &device);
    let t = occ_model::sparseocc_pp::pp_targets(&out, &batch, &full).expect("targets");
    let target = batch.target.as_ref().unwrap();
    for (c, &l) in out.out.coords.iter().zip(&t.labels) {
        let [b, x, y, z] = c.map(|v| v as usize);
        assert_eq!(l, target[b][(x * FULL_DIMS[1] + y) * FULL_DIMS[2] + z]);
    }
    let losses = out.losses(&batch, &full, &[1.0; 6]).expect("losses");
    assert!(losses.iter().any(|(n, _)| n.to_string() == "occ.ce"));
    let grads = sum_all(&out).backward();
    assert_all_grads(&model, &grads);
}

/// Literal Algorithm 1 on a dense grid: for each s_j, max-pool (dilate) the anchors with s = -s_j by
/// the planar and vertical kernels, union with the anchors.
fn algorithm1_dense(
    anchors: &[[i32; 3]],
    sp: &[i32],
    sv: &[i32],
    dims: [usize; 3],
    s_max: i32,
) -> Vec<u8> {
    let [nx, ny, nz] = dims;
    let idx = |x: i64, y: i64, z: i64| -> Option<usize> {
        (x >= 0 && y >= 0 && z >= 0 && (x as usize) < nx && (y as usize) < ny && (z as usize) < nz)
            .then(|| (x as usize * ny + y as usize) * nz + z as usize)
    };
    let mut m = vec![0u8; nx * ny * nz];
    for a in anchors {
        m[idx(a[0] as i64, a[1] as i64, a[2] as i64).unwrap()] = 1;
    }
    for sj in 1..=s_max {
        // Planar component: kernel [2sj+1, 2sj+1, 1]; vertical: [1, 1, 2sj+1].
        for (which, s) in [(0, sp), (1, sv)] {
            let mut mj = vec![0u8; nx * ny * nz];
            for (a, &sa) in anchors.iter().zip(s) {
                if sa == -sj {
                    mj[idx(a[0] as i64, a[1] as i64, a[2] as i64).unwrap()] = 1;
                }
            }
            let r = sj as i64;
            let (rx, ry, rz) = if which == 0 { (r, r, 0) } else { (0, 0, r) };
            for x in 0..nx as i64 {
                for y in 0..ny as i64 {
                    for z in 0..nz as i64 {
                        let mut any = false;
                        for dx in -rx..=rx {
                            for dy in -ry..=ry {
                                for dz in -rz..=rz {
                                    if let Some(i) = idx(x + dx, y + dy, z + dz) {
                                        any |= mj[i] == 1;
                                    }
                                }
                            }
                        }
                        if any {
                            m[idx(x, y, z).unwrap()] = 1;
                        }
                    }
                }
            }
        }
    }
    m
}

#[test]
fn propagation_inside_the_model_is_algorithm1() {
    let cfg = tiny_config();
    let device = Default::default();
    // Every parameter re-drawn from a fixed seed: the tests of this binary share burn's RNG across
    // threads, so a plain init is not reproducible (and once in a while left no interior anchor).
    let mut model: SparseOccPP<NB> = seeded_init(cfg.try_init(&device).unwrap(), 2024);
    // Spread the SCF predictions over all bins, with a bias towards the negative (interior) ones, so
    // that many anchors are interior.
    let head = model.scf.as_mut().unwrap();
    for mlp in [&mut head.planar, head.vertical.as_mut().unwrap()] {
        let w = mlp.fc2.weight.val();
        let dims = w.dims();
        mlp.fc2.weight = Param::from_tensor(randn::<NB, 2>(dims, 77, &device) * 5.0);
        let k = dims[1];
        let s_max = (k - 1) / 2;
        // Bins 0..s_max-1 are s = -s_max..-2.
        let bias: Vec<f64> = (0..k)
            .map(|i| if i + 1 < s_max { 8.0 } else { 0.0 })
            .collect();
        mlp.fc2.bias = Some(Param::from_tensor(Tensor::<NB, 1>::from_data(
            TensorData::new(bias, [k]),
            &device,
        )));
    }
    let bsz = 2;
    let batch = batch::<NB>(bsz, 3, &device);
    let feats = features::<NB>(bsz, 30, &device);
    let out = model.forward(&feats, &STRIDES, &batch).unwrap();
    let scf = out.scf.as_ref().unwrap();
    eprintln!(
        "s_planar {:?}\ns_vertical {:?}",
        scf.s_planar, scf.s_vertical
    );
    assert!(
        scf.s_planar.iter().any(|&s| s < -1),
        "no interior planar anchor"
    );
    assert!(
        scf.s_vertical.iter().any(|&s| s < 0),
        "no interior vertical anchor"
    );
    let dims = scf.dims;
    let mut total_new = 0;
    for b in 0..bsz as i32 {
        let rows: Vec<usize> = (0..scf.coords.len())
            .filter(|&i| scf.coords[i][0] == b)
            .collect();
        let anchors: Vec<[i32; 3]> = rows
            .iter()
            .map(|&i| [scf.coords[i][1], scf.coords[i][2], scf.coords[i][3]])
            .collect();
        let sp: Vec<i32> = rows.iter().map(|&i| scf.s_planar[i]).collect();
        let sv: Vec<i32> = rows.iter().map(|&i| scf.s_vertical[i]).collect();
        // occ_geometry's Algorithm 1 on this item's anchors.
        let prop = occ_geometry::scf::propagate(&anchors, &sp, &sv, dims).unwrap();
        total_new += prop.new_voxels.len();
        let mut expected: Vec<[i32; 3]> = anchors.clone();
        expected.extend(prop.new_voxels.iter().copied());
        expected.sort_unstable();
        let mut got: Vec<[i32; 3]> = out
            .out
            .coords
            .iter()
            .filter(|c| c[0] == b)
            .map(|c| [c[1], c[2], c[3]])
            .collect();
        got.sort_unstable();
        assert_eq!(got, expected, "item {b}");
        // And the literal dense Algorithm 1.
        let dense = algorithm1_dense(&anchors, &sp, &sv, dims, 4);
        let mut dense_sites = Vec::new();
        for (i, &m) in dense.iter().enumerate() {
            if m == 1 {
                let z = i % dims[2];
                let y = (i / dims[2]) % dims[1];
                let x = i / (dims[2] * dims[1]);
                dense_sites.push([x as i32, y as i32, z as i32]);
            }
        }
        assert_eq!(got, dense_sites, "item {b} vs dense Algorithm 1");
    }
    let stat = out
        .out
        .stats
        .iter()
        .find(|(n, _)| n == "propagated_new")
        .unwrap()
        .1;
    assert_eq!(stat, total_new);
    assert!(total_new > 0);
}

#[test]
fn anchor_topk_keeps_the_best_scores_and_splits_them() {
    let cfg = tiny_config().with_keep_ratios(vec![0.5, 0.3, 0.25]);
    let (_, out) = run::<NB>(&cfg, 2, 4);
    let levels = &out.anchor_levels;
    let mut n_item = 16usize;
    for (r, lvl) in levels.iter().enumerate() {
        let k = occ_model::sparseocc_pp::anchors::keep_count(n_item, cfg.keep_ratios[r]);
        let scores = occupancy_score(&lvl.logits);
        for b in 0..2 {
            let rows: Vec<usize> = (0..lvl.coords.len())
                .filter(|&i| lvl.coords[i][0] == b)
                .collect();
            assert_eq!(rows.len(), n_item, "level {r} item {b} candidates");
            let kept: Vec<usize> = lvl
                .kept
                .iter()
                .copied()
                .filter(|&i| lvl.coords[i][0] == b)
                .collect();
            assert_eq!(kept.len(), k, "level {r} item {b} kept");
            // Every kept score >= every dropped score.
            let min_kept = kept
                .iter()
                .map(|&i| scores[i])
                .fold(f32::INFINITY, f32::min);
            let max_dropped = rows
                .iter()
                .filter(|i| !kept.contains(i))
                .map(|&i| scores[i])
                .fold(f32::NEG_INFINITY, f32::max);
            assert!(
                min_kept >= max_dropped,
                "level {r}: {min_kept} < {max_dropped}"
            );
        }
        // Candidates of the next level are exactly the children of the kept voxels.
        if r + 1 < levels.len() {
            let mut children: Vec<[i32; 4]> = lvl
                .kept
                .iter()
                .flat_map(|&i| {
                    let c = lvl.coords[i];
                    (0..8).map(move |j| {
                        [
                            c[0],
                            2 * c[1] + (j >> 2),
                            2 * c[2] + ((j >> 1) & 1),
                            2 * c[3] + (j & 1),
                        ]
                    })
                })
                .collect();
            children.sort_unstable();
            let mut next = levels[r + 1].coords.clone();
            next.sort_unstable();
            assert_eq!(children, next);
        }
        n_item = 8 * k;
    }
    // The anchors are the kept level-2 voxels.
    let l2 = &levels[2];
    let mut kept: Vec<[i32; 4]> = l2.kept.iter().map(|&i| l2.coords[i]).collect();
    kept.sort_unstable();
    let mut anchors = out.scf.as_ref().unwrap().coords.clone();
    anchors.sort_unstable();
    assert_eq!(kept, anchors);
}

#[test]
fn bad_inputs_are_errors() {
    let cfg = tiny_config();
    let device = Default::default();
    let model: SparseOccPP<NB> = cfg.init(&device);
    let batch = batch::<NB>(1, 5, &device);
    let feats = features::<NB>(1, 50, &device);
    assert!(model.forward(&feats[..1], &STRIDES[..1], &batch).is_err());
    let wrong = vec![feats[0].clone(), feats[0].clone().narrow(1, 0, 4)];
    assert!(model.forward(&wrong, &STRIDES, &batch).is_err());
    let mut b2 = batch.clone();
    b2.grid.dims = [16, 16, 8];
    assert!(model.forward(&feats, &STRIDES, &b2).is_err());
    let bad = tiny_config().with_dca_heads(3);
    assert!(bad.validate().is_err());
    let mut odd = tiny_config();
    odd.full_dims = [30, 32, 8];
    assert!(odd.validate().is_err());
    let bad: SparseOccPP<NB> = odd.init(&device);
    assert!(bad.forward(&feats, &STRIDES, &batch).is_err());
}

/// The depth gate (not in the paper, `depth_gate = true`): the depth map has one logit per bin at the
/// finest feature level, every parameter (the depth head included) gets a gradient through the gated
/// DCA, and the `depth` loss term appears exactly when the batch carries LiDAR points.
#[test]
fn depth_gate_is_trained_by_the_gated_attention_and_the_lidar_depth() {
    let cfg = tiny_config()
        .with_depth_gate(true)
        .with_depth_dbound([0.5, 8.0, 0.5]);
    let device = Default::default();
    let model: SparseOccPP<AD> = cfg.try_init(&device).expect("valid config");
    let mut batch = batch::<AD>(2, 31, &device);
    let feats = features::<AD>(2, 131, &device);
    let out = model.forward(&feats, &STRIDES, &batch).expect("forward");
    let depth = out.depth.as_ref().expect("depth map");
    let (h, w) = (IMG_HW.0 / STRIDES[0], IMG_HW.1 / STRIDES[0]);
    assert_eq!(depth.logits.dims(), [4, 15, h, w]);
    let grads = sum_all(&out).backward();
    let n = assert_all_grads(&model, &grads);
    assert!(n > 50, "only {n} parameters visited");

    let weights = vec![1.0; cfg.num_classes];
    let names = |o: &PPOutput<AD>, b: &occ_model::Batch<AD>| -> Vec<String> {
        o.losses(b, &cfg, &weights)
            .unwrap()
            .into_iter()
            .map(|(n, _)| n.to_string())
            .collect()
    };
    assert!(!names(&out, &batch).contains(&"depth".to_string()));
    // Points on the ground slab and on a wall in front of both cameras.
    let pts: Vec<[f32; 3]> = (0..200)
        .map(|i| {
            let y = -3.0 + 0.03 * i as f32;
            if i % 2 == 0 {
                [5.0, y, -0.2 + 0.004 * i as f32]
            } else {
                [1.0 + 0.02 * i as f32, y, -0.7]
            }
        })
        .collect();
    batch.points = Some(vec![pts.clone(), pts]);
    let losses = out.losses(&batch, &cfg, &weights).unwrap();
    let (_, d) = losses
        .iter()
        .find(|(n, _)| n.to_string() == "depth")
        .expect("depth term with points");
    let d: f64 = d.clone().into_scalar();
    assert!(d.is_finite() && d > 0.0, "{d}");
    assert!(names(&out, &batch).contains(&"occ.ce".to_string()));
    // The paper model has no depth head and ignores points.
    let (_, plain) = run::<AD>(&tiny_config(), 2, 31);
    assert!(plain.depth.is_none());
    assert!(!names(&plain, &batch).contains(&"depth".to_string()));
}

/// `anchor_unknown_as_empty` (not in the paper): the anchor terms equal `occ_loss` on the candidates
/// with every ignored label (255) replaced by empty; the final-voxel terms are unchanged.
#[test]
fn anchor_unknown_as_empty_supervises_ignored_candidates_as_empty() {
    let cfg = tiny_config();
    let device = Default::default();
    let model: SparseOccPP<NB> = cfg.try_init(&device).unwrap();
    let mut batch = batch::<NB>(1, 41, &device);
    // An unobserved block (x < 16: a whole 1/8 voxel column and its children) is ignored.
    let [_, ny, nz] = FULL_DIMS;
    for t in batch.target.as_mut().unwrap() {
        t[..16 * ny * nz].iter_mut().for_each(|l| *l = 255);
    }
    let feats = features::<NB>(1, 141, &device);
    let out = model.forward(&feats, &STRIDES, &batch).unwrap();
    let weights: Vec<f64> = (0..cfg.num_classes).map(|c| 1.0 + 0.1 * c as f64).collect();
    let as_map = |l: Vec<(LossKey, Tensor<NB, 1>)>| -> Vec<(String, f64)> {
        l.into_iter()
            .map(|(n, t)| (n.to_string(), t.into_scalar()))
            .collect()
    };
    let plain = as_map(out.losses(&batch, &cfg, &weights).unwrap());
    let cfg_ue = cfg.clone().with_anchor_unknown_as_empty(true);
    let ue = as_map(out.losses(&batch, &cfg_ue, &weights).unwrap());
    let targets = occ_model::sparseocc_pp::pp_targets(&out, &batch, &cfg).unwrap();
    let levels_with_unknown = targets
        .anchor_labels
        .iter()
        .filter(|l| l.contains(&255))
        .count();
    assert!(
        levels_with_unknown > 0,
        "no ignored candidate in the test scene"
    );
    let mut changed = 0;
    for ((n0, v0), (n1, v1)) in plain.iter().zip(&ue) {
        assert_eq!(n0, n1);
        if let Some(rest) = n0.strip_prefix("anchor") {
            let level: usize = rest[..1].parse().unwrap();
            let labels = &targets.anchor_labels[level];
            let mapped: Vec<u8> = labels
                .iter()
                .map(|&l| if l == 255 { 0 } else { l })
                .collect();
            let term = &n0[n0.find('.').unwrap() + 1..];
            let want: f64 = occ_model::loss::occ_loss(
                out.anchor_levels[level].logits.clone(),
                &mapped,
                &weights,
            )
            .unwrap()
            .into_iter()
            .find(|(n, _)| n.as_str() == term)
            .unwrap()
            .1
            .into_scalar();
            assert!((v1 - want).abs() < 1e-9, "{n0}: {v1} vs {want}");
            changed += usize::from((v1 - v0).abs() > 1e-9);
        } else {
            assert_eq!(v0, v1, "{n0} must not change");
        }
    }
    assert!(
        changed >= 2 * levels_with_unknown,
        "only {changed} anchor terms changed"
    );
}

/// The image semantic head (not in the paper, `sem2d_aux = true`): one logit per class at the finest
/// feature level; the `sem2d` loss term appears exactly when the batch carries LiDAR points, and it
/// sends a gradient into the image features it reads (its only purpose).
#[test]
fn sem2d_aux_supervises_the_finest_image_features() {
    let cfg = tiny_config().with_sem2d_aux(true);
    let device = Default::default();
    let model: SparseOccPP<AD> = cfg.try_init(&device).expect("valid config");
    let mut batch = batch::<AD>(2, 33, &device);
    let mut feats = features::<AD>(2, 133, &device);
    feats[0] = feats[0].clone().detach().require_grad();
    let out = model.forward(&feats, &STRIDES, &batch).expect("forward");
    let sem = out.sem2d.as_ref().expect("image class logits");
    let (h, w) = (IMG_HW.0 / STRIDES[0], IMG_HW.1 / STRIDES[0]);
    assert_eq!(sem.logits.dims(), [4, cfg.num_classes, h, w]);
    let weights = vec![1.0; cfg.num_classes];
    let term = |b: &occ_model::Batch<AD>| {
        out.losses(b, &cfg, &weights)
            .unwrap()
            .into_iter()
            .find(|(n, _)| n.to_string() == "sem2d")
            .map(|(_, l)| l)
    };
    assert!(term(&batch).is_none(), "sem2d term without points");
    // Points spread over the whole grid volume in front of the cameras: some land in labelled voxels.
    let g = batch.grid;
    let pts: Vec<[f32; 3]> = (0..2000)
        .map(|i| {
            let f = |k: usize, n: usize| ((i * k) % n) as f64 / n as f64;
            std::array::from_fn(|a| {
                let span = g.dims[a] as f64 * g.voxel_size_m;
                (g.origin_m[a] + span * f([7, 13, 29][a], [97, 89, 83][a])) as f32
            })
        })
        .collect();
    batch.points = Some(vec![pts.clone(), pts]);
    let l = term(&batch).expect("sem2d term with points");
    let v: f64 = l.clone().into_scalar();
    assert!(v.is_finite() && v > 0.0, "{v}");
    let grads = l.backward();
    let g0 = feats[0]
        .grad(&grads)
        .expect("gradient into the image features");
    let gsum: f64 = g0.abs().sum().into_scalar();
    assert!(gsum > 0.0);
    // The paper model has no such head.
    let (_, plain) = run::<AD>(&tiny_config(), 2, 33);
    assert!(plain.sem2d.is_none());
}
