//! `prepare semantickitti`: layout report on the real data (check only) and label writing on a
//! small dataset built by the test.

mod common;

use common::kitti_root;
use occ_data::formats::semantic_kitti::*;
use occ_data::prepare::{prepare_semantic_kitti, PrepareOptions};
use occ_testdata::TempDir;
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;

#[test]
fn check_only_report_on_real_data() {
    let Some(root) = kitti_root() else { return };
    let mut calls = 0;
    let report = prepare_semantic_kitti(
        &root,
        &PrepareOptions {
            check_only: true,
            ..Default::default()
        },
        &mut |_, _| calls += 1,
    )
    .unwrap();
    let seqs = list_sequences(&root).unwrap();
    assert_eq!(
        report
            .sequences
            .iter()
            .map(|s| s.sequence.clone())
            .collect::<Vec<_>>(),
        seqs
    );
    assert_eq!(
        report.absent_sequences.len(),
        22 - seqs.iter().filter(|s| split_of(s).is_some()).count()
    );
    for s in &report.sequences {
        let frames = list_frames(&root, &s.sequence).unwrap();
        assert_eq!(s.ssc_frames, frames.len());
        assert!(s.has_calib && s.has_poses);
        assert_eq!(s.voxel_invalid, frames.len());
        assert!(
            s.missing_image.is_empty()
                && s.missing_velodyne.is_empty()
                && s.missing_invalid.is_empty()
        );
        // the public sample has no completion labels: all reported missing, none preprocessable
        assert_eq!(s.voxel_label, 0);
        assert_eq!(s.missing_label, frames);
        assert_eq!(s.split, split_of(&s.sequence).unwrap());
    }
    assert_eq!(report.preprocessable, 0);
    assert_eq!(report.written, 0);
    assert_eq!(calls, 0);
    let json = serde_json::to_value(&report).unwrap();
    assert!(json["sequences"][0]["missing_label"].is_array());
    assert!(
        !root.join("labels").join("00").exists(),
        "check-only must write nothing"
    );
}

#[test]
fn writes_preprocessed_labels() {
    let tmp = TempDir::new("occ-data-test", "prepare");
    let root = tmp.path();
    let p = KittiPaths::new(root);
    let mut rng = ChaCha8Rng::seed_from_u64(77);
    let map = LearningMap::semantic_kitti();
    let raw_ids = [0u16, 0, 0, 10, 40, 48, 50, 70, 72, 1, 52, 9999];
    let mut expected = Vec::new();
    for (seq, frames) in [
        ("00", vec!["000000", "000005", "000010"]),
        ("08", vec!["000000"]),
    ] {
        std::fs::create_dir_all(p.sequence_dir(seq).join("voxels")).unwrap();
        for f in &frames {
            let raw: Vec<u16> = (0..NUM_VOXELS)
                .map(|_| raw_ids[rng.random_range(0..raw_ids.len())])
                .collect();
            let invalid: Vec<u8> = (0..NUM_VOXELS)
                .map(|_| rng.random_bool(0.2) as u8)
                .collect();
            write_label_raw(&p.voxels(seq, f, "label"), &raw).unwrap();
            write_packed_bits(&p.voxels(seq, f, "bin"), &invalid).unwrap();
            if !(seq == "00" && *f == "000010") {
                write_packed_bits(&p.voxels(seq, f, "invalid"), &invalid).unwrap();
                // expected targets computed here straight from the rule of docs/formats.md §2.5
                let full: Vec<u8> = raw
                    .iter()
                    .zip(&invalid)
                    .map(|(&r, &i)| if i == 1 { 255 } else { map.to_class(r) })
                    .collect();
                expected.push((seq, f.to_string(), full));
            }
        }
    }
    // a corrupt label: recorded as a failure naming the file, other frames continue
    std::fs::create_dir_all(p.sequence_dir("01").join("voxels")).unwrap();
    std::fs::write(p.voxels("01", "000000", "label"), vec![0u8; 100]).unwrap();
    write_packed_bits(&p.voxels("01", "000000", "invalid"), &vec![0u8; NUM_VOXELS]).unwrap();

    let mut seen = Vec::new();
    let report = prepare_semantic_kitti(root, &PrepareOptions::default(), &mut |d, t| {
        seen.push((d, t))
    })
    .unwrap();
    assert_eq!(report.preprocessable, 4);
    assert_eq!(report.written, 3);
    assert_eq!(report.failures.len(), 1);
    assert!(
        report.failures[0].error.contains("000000.label")
            && report.failures[0].error.contains("truncated"),
        "{:?}",
        report.failures
    );
    assert!(!report.ok());
    assert_eq!(seen.first(), Some(&(0, 4)));
    assert_eq!(seen.last(), Some(&(4, 4)));
    assert!(seen.windows(2).all(|w| w[0].0 <= w[1].0));
    let s00 = report
        .sequences
        .iter()
        .find(|s| s.sequence == "00")
        .unwrap();
    assert_eq!(s00.missing_invalid, vec!["000010".to_string()]);
    assert_eq!(s00.missing_image.len(), 3);
    assert!(!s00.has_calib);
    for (seq, f, full) in &expected {
        let (got, dims) = read_label_npy(&p.preprocessed_label(seq, f, 1)).unwrap();
        assert_eq!(dims, DIMS);
        assert!(got == *full, "{seq}/{f} 1_1 differs");
        let (half, hd) = read_label_npy(&p.preprocessed_label(seq, f, 2)).unwrap();
        assert_eq!(hd, [128, 128, 16]);
        assert_eq!(half, downsample_labels(full, DIMS, 2).unwrap());
    }
    assert!(!p.preprocessed_label("00", "000010", 1).exists());
    // a second run skips what exists; overwrite rewrites
    let again = prepare_semantic_kitti(root, &PrepareOptions::default(), &mut |_, _| {}).unwrap();
    assert_eq!((again.written, again.skipped_existing), (0, 3));
    let over = prepare_semantic_kitti(
        root,
        &PrepareOptions {
            overwrite: true,
            sequences: Some(vec!["08".into()]),
            ..Default::default()
        },
        &mut |_, _| {},
    )
    .unwrap();
    assert_eq!(over.written, 1);
    // errors: no sequences folder, unknown sequence
    assert!(prepare_semantic_kitti(
        &root.join("nope"),
        &PrepareOptions::default(),
        &mut |_, _| {}
    )
    .unwrap_err()
    .to_string()
    .contains("sequences"));
    assert!(prepare_semantic_kitti(
        root,
        &PrepareOptions {
            sequences: Some(vec!["42".into()]),
            ..Default::default()
        },
        &mut |_, _| {}
    )
    .is_err());
}

