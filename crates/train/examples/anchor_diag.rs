//! Diagnostic: how well a trained SparseOcc++ run's anchor levels cover the occupied voxels of a
//! dataset's frames, and what the final head predicts for each ground-truth class.
//!
//! `cargo run --release -p occ-train --example anchor_diag -- RUN_DIR DATA_DIR SEQ [FRAMES]`
mod common;

use burn::backend::NdArray;
use occ_model::sparseocc_pp::pp_targets;
use occ_train::dataset::collate;

type B = NdArray<f32>;

/// Argmax over dimension 1, flattened.
fn argmax1<const D: usize>(t: &burn::tensor::Tensor<B, D>) -> Result<Vec<i64>, String> {
    t.clone()
        .argmax(1)
        .into_data()
        .convert::<i64>()
        .to_vec()
        .map_err(|e| format!("{e:?}"))
}

fn main() -> Result<(), Box<dyn std::error::Error>> {
    let device = Default::default();
    let (cfg, grid, model, ds, frames) = common::open_run::<B>("anchor_diag", &device)?;
    let occ_model::Network::SparseOccPP(pp) = model.network()? else {
        return Err("not a SparseOcc++ run".into());
    };
    // Sampling-offset drift at level 0, whose queries are image-independent (learned embedding +
    // position code of every 1/8-resolution candidate): mean |offset| in feature pixels per image
    // level, trained (W·q + b) against the bias alone and against the initial ring's scale.
    {
        let a = &pp.anchors;
        let dims0 = a.level_dims(0);
        let coords = occ_sparse::full_grid_coords(1, dims0);
        let q = a.embed0.val() + a.pos.encode(&coords, dims0, &device);
        let dca = &a.stages[0].dca;
        let (off, _) = dca.sampling(q);
        let [n, m, l, p, _] = off.dims();
        let v: Vec<f32> = off
            .into_data()
            .convert::<f32>()
            .to_vec()
            .map_err(|e| format!("{e:?}"))?;
        let b: Vec<f32> = dca
            .sampling_offsets
            .bias
            .as_ref()
            .map(|b| {
                b.val()
                    .into_data()
                    .convert::<f32>()
                    .to_vec()
                    .unwrap_or_default()
            })
            .unwrap_or_default();
        for lv in 0..l {
            let (mut s, mut sb, mut mx) = (0.0f64, 0.0f64, 0.0f64);
            let mut cnt = 0usize;
            for qi in 0..n {
                for h in 0..m {
                    for pt in 0..p {
                        let i = (((qi * m + h) * l + lv) * p + pt) * 2;
                        let d = ((v[i] as f64).powi(2) + (v[i + 1] as f64).powi(2)).sqrt();
                        s += d;
                        mx = mx.max(d);
                        if qi == 0 {
                            let j = ((h * l + lv) * p + pt) * 2;
                            sb += ((b[j] as f64).powi(2) + (b[j + 1] as f64).powi(2)).sqrt();
                        }
                        cnt += 1;
                    }
                }
            }
            println!(
                "level-0 DCA offsets, image level {lv}: mean |offset| {:.2} feature px (max {:.2}); bias alone {:.2}",
                s / cnt.max(1) as f64,
                mx,
                sb / (m * p).max(1) as f64
            );
        }
    }
    let nc = cfg.model.num_classes;
    let mut conf = vec![vec![0usize; nc]; nc]; // final: gt x pred (final voxels only)
    let mut conf_l2 = vec![vec![0usize; nc]; nc]; // level-2 anchor logits on the kept anchors
    for i in 0..frames.min(ds.len()) {
        let s = ds.load::<rand_chacha::ChaCha8Rng>(i, None)?;
        let batch = collate::<B>(std::slice::from_ref(&s), grid, &device)?;
        let [b, v, c, h, w] = batch.images.dims();
        let feats = model
            .encoder
            .forward(batch.images.clone().reshape([b * v, c, h, w]));
        let strides = model.encoder.strides();
        let out = pp.forward(&feats, &strides, &batch)?;
        let t = pp_targets(&out, &batch, pp.config())?;
        let mut line = format!("frame {i}:");
        if let Some(dm) = &out.depth {
            let [_, _, h, w] = dm.logits.dims();
            let t = occ_model::lss::depth_targets(&batch, h, w, dm.stride, dm.dbound)?
                .unwrap_or_default();
            let am = argmax1(&dm.logits)?;
            let (mut n, mut ok1, mut ok3) = (0, 0, 0);
            for (&tt, &p) in t.iter().zip(&am) {
                if tt >= 0 {
                    n += 1;
                    ok1 += usize::from((tt - p).abs() <= 1);
                    ok3 += usize::from((tt - p).abs() <= 3);
                }
            }
            line += &format!(
                " depth: {n} px, argmax within 1 bin {:.2}, 3 bins {:.2};",
                ok1 as f64 / n.max(1) as f64,
                ok3 as f64 / n.max(1) as f64
            );
        }
        for (r, (lvl, labels)) in out.anchor_levels.iter().zip(&t.anchor_labels).enumerate() {
            let occ = |l: u8| l != 0 && l != 255;
            let n_occ = labels.iter().filter(|&&l| occ(l)).count();
            let kept_occ = lvl.kept.iter().filter(|&&k| occ(labels[k])).count();
            // Ground layer (z = 0) among kept, and occupied above it.
            let kept_z0 = lvl.kept.iter().filter(|&&k| lvl.coords[k][3] == 0).count();
            let occ_above = labels
                .iter()
                .zip(&lvl.coords)
                .filter(|(&l, c)| occ(l) && c[3] > 0)
                .count();
            let kept_occ_above = lvl
                .kept
                .iter()
                .filter(|&&k| occ(labels[k]) && lvl.coords[k][3] > 0)
                .count();
            let n_ign = labels.iter().filter(|&&l| l == 255).count();
            let kept_ign = lvl.kept.iter().filter(|&&k| labels[k] == 255).count();
            line += &format!(
                " | L{r} cand {} ignored {n_ign} kept {kept_ign} | occ {} kept {} kept_occ {} (z0 kept {}; occ above z0 {} kept {})",
                labels.len(),
                n_occ,
                lvl.kept.len(),
                kept_occ,
                kept_z0,
                occ_above,
                kept_occ_above
            );
        }
        line += &format!(" | stats {:?}", out.out.stats);
        if let (Some(pred), Some(tg)) = (&out.scf, &t.scf) {
            // Planar SCF: histogram of target and predicted signed distance (bin - s_max).
            let am = argmax1(&pred.planar)?;
            let sm = pred.s_max_planar as i64;
            let (mut ht, mut hp) = (
                vec![0usize; 2 * sm as usize + 1],
                vec![0usize; 2 * sm as usize + 1],
            );
            for (&t, &p) in tg.planar.iter().zip(&am) {
                if t != 255 {
                    ht[t as usize] += 1;
                    hp[p as usize] += 1;
                }
            }
            line += &format!(" | scf planar s=-{sm}..{sm}: target {ht:?} predicted {hp:?}");
            let neg_p = pred.s_planar.iter().filter(|&&v| v < 0).count();
            let neg_v = pred.s_vertical.iter().filter(|&&v| v < 0).count();
            let new = occ_model::sparseocc_pp::propagation::propagated_voxels(
                &pred.coords,
                &pred.s_planar,
                &pred.s_vertical,
                pred.dims,
                pred.decomposition,
            )?;
            let set: std::collections::HashSet<_> = pred.coords.iter().copied().collect();
            let (mut rmax, mut holes) = (0i32, 0usize);
            for (c, &sp) in pred.coords.iter().zip(&pred.s_planar) {
                if sp < 0 {
                    rmax = rmax.max(-sp);
                    for dx in -1..=1 {
                        for dy in -1..=1 {
                            let (x, y) = (c[1] + dx, c[2] + dy);
                            let inside = x >= 0
                                && y >= 0
                                && (x as usize) < pred.dims[0]
                                && (y as usize) < pred.dims[1];
                            if inside && !set.contains(&[c[0], x, y, c[3]]) {
                                holes += 1;
                            }
                        }
                    }
                }
            }
            line += &format!(
                " | decoded s<0: planar {neg_p} (max radius {rmax}, 3x3 neighbours not anchors {holes}) vertical {neg_v}; recomputed new voxels {}",
                new.len()
            );
        }
        println!("{line}");
        if let (Some(lvl), Some(labels)) = (out.anchor_levels.last(), t.anchor_labels.last()) {
            let am = argmax1(&lvl.logits)?;
            for &k in &lvl.kept {
                if labels[k] != 255 {
                    conf_l2[labels[k] as usize][am[k] as usize] += 1;
                }
            }
        }
        let pred = argmax1(&out.out.logits)?;
        if out.out.upsample == 1 && t.labels.len() == pred.len() && pred.len() % 8 == 0 {
            // Full-resolution children, 8 per final voxel in order: for the final voxels with a
            // valid occupied child of a non-ground class, the share of their valid children that
            // are occupied, and how many of them have every child predicted empty.
            let ground = [9usize, 10, 11, 12, 17];
            let (mut parents, mut occ_share, mut all_empty, mut child_occ_pred) = (0, 0.0, 0, 0);
            let (mut up_parents, mut up_all_empty, mut up_occ, mut up_pred_occ) = (0, 0, 0, 0);
            for ((lab, pr), cs) in t
                .labels
                .chunks(8)
                .zip(pred.chunks(8))
                .zip(out.out.coords.chunks(8))
            {
                if cs[0][3] >= 2 {
                    // the final voxel lies above the 1/2-resolution ground layer
                    let occ = lab.iter().filter(|&&l| l != 0 && l != 255).count();
                    if occ > 0 {
                        up_parents += 1;
                        up_occ += occ;
                        up_all_empty += usize::from(pr.iter().all(|&p| p == 0));
                        up_pred_occ += lab
                            .iter()
                            .zip(pr)
                            .filter(|(&l, &p)| l != 0 && l != 255 && p != 0)
                            .count();
                    }
                }
                let ng = lab
                    .iter()
                    .any(|&l| l != 0 && l != 255 && !ground.contains(&(l as usize)));
                if !ng {
                    continue;
                }
                parents += 1;
                let valid = lab.iter().filter(|&&l| l != 255).count();
                let occ = lab.iter().filter(|&&l| l != 0 && l != 255).count();
                occ_share += occ as f64 / valid.max(1) as f64;
                all_empty += usize::from(pr.iter().all(|&p| p == 0));
                child_occ_pred += pr.iter().filter(|&&p| p != 0).count();
            }
            println!(
                "frame {i}: final voxels with a valid non-ground occupied child: {parents}; mean share of their valid children occupied {:.2}; all 8 children predicted empty {all_empty}; children predicted occupied {child_occ_pred}",
                occ_share / parents.max(1) as f64
            );
            println!(
                "frame {i}: final voxels above the 1/2-res ground layer with a valid occupied child: {up_parents} ({up_occ} such children, {up_pred_occ} predicted occupied); all 8 children predicted empty {up_all_empty}"
            );
        }
        for (&g, &p) in t.labels.iter().zip(&pred) {
            if g != 255 {
                conf[g as usize][p as usize] += 1;
            }
        }
    }
    for (name, conf) in [
        ("level-2 anchors (anchor logits)", &conf_l2),
        ("final voxels", &conf),
    ] {
        println!("{name}: gt class -> total, predicted empty, predicted right, top other");
        for (g, row) in conf.iter().enumerate() {
            let tot: usize = row.iter().sum();
            if tot == 0 {
                continue;
            }
            let (best, n) = row
                .iter()
                .enumerate()
                .filter(|(p, _)| *p != g && *p != 0)
                .max_by_key(|(_, &n)| n)
                .unwrap_or((0, &0));
            println!(
                "  {g:2} -> {tot:6} empty {:6} right {:6} other {best}:{n}",
                row[0], row[g]
            );
        }
    }
    Ok(())
}
