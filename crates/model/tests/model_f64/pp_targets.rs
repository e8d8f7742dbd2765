//! `pp_targets` against brute force (label downsampling rule, literal Algorithm 2), the shared
//! reference fixtures (downsampling, SCF ground truth, propagation) and hand cases.

use crate::pp_common;

use occ_labels::{downsample_monoscene, monoscene_block_label};
use occ_model::sparseocc_pp::propagation::propagated_voxels;
use occ_model::sparseocc_pp::scf_head::{scf_isotropic, scf_targets, ScfDecomposition};
use occ_model::sparseocc_pp::{pp_targets, SparseOccPP, SparseOccPPConfig};
use pp_common::*;
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;

/// The docs/formats.md §2.6 rule written out directly: counts of 0 and 255, then the majority label in 1..=254
/// with ties to the smaller id.
fn brute_block(labels: &[u8]) -> u8 {
    let n0 = labels.iter().filter(|&&l| l == 0).count();
    let n255 = labels.iter().filter(|&&l| l == 255).count();
    if (n0 + n255) as f64 > 0.95 * labels.len() as f64 {
        return if n0 > n255 { 0 } else { 255 };
    }
    let mut sem: Vec<u8> = labels
        .iter()
        .copied()
        .filter(|&l| l != 0 && l != 255)
        .collect();
    sem.sort_unstable();
    let mut best = (0usize, 0u8);
    let mut i = 0;
    while i < sem.len() {
        let j = sem[i..].iter().take_while(|&&l| l == sem[i]).count();
        if j > best.0 {
            best = (j, sem[i]);
        }
        i += j;
    }
    best.1
}

fn brute_label(full: &[u8], full_dims: [usize; 3], f: usize, c: [i32; 4]) -> u8 {
    let mut v = Vec::new();
    for dx in 0..f {
        for dy in 0..f {
            for dz in 0..f {
                let (x, y, z) = (
                    c[1] as usize * f + dx,
                    c[2] as usize * f + dy,
                    c[3] as usize * f + dz,
                );
                v.push(full[(x * full_dims[1] + y) * full_dims[2] + z]);
            }
        }
    }
    brute_block(&v)
}

/// Literal Algorithm 2 at one voxel: for s_j = 1..=s_max, average-pool with kernel `k` (radius per
/// axis `r·s_j`), zero padding counted; homogeneous → ±s_j (later s_j overwrite).
fn brute_scf(occ: &[u8], dims: [usize; 3], p: [usize; 3], radius: [usize; 3], s_max: i32) -> i32 {
    let own = occ[(p[0] * dims[1] + p[1]) * dims[2] + p[2]] as f64;
    let mut out = 0;
    for sj in 1..=s_max {
        let r = radius.map(|a| a * sj as usize);
        let (mut sum, mut vol) = (0.0, 0.0);
        for dx in -(r[0] as i64)..=r[0] as i64 {
            for dy in -(r[1] as i64)..=r[1] as i64 {
                for dz in -(r[2] as i64)..=r[2] as i64 {
                    vol += 1.0;
                    let q = [p[0] as i64 + dx, p[1] as i64 + dy, p[2] as i64 + dz];
                    if (0..3).all(|a| q[a] >= 0 && (q[a] as usize) < dims[a]) {
                        sum += occ
                            [(q[0] as usize * dims[1] + q[1] as usize) * dims[2] + q[2] as usize]
                            as f64;
                    }
                }
            }
        }
        if sum / vol == own {
            out = if own == 1.0 { -sj } else { sj };
        }
    }
    out
}

#[test]
fn block_rule_hand_cases() {
    assert_eq!(
        monoscene_block_label([0, 0, 0, 0, 255, 255, 255, 255].into_iter(), 2),
        255
    );
    assert_eq!(
        monoscene_block_label([0, 0, 0, 0, 0, 255, 255, 255].into_iter(), 2),
        0
    );
    assert_eq!(
        monoscene_block_label([3, 3, 2, 2, 0, 0, 0, 0].into_iter(), 2),
        2
    );
    assert_eq!(
        monoscene_block_label([0, 0, 0, 0, 0, 0, 0, 7].into_iter(), 2),
        7
    );
    let mut b = vec![0u8; 61];
    b.extend([5, 5, 5]);
    assert_eq!(monoscene_block_label(b.into_iter(), 4), 0);
    let mut b = vec![0u8; 60];
    b.extend([5, 5, 4, 255]);
    assert_eq!(monoscene_block_label(b.into_iter(), 4), 0);
    let mut b = vec![0u8; 59];
    b.extend([5, 5, 5, 4, 255]);
    assert_eq!(monoscene_block_label(b.into_iter(), 4), 5);
}