/// The project's own `kitti-small` synthetic output (128x128x16 labels, its grid in
/// `synthetic.json`) prepares without failures; with `--check`, a voxel file of the wrong size is a
/// failure naming it (a 1000-byte `.label` used to pass).
#[test]
fn synthetic_grids_prepare_and_check_catches_wrong_sizes() {
    use occ_data::synthetic::{generate, Preset, SynthConfig};
    let tmp = TempDir::new("occ-data-test", "prepare-synth");
    let root = tmp.path();
    let cfg = SynthConfig::new(Preset::KittiSmall, 3, vec![("00".to_string(), 2)]);
    generate(root, &cfg, &mut |_, _| {}).unwrap();
    let check = PrepareOptions {
        check_only: true,
        ..Default::default()
    };
    let r = prepare_semantic_kitti(root, &check, &mut |_, _| {}).unwrap();
    assert!(r.ok(), "{:?}", r.failures);
    let p = KittiPaths::new(root);
    let label = p.voxels("00", "000001", "label");
    let good = std::fs::read(&label).unwrap();
    std::fs::write(&label, vec![0u8; 1000]).unwrap();
    let r = prepare_semantic_kitti(root, &check, &mut |_, _| {}).unwrap();
    assert_eq!(r.failures.len(), 1, "{:?}", r.failures);
    let e = &r.failures[0].error;
    assert!(e.contains("000001.label") && e.contains("truncated"), "{e}");
    assert_eq!(r.written, 0);
    std::fs::write(&label, &good).unwrap();
    let r = prepare_semantic_kitti(root, &PrepareOptions::default(), &mut |_, _| {}).unwrap();
    assert!(r.ok(), "{:?}", r.failures);
    assert_eq!(r.written, 2);
    let (_, dims) = read_label_npy(&p.preprocessed_label("00", "000000", 1)).unwrap();
    assert_eq!(dims, [128, 128, 16]);
    let (_, half) = read_label_npy(&p.preprocessed_label("00", "000000", 2)).unwrap();
    assert_eq!(half, [64, 64, 8]);
}
