//! Folder scoring end to end on temporary dataset folders written with the occ-data writers, and
//! on the real samples in `$SPARSEOCC_REALDATA` (an external folder found by `occ_testdata`; the
//! tests that need it print a skip line without it).

mod common;

use common::{counting_frames, gt_and_pred, with_sequences};
use occ_data::formats::npy::npy_bytes;
use occ_data::formats::occ3d::{read_labels_npz, write_labels_npz, Occ3dLabels};
use occ_data::formats::semantic_kitti::{
    read_packed_bits, write_label_raw, write_packed_bits, write_prediction, FrameId, KittiPaths,
    LearningMap, NUM_VOXELS,
};
use occ_eval::{
    score_occ3d_folder, score_semantic_kitti_folder, EvalError, EvalMask, Evaluator, FolderOptions,
    Occ3dMask, Protocol,
};
use occ_testdata::TempDir;
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;
use std::io::Write;
use std::path::Path;

/// Real `.invalid` masks of the sample (sequence, frame, unpacked mask), found by listing; `None`
/// (skip reported) without the real-data folder.
fn real_invalid_masks() -> Option<Vec<(String, String, Vec<u8>)>> {
    let root = occ_testdata::realdata()?.join("semantickitti");
    let mut out = Vec::new();
    let mut seqs: Vec<_> = std::fs::read_dir(root.join("sequences"))
        .expect("realdata semantickitti/sequences")
        .map(|e| e.unwrap().path())
        .collect();
    seqs.sort();
    for seq in seqs {
        let mut files: Vec<_> = std::fs::read_dir(seq.join("voxels"))
            .map(|rd| rd.map(|e| e.unwrap().path()).collect())
            .unwrap_or_default();
        files.sort();
        for f in files
            .into_iter()
            .filter(|f| f.extension().is_some_and(|e| e == "invalid"))
        {
            let mask = read_packed_bits(&f, NUM_VOXELS).unwrap();
            out.push((
                seq.file_name().unwrap().to_string_lossy().into_owned(),
                f.file_stem().unwrap().to_string_lossy().into_owned(),
                mask,
            ));
        }
    }
    assert!(
        !out.is_empty(),
        "no .invalid files in the real SemanticKITTI sample"
    );
    Some(out)
}

/// Class grid of a driving-like scene (z fastest) and a noisy prediction of it.
fn kitti_like_frame(rng: &mut ChaCha8Rng) -> (Vec<u8>, Vec<u8>) {
    let (ny, nz) = (256usize, 32usize);
    let mut gt = vec![0u8; NUM_VOXELS];
    for x in 0..256 {
        for y in 0..ny {
            let i = (x * ny + y) * nz;
            gt[i + 5] = [9, 11, 17][(x / 30 + y / 40) % 3];
            if (x / 10 + y / 12) % 5 == 0 {
                for z in 6..rng.random_range(7..20) {
                    gt[i + z] = [1, 13, 15, 18, 19][(y / 52) % 5];
                }
            }
        }
    }
    let pred = gt
        .iter()
        .map(|&g| {
            if rng.random_bool(0.75) {
                g
            } else {
                rng.random_range(0..20)
            }
        })
        .collect();
    (gt, pred)
}