#[test]
fn targets_match_brute_force() {
    let cfg = SparseOccPPConfig::new(6, 8, FEAT_C, FULL_DIMS)
        .with_num_feature_levels(2)
        .with_dca_heads(2)
        .with_s_max_planar(4)
        .with_s_max_vertical(2);
    let device = Default::default();
    let model: SparseOccPP<NB> = cfg.try_init(&device).unwrap();
    let bsz = 2;
    let batch = batch::<NB>(bsz, 8, &device);
    let feats = features::<NB>(bsz, 80, &device);
    let out = model.forward(&feats, &STRIDES, &batch).unwrap();
    let t = pp_targets(&out, &batch, &cfg).unwrap();
    let full = batch.target.as_ref().unwrap();
    assert_eq!(t.labels.len(), out.out.coords.len());
    for (c, &l) in out.out.coords.iter().zip(&t.labels) {
        assert_eq!(
            l,
            brute_label(&full[c[0] as usize], FULL_DIMS, 2, *c),
            "{c:?}"
        );
    }
    assert!(t.labels.iter().any(|&l| l != 0 && l != 255));
    assert_eq!(t.anchor_labels.len(), 3);
    for (lvl, labels) in out.anchor_levels.iter().zip(&t.anchor_labels) {
        assert_eq!(labels.len(), lvl.coords.len());
        for (c, &l) in lvl.coords.iter().zip(labels) {
            assert_eq!(
                l,
                brute_label(&full[c[0] as usize], FULL_DIMS, lvl.factor, *c)
            );
        }
    }
    // SCF: literal Algorithm 2 on the brute-force half-resolution occupancy.
    let scf = out.scf.as_ref().unwrap();
    let st = t.scf.as_ref().unwrap();
    let half = [16, 16, 4];
    let occ: Vec<Vec<u8>> = full
        .iter()
        .map(|f| {
            let mut o = vec![0u8; 16 * 16 * 4];
            for x in 0..16 {
                for y in 0..16 {
                    for z in 0..4 {
                        let l = brute_label(f, FULL_DIMS, 2, [0, x, y, z]);
                        o[(x as usize * 16 + y as usize) * 4 + z as usize] =
                            u8::from(l != 0 && l != 255);
                    }
                }
            }
            o
        })
        .collect();
    let vertical = st.vertical.as_ref().unwrap();
    let mut ignored = 0;
    for (i, c) in scf.coords.iter().enumerate() {
        let b = c[0] as usize;
        let p = [c[1] as usize, c[2] as usize, c[3] as usize];
        if brute_label(&full[b], FULL_DIMS, 2, *c) == 255 {
            assert_eq!((st.planar[i], vertical[i]), (255, 255));
            ignored += 1;
            continue;
        }
        let sp = brute_scf(&occ[b], half, p, [1, 1, 0], 4);
        let sv = brute_scf(&occ[b], half, p, [0, 0, 1], 2);
        assert_eq!(st.planar[i] as i32, sp + 4, "planar at {c:?}");
        assert_eq!(vertical[i] as i32, sv + 2, "vertical at {c:?}");
    }
    assert!(ignored < scf.coords.len());
    // No target → typed error.
    let mut nb = batch.clone();
    nb.target = None;
    assert!(pp_targets(&out, &nb, &cfg).is_err());
}

#[test]
fn isotropic_scf_matches_literal_algorithm2() {
    let mut rng = ChaCha8Rng::seed_from_u64(3);
    let dims = [12, 10, 6];
    for _ in 0..3 {
        let mut occ = vec![0u8; 12 * 10 * 6];
        // A few solid boxes so interior distances > 1 exist.
        for _ in 0..4 {
            let (x0, y0, z0) = (
                rng.random_range(0..8),
                rng.random_range(0..6),
                rng.random_range(0..3),
            );
            for x in x0..(x0 + 5).min(12) {
                for y in y0..(y0 + 5).min(10) {
                    for z in z0..(z0 + 4).min(6) {
                        occ[(x * 10 + y) * 6 + z] = 1;
                    }
                }
            }
        }
        let got = scf_isotropic(&occ, dims, 3).unwrap();
        let mut saw_interior = false;
        for x in 0..12 {
            for y in 0..10 {
                for z in 0..6 {
                    let e = brute_scf(&occ, dims, [x, y, z], [1, 1, 1], 3);
                    saw_interior |= e < 0;
                    assert_eq!(got[(x * 10 + y) * 6 + z] as i32, e, "at {x},{y},{z}");
                }
            }
        }
        assert!(saw_interior);
    }
    assert!(scf_isotropic(&[0u8; 5], dims, 3).is_err());
}