#[test]
fn semantic_kitti_folder_end_to_end() {
    let Some(masks) = real_invalid_masks() else {
        return;
    };
    let map = LearningMap::semantic_kitti();
    let mut rng = ChaCha8Rng::seed_from_u64(21);
    let (gt_dir, pred_dir) = gt_and_pred("occ-eval", "kitti");
    let gt_paths = KittiPaths::new(&gt_dir.0);
    // Frames: the real sample's (sequence, frame) ids and invalid masks, plus synthetic labels.
    let mut expected_all = Evaluator::new(Protocol::SemanticKitti);
    let mut expected_by_seq = std::collections::BTreeMap::<String, Evaluator>::new();
    for (k, (seq, frame, invalid)) in masks.iter().enumerate() {
        let (gt_cls, pred_cls) = kitti_like_frame(&mut rng);
        let mut gt_raw = map.inverse_remap(&gt_cls);
        // Raw ids that the lut ignores (outlier, other-structure, other-object, unknown).
        for (j, raw) in [1u16, 52, 99, 4000].into_iter().enumerate() {
            for i in (j * 1000..j * 1000 + 300).map(|i| i * 7 + 5) {
                gt_raw[i] = raw;
            }
        }
        std::fs::create_dir_all(gt_paths.sequence_dir(seq).join("voxels")).unwrap();
        write_label_raw(&gt_paths.voxels(seq, frame, "label"), &gt_raw).unwrap();
        write_packed_bits(&gt_paths.voxels(seq, frame, "invalid"), invalid).unwrap();
        let id = FrameId {
            sequence: seq.clone(),
            frame: frame.clone(),
        };
        let mut pred_eval = pred_cls.clone();
        if k == 0 {
            // A submission holding ids that remap to 255 (invalid predictions).
            let mut raw = map.inverse_remap(&pred_cls);
            for i in 0..500 {
                raw[i * 13] = 52;
                pred_eval[i * 13] = 255;
            }
            let p = KittiPaths::new(&pred_dir.0).prediction(seq, frame);
            std::fs::create_dir_all(p.parent().unwrap()).unwrap();
            write_label_raw(&p, &raw).unwrap();
        } else {
            write_prediction(&pred_dir.0, &id, &pred_cls, &map).unwrap();
        }
        // Expected: the evaluator on the in-memory class grids (GT 255 where the raw id is ignored).
        let gt_eval: Vec<u8> = gt_raw.iter().map(|&r| map.to_class(r)).collect();
        assert!(gt_eval.contains(&255));
        for ev in [
            &mut expected_all,
            expected_by_seq
                .entry(seq.clone())
                .or_insert_with(|| Evaluator::new(Protocol::SemanticKitti)),
        ] {
            ev.add_frame(&pred_eval, &gt_eval, EvalMask::Invalid(invalid), frame)
                .unwrap();
        }
    }
    // An input-only frame (voxels/*.bin without .label) is not a GT frame.
    let (seq0, _, _) = &masks[0];
    write_packed_bits(
        &gt_paths.voxels(seq0, "999999", "bin"),
        &vec![0u8; NUM_VOXELS],
    )
    .unwrap();

    let (report, counted) =
        counting_frames(|opts| score_semantic_kitti_folder(&gt_dir.0, &pred_dir.0, opts));
    let report = report.unwrap();
    assert_eq!(report, expected_all.report());
    assert_eq!(report.frames as usize, masks.len());
    assert_eq!(counted, masks.len());
    assert_eq!(
        report.invalid_predictions,
        expected_all.report().invalid_predictions
    );
    assert!(report.invalid_predictions > 0);
    assert!(report.miou > 0.1 && report.miou < 0.95, "{}", report.miou);

    // --sequences: numeric ids are zero-padded ("8" -> "08").
    for (seq, ev) in &expected_by_seq {
        let short = vec![seq.trim_start_matches('0').to_string()];
        let short = if short[0].is_empty() {
            vec!["0".to_string()]
        } else {
            short
        };
        let opts = FolderOptions {
            sequences: Some(&short),
            ..Default::default()
        };
        let r = score_semantic_kitti_folder(&gt_dir.0, &pred_dir.0, &opts).unwrap();
        assert_eq!(r, ev.report(), "sequence {seq}");
    }
    let e = with_sequences(&["42"], |opts| {
        score_semantic_kitti_folder(&gt_dir.0, &pred_dir.0, opts)
    })
    .unwrap_err();
    assert!(e.to_string().contains("42"), "{e}");

    // A truncated prediction is an error naming the file.
    let (seq, frame, _) = &masks[masks.len() - 1];
    let p = KittiPaths::new(&pred_dir.0).prediction(seq, frame);
    let good = std::fs::read(&p).unwrap();
    std::fs::write(&p, &good[..1000]).unwrap();
    let e =
        score_semantic_kitti_folder(&gt_dir.0, &pred_dir.0, &FolderOptions::default()).unwrap_err();
    assert!(e.to_string().contains(&p.display().to_string()), "{e}");

    // Missing predictions: the error names the first missing file and counts them all.
    std::fs::remove_file(&p).unwrap();
    let e =
        score_semantic_kitti_folder(&gt_dir.0, &pred_dir.0, &FolderOptions::default()).unwrap_err();
    match &e {
        EvalError::MissingPrediction { path, count, .. } => {
            assert_eq!(path, &p);
            assert_eq!(*count, 1);
        }
        other => panic!("expected MissingPrediction, got {other}"),
    }
    assert!(e.to_string().contains(&format!("{frame}.label")), "{e}");
    let (seq, frame, _) = &masks[0];
    std::fs::remove_file(KittiPaths::new(&pred_dir.0).prediction(seq, frame)).unwrap();
    match score_semantic_kitti_folder(&gt_dir.0, &pred_dir.0, &FolderOptions::default()) {
        Err(EvalError::MissingPrediction { count, .. }) => assert_eq!(count, 2),
        other => panic!("expected MissingPrediction, got {other:?}"),
    }

    // An empty ground-truth folder has no frames.
    let empty = TempDir::new("occ-eval", "kitti-empty");
    std::fs::create_dir_all(empty.0.join("sequences/08")).unwrap();
    assert!(matches!(
        score_semantic_kitti_folder(&empty.0, &pred_dir.0, &FolderOptions::default()),
        Err(EvalError::NoFrames { .. })
    ));
}

/// An `.npz` holding only `semantics` as int64 (what `np.savez(f, semantics=pred.astype(int))` writes).
fn write_semantics_only_npz(path: &Path, dims: [usize; 3], values: &[i64]) {
    let mut zw = zip::ZipWriter::new(std::fs::File::create(path).unwrap());
    zw.start_file("semantics.npy", zip::write::SimpleFileOptions::default())
        .unwrap();
    zw.write_all(&npy_bytes(&dims, values).unwrap()).unwrap();
    zw.finish().unwrap();
}

#[test]
fn occ3d_folder_end_to_end() {
    let mut rng = ChaCha8Rng::seed_from_u64(33);
    let dims = [200usize, 200, 16];
    let n = dims.iter().product::<usize>();
    let (gt_dir, pred_dir) = gt_and_pred("occ-eval", "occ3d");
    let mut expected = Evaluator::new(Protocol::Occ3d);
    let mut expected_lidar = Evaluator::new(Protocol::Occ3d);
    let frames = [
        ("scene-0001", "tok_a"),
        ("scene-0001", "tok_b"),
        ("scene-0002", "tok_c"),
    ];
    for (k, (scene, token)) in frames.iter().enumerate() {
        let semantics: Vec<u8> = (0..n)
            .map(|i| {
                if i % 16 < 3 {
                    rng.random_range(0..17)
                } else if rng.random_bool(0.1) {
                    rng.random_range(0..18)
                } else {
                    17
                }
            })
            .collect();
        let mask_camera: Vec<u8> = (0..n).map(|_| u8::from(rng.random_bool(0.6))).collect();
        let mask_lidar: Vec<u8> = (0..n).map(|_| u8::from(rng.random_bool(0.4))).collect();
        let gt = Occ3dLabels {
            semantics: semantics.clone(),
            mask_lidar,
            mask_camera,
            dims,
        };
        let dir = gt_dir.0.join("gts").join(scene).join(token);
        std::fs::create_dir_all(&dir).unwrap();
        write_labels_npz(&dir.join("labels.npz"), &gt).unwrap();
        let pred: Vec<i64> = semantics
            .iter()
            .map(|&s| {
                if rng.random_bool(0.7) {
                    s as i64
                } else if rng.random_bool(0.02) {
                    300
                } else {
                    rng.random_range(0..18)
                }
            })
            .collect();
        let pred_u8: Vec<u8> = pred
            .iter()
            .map(|&v| if v < 255 { v as u8 } else { 255 })
            .collect();
        if k == 1 {
            // Flat layout PRED/<token>.npz, int64 semantics only.
            write_semantics_only_npz(&pred_dir.0.join(format!("{token}.npz")), dims, &pred);
        } else {
            // Ground-truth layout PRED/<scene>/<token>/labels.npz (uint8, masks present but unused).
            let pdir = pred_dir.0.join(scene).join(token);
            std::fs::create_dir_all(&pdir).unwrap();
            let p = Occ3dLabels {
                semantics: pred_u8.clone(),
                mask_lidar: vec![0; n],
                mask_camera: vec![0; n],
                dims,
            };
            // uint8 cannot hold 300: that voxel is written as an invalid id instead.
            let p = Occ3dLabels {
                semantics: p.semantics.iter().map(|&v| v.min(17)).collect(),
                ..p
            };
            write_labels_npz(&pdir.join("labels.npz"), &p).unwrap();
        }
        let pred_eval: Vec<u8> = if k == 1 {
            pred_u8
        } else {
            pred_u8.iter().map(|&v| v.min(17)).collect()
        };
        expected
            .add_frame(
                &pred_eval,
                &semantics,
                EvalMask::Visible(&gt.mask_camera),
                token,
            )
            .unwrap();
        expected_lidar
            .add_frame(
                &pred_eval,
                &semantics,
                EvalMask::Visible(&gt.mask_lidar),
                token,
            )
            .unwrap();
    }
    let r = score_occ3d_folder(&gt_dir.0, &pred_dir.0, &FolderOptions::default()).unwrap();
    assert_eq!(r, expected.report());
    assert_eq!(r.frames, 3);
    assert!(
        r.invalid_predictions > 0,
        "int64 value 300 must count as invalid"
    );
    // GT root given as the gts folder itself; lidar mask.
    let opts = FolderOptions {
        occ3d_mask: Occ3dMask::Lidar,
        ..Default::default()
    };
    let r = score_occ3d_folder(&gt_dir.0.join("gts"), &pred_dir.0, &opts).unwrap();
    assert_eq!(r, expected_lidar.report());

    // Wrong shape and missing key are errors naming the file.
    let flat = pred_dir.0.join("tok_b.npz");
    write_semantics_only_npz(&flat, [200, 200, 8], &vec![0i64; n / 2]);
    let e = score_occ3d_folder(&gt_dir.0, &pred_dir.0, &FolderOptions::default()).unwrap_err();
    assert!(
        e.to_string().contains("tok_b.npz") && e.to_string().contains("shape"),
        "{e}"
    );
    // Missing prediction.
    std::fs::remove_file(&flat).unwrap();
    match score_occ3d_folder(&gt_dir.0, &pred_dir.0, &FolderOptions::default()) {
        Err(EvalError::MissingPrediction { path, count, gt }) => {
            assert_eq!(count, 1);
            assert!(
                path.ends_with("scene-0001/tok_b/labels.npz"),
                "{}",
                path.display()
            );
            assert!(gt.ends_with("gts/scene-0001/tok_b/labels.npz"));
        }
        other => panic!("expected MissingPrediction, got {other:?}"),
    }
}