#[test]
fn downsampling_matches_fixture() {
    let Some((dir, files)) = reference_fixtures() else {
        return;
    };
    let mut cases = 0;
    for name in files.keys() {
        let Some(stem) = name.strip_prefix("downsample_in") else {
            continue;
        };
        let (shape, input) = read_npy::<u8>(&dir.join(name));
        let (oshape, expected) = read_npy::<u8>(&dir.join(format!("downsample_out{stem}")));
        let dims: [usize; 3] = shape.try_into().unwrap();
        let factor = dims[0] / oshape[0];
        assert_eq!(
            downsample_monoscene(&input, dims, factor).unwrap(),
            expected,
            "{name}"
        );
        cases += 1;
    }
    assert!(cases > 0, "no downsample_in* fixture in the manifest");
}

#[test]
fn scf_targets_match_fixture() {
    let Some((dir, files)) = reference_fixtures() else {
        return;
    };
    let mut cases = 0;
    for name in files.keys() {
        let Some(stem) = name.strip_prefix("scf_occupancy") else {
            continue;
        };
        let (shape, occ) = read_npy::<u8>(&dir.join(name));
        let (_, planar) = read_npy::<i8>(&dir.join(format!("scf_gt_planar{stem}")));
        let (_, vertical) = read_npy::<i8>(&dir.join(format!("scf_gt_vertical{stem}")));
        let dims: [usize; 3] = shape.try_into().unwrap();
        // Every voxel is an anchor; labels are the occupancy itself (1 = some class).
        let mut coords = Vec::new();
        for x in 0..dims[0] {
            for y in 0..dims[1] {
                for z in 0..dims[2] {
                    coords.push([0, x as i32, y as i32, z as i32]);
                }
            }
        }
        let t = scf_targets(&coords, &[occ], dims, ScfDecomposition::Decomposed, 10, 3).unwrap();
        let exp_p: Vec<u8> = planar.iter().map(|&s| (s as i32 + 10) as u8).collect();
        let exp_v: Vec<u8> = vertical.iter().map(|&s| (s as i32 + 3) as u8).collect();
        assert_eq!(t.planar, exp_p, "{name} planar");
        assert_eq!(t.vertical.unwrap(), exp_v, "{name} vertical");
        cases += 1;
    }
    assert!(cases > 0, "no scf_occupancy* fixture in the manifest");
}

#[test]
fn propagation_matches_fixture() {
    let Some((dir, files)) = reference_fixtures() else {
        return;
    };
    let mut cases = 0;
    for name in files.keys() {
        let Some(stem) = name.strip_prefix("prop_anchors") else {
            continue;
        };
        let (_, a) = read_npy::<i32>(&dir.join(name));
        // Per-anchor arrays are named without the `_xyz` layout tag.
        let pick = |prefix: &str| {
            [
                format!("{prefix}{stem}"),
                format!("{prefix}{}", stem.replace("_xyz", "")),
            ]
            .into_iter()
            .find(|n| files.contains_key(n))
            .unwrap_or_else(|| panic!("no {prefix}* file for {name} in the manifest"))
        };
        let (_, sp) = read_npy::<i32>(&dir.join(pick("prop_s_planar")));
        let (_, sv) = read_npy::<i32>(&dir.join(pick("prop_s_vertical")));
        let (shape, expected) = read_npy::<u8>(&dir.join(format!("prop_result{stem}")));
        let dims: [usize; 3] = shape.try_into().unwrap();
        let anchors: Vec<[i32; 4]> = a.chunks(3).map(|c| [0, c[0], c[1], c[2]]).collect();
        let new =
            propagated_voxels(&anchors, &sp, &sv, dims, ScfDecomposition::Decomposed).unwrap();
        let mut got = vec![0u8; expected.len()];
        for c in anchors.iter().chain(&new) {
            got[(c[1] as usize * dims[1] + c[2] as usize) * dims[2] + c[3] as usize] = 1;
        }
        assert_eq!(got, expected, "{name}");
        cases += 1;
    }
    assert!(cases > 0, "no prop_anchors* fixture in the manifest");
}