#[test]
fn real_occ3d_sample_scored_against_itself() {
    let Some(realdata) = occ_testdata::realdata() else {
        return;
    };
    let root = realdata.join("occ3d");
    let mut gts = Vec::new();
    for e in std::fs::read_dir(&root).expect("realdata occ3d folder") {
        let p = e.unwrap().path().join("labels.npz");
        if p.is_file() {
            gts.push(p);
        }
    }
    assert!(
        !gts.is_empty(),
        "no <token>/labels.npz in {}",
        root.display()
    );
    // GT against itself, through the folder scorer (prediction root = GT root).
    let r = score_occ3d_folder(&root, &root, &FolderOptions::default()).unwrap();
    assert_eq!(r.frames as usize, gts.len());
    let mut present = [false; 18];
    let mut visible = 0u64;
    for p in &gts {
        let l = read_labels_npz(p).unwrap();
        for (&s, &m) in l.semantics.iter().zip(&l.mask_camera) {
            if m != 0 {
                present[s as usize] = true;
                visible += 1;
            }
        }
    }
    assert_eq!(r.evaluated_voxels, visible);
    assert_eq!(r.invalid_predictions, 0);
    assert_eq!(r.miou, 1.0);
    assert_eq!((r.iou, r.per_class.0.len()), (1.0, 17));
    assert!((r.precision - 1.0).abs() < 1e-9 && (r.recall - 1.0).abs() < 1e-9);
    for (c, (name, iou)) in r.per_class.0.iter().enumerate() {
        if present[c] {
            assert_eq!(*iou, 1.0, "{name}");
        } else {
            assert!(
                iou.is_nan(),
                "{name} is absent and must be NaN (skipped by nanmean)"
            );
        }
    }
    assert!(
        present[..17].iter().filter(|&&p| p).count() >= 3,
        "sample should hold several classes"
    );

    // A degraded prediction (every 'driveable_surface' predicted as 'sidewalk'): that class drops
    // to 0, sidewalk to |sidewalk| / (|sidewalk| + |driveable|); the other present classes stay 1.
    let l = read_labels_npz(&gts[0]).unwrap();
    let pred: Vec<u8> = l
        .semantics
        .iter()
        .map(|&s| if s == 11 { 13 } else { s })
        .collect();
    let mut ev = Evaluator::new(Protocol::Occ3d);
    ev.add_frame(
        &pred,
        &l.semantics,
        EvalMask::Visible(&l.mask_camera),
        "degraded",
    )
    .unwrap();
    let d = ev.report();
    let count = |c: u8| {
        l.semantics
            .iter()
            .zip(&l.mask_camera)
            .filter(|(&s, &m)| s == c && m != 0)
            .count() as f64
    };
    let (n11, n13) = (count(11), count(13));
    assert!(n11 > 0.0, "the sample has driveable_surface");
    assert_eq!(d.per_class.get("driveable_surface"), Some(0.0));
    assert!((d.per_class.get("sidewalk").unwrap() - n13 / (n13 + n11)).abs() < 1e-12);
    assert_eq!(d.iou, 1.0, "class swaps do not change geometry");
}

/// Occ3D scoring honours `sequences` (scene names, each once), and ground truth of the wrong grid
/// is an error blaming the ground-truth file, not the prediction.
#[test]
fn occ3d_sequences_and_ground_truth_shape() {
    let dims = [200usize, 200, 16];
    let n = dims.iter().product::<usize>();
    let (gt_dir, pred_dir) = gt_and_pred("occ-eval", "occ3d-seq");
    let write = |root: &Path, scene: &str, token: &str, dims: [usize; 3], v: u8| {
        let n: usize = dims.iter().product();
        let l = Occ3dLabels {
            semantics: vec![v; n],
            mask_lidar: vec![1; n],
            mask_camera: vec![1; n],
            dims,
        };
        let dir = root.join(scene).join(token);
        std::fs::create_dir_all(&dir).unwrap();
        write_labels_npz(&dir.join("labels.npz"), &l).unwrap();
    };
    for (scene, token) in [
        ("scene-0001", "a"),
        ("scene-0001", "b"),
        ("scene-0002", "c"),
    ] {
        write(&gt_dir.0.join("gts"), scene, token, dims, 17);
        write(&pred_dir.0, scene, token, dims, 17);
    }
    let score = |seqs: &[&str]| {
        let s: Vec<String> = seqs.iter().map(|s| s.to_string()).collect();
        let opts = FolderOptions {
            sequences: Some(&s),
            ..Default::default()
        };
        score_occ3d_folder(&gt_dir.0, &pred_dir.0, &opts)
    };
    assert_eq!(score(&["scene-0002"]).unwrap().frames, 1);
    assert_eq!(score(&["scene-0001"]).unwrap().frames, 2);
    assert_eq!(score(&["scene-0001", "scene-0002"]).unwrap().frames, 3);
    let e = score(&["scene-0001", "scene-0001"])
        .unwrap_err()
        .to_string();
    assert!(e.contains("scene-0001") && e.contains("twice"), "{e}");
    let e = score(&["scene-9999"]).unwrap_err().to_string();
    assert!(e.contains("scene-9999"), "{e}");
    // A ground truth of another grid: the error names it (the prediction has the right grid).
    write(&gt_dir.0.join("gts"), "scene-0002", "c", [100, 100, 16], 17);
    let e = score(&["scene-0002"]).unwrap_err().to_string();
    assert!(
        e.contains("gts/scene-0002/c/labels.npz") && e.contains("[100, 100, 16]"),
        "{e}"
    );
    assert_eq!(n, 640_000);
}
