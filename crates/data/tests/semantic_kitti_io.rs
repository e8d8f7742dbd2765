//! SemanticKITTI writers (round trips, submissions) and bad-input handling.

mod common;

use common::kitti_root;
use occ_data::formats::semantic_kitti::*;
use occ_data::image::read_png;
use occ_data::DataError;
use occ_testdata::TempDir;
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;

fn random_classes(rng: &mut ChaCha8Rng, n: usize) -> Vec<u8> {
    (0..n)
        .map(|_| match rng.random_range(0..20) {
            0..=9 => 0,
            10 => 255,
            _ => rng.random_range(1..20),
        })
        .collect()
}

#[test]
fn round_trips_of_every_format() {
    let tmp = TempDir::new("occ-data-test", "kitti-rt");
    let d = tmp.path();
    let mut rng = ChaCha8Rng::seed_from_u64(21);
    let map = LearningMap::semantic_kitti();

    // packed bits (length not a multiple of 8 too)
    for n in [NUM_VOXELS, 13] {
        let bits: Vec<u8> = (0..n).map(|_| rng.random_range(0..2)).collect();
        write_packed_bits(&d.join("a.invalid"), &bits).unwrap();
        assert_eq!(
            std::fs::metadata(d.join("a.invalid")).unwrap().len() as usize,
            n.div_ceil(8)
        );
        assert_eq!(read_packed_bits(&d.join("a.invalid"), n).unwrap(), bits);
    }
    // raw labels
    let raw: Vec<u16> = (0..NUM_VOXELS).map(|_| rng.random()).collect();
    write_label_raw(&d.join("a.label"), &raw).unwrap();
    assert_eq!(
        std::fs::metadata(d.join("a.label")).unwrap().len(),
        4_194_304
    );
    assert_eq!(read_label_raw(&d.join("a.label"), NUM_VOXELS).unwrap(), raw);
    // remap of all 65536 ids: no panic, every value a class or 255
    let all: Vec<u16> = (0..=u16::MAX).collect();
    let classes = map.remap(&all);
    assert!(classes
        .iter()
        .all(|&c| (c as usize) < NUM_CLASSES || c == 255));
    // raw 0 plus the 30 raw ids of the remap table (docs/formats.md §2.4)
    assert_eq!(classes.iter().filter(|&&c| c != 255).count(), 1 + 30);

    // preprocessed .npy (float32), full and half resolution
    let grid = random_classes(&mut rng, NUM_VOXELS);
    write_label_npy(&d.join("000000_1_1.npy"), &grid, DIMS).unwrap();
    let (back, dims) = read_label_npy(&d.join("000000_1_1.npy")).unwrap();
    assert_eq!((back.as_slice(), dims), (grid.as_slice(), DIMS));
    let bytes = std::fs::read(d.join("000000_1_1.npy")).unwrap();
    assert!(
        String::from_utf8_lossy(&bytes[..128]).contains("'descr': '<f4'"),
        "official dtype is float32"
    );
    let half = downsample_labels(&grid, DIMS, 2).unwrap();
    write_label_npy(&d.join("000000_1_2.npy"), &half, [128, 128, 16]).unwrap();
    assert_eq!(
        read_label_npy(&d.join("000000_1_2.npy")).unwrap(),
        (half, [128, 128, 16])
    );

    // submission: classes -> raw ids via learning_map_inv, readable back through the map
    let frame = FrameId {
        sequence: "11".into(),
        frame: "000005".into(),
    };
    let path = write_prediction(d, &frame, &grid, &map).unwrap();
    assert!(path.ends_with("sequences/11/predictions/000005.label"));
    let raw_pred = read_label_raw(&path, NUM_VOXELS).unwrap();
    for (&c, &r) in grid.iter().zip(&raw_pred) {
        let want = if c == 255 { 0 } else { c };
        assert_eq!(map.to_class(r), want);
    }
    assert!(write_prediction(d, &frame, &grid[..10], &map).is_err());

    // calibration and poses (from the real sample; skipped with a note without it)
    if let Some(root) = kitti_root() {
        let real = read_calib(&KittiPaths::new(&root).calib("00")).unwrap();
        write_calib(&d.join("calib.txt"), &real).unwrap();
        let c2 = read_calib(&d.join("calib.txt")).unwrap();
        for i in 0..3 {
            for j in 0..4 {
                assert!((c2.p2[i][j] - real.p2[i][j]).abs() <= 1e-9 * real.p2[i][j].abs().max(1.0));
                assert!((c2.tr[i][j] - real.tr[i][j]).abs() <= 1e-12);
            }
        }
        let poses = read_poses(&KittiPaths::new(&root).poses("08")).unwrap();
        write_poses(&d.join("poses.txt"), &poses[..50]).unwrap();
        let p2 = read_poses(&d.join("poses.txt")).unwrap();
        assert_eq!(p2.len(), 50);
        for (a, b) in p2.iter().zip(&poses) {
            for i in 0..4 {
                for j in 0..4 {
                    assert!((a[i][j] - b[i][j]).abs() < 1e-9);
                }
            }
        }
    }

    // scans and point labels
    let pts: Vec<[f32; 4]> = (0..1000)
        .map(|_| [rng.random(), rng.random(), rng.random(), rng.random()])
        .collect();
    let pl: Vec<u32> = (0..1000).map(|_| rng.random()).collect();
    write_velodyne(&d.join("s.bin"), &pts).unwrap();
    write_point_labels(&d.join("s.label"), &pl).unwrap();
    assert_eq!(
        read_labelled_scan(&d.join("s.bin"), &d.join("s.label")).unwrap(),
        (pts, pl)
    );
    // no temporary files are left behind
    let leftovers: Vec<_> = std::fs::read_dir(d)
        .unwrap()
        .filter_map(|e| e.ok())
        .filter(|e| e.file_name().to_string_lossy().contains(".tmp-"))
        .collect();
    assert!(leftovers.is_empty());
}

fn msg(e: &DataError) -> String {
    e.to_string()
}

#[test]
fn bad_inputs_give_errors_naming_the_file() {
    let tmp = TempDir::new("occ-data-test", "kitti-bad");
    let d = tmp.path();
    let Some(root) = kitti_root() else { return };
    let p = KittiPaths::new(&root);
    let seq = list_sequences(&root).unwrap()[0].clone();
    let frame = list_frames(&root, &seq).unwrap()[0].clone();

    // truncated packed file
    let real = std::fs::read(p.voxels(&seq, &frame, "bin")).unwrap();
    let short = d.join("short.bin");
    std::fs::write(&short, &real[..1000]).unwrap();
    let e = read_packed_bits(&short, NUM_VOXELS).unwrap_err();
    assert!(
        matches!(
            e,
            DataError::Truncated {
                expected: 262_144,
                actual: 1000,
                ..
            }
        ),
        "{e}"
    );
    assert!(msg(&e).contains("short.bin"));
    // too long
    let long = d.join("long.occluded");
    let mut l = real.clone();
    l.push(0);
    std::fs::write(&long, &l).unwrap();
    let e = read_packed_bits(&long, NUM_VOXELS).unwrap_err();
    assert!(
        matches!(e, DataError::WrongSize { .. }) && msg(&e).contains("long.occluded"),
        "{e}"
    );
    // label of the wrong size
    let bad_label = d.join("000000.label");
    std::fs::write(&bad_label, vec![0u8; 4_194_303]).unwrap();
    assert!(msg(&read_label_raw(&bad_label, NUM_VOXELS).unwrap_err()).contains("000000.label"));
    // velodyne not a multiple of 16 bytes, point labels not a multiple of 4
    let v = d.join("scan.bin");
    std::fs::write(&v, vec![0u8; 16 * 10 + 7]).unwrap();
    assert!(matches!(
        read_velodyne(&v),
        Err(DataError::WrongSize { .. })
    ));
    let pl = d.join("scan.label");
    std::fs::write(&pl, vec![0u8; 4 * 9]).unwrap();
    std::fs::write(&v, vec![0u8; 16 * 10]).unwrap();
    let e = read_labelled_scan(&v, &pl).unwrap_err();
    assert!(
        msg(&e).contains("scan.label") && msg(&e).contains("9 labels for 10 points"),
        "{e}"
    );
    std::fs::write(&pl, vec![0u8; 4 * 9 + 1]).unwrap();
    assert!(matches!(
        read_point_labels(&pl),
        Err(DataError::WrongSize { .. })
    ));

    // calib without Tr, with a bad number, with a short line
    let calib_real = std::fs::read_to_string(p.calib(&seq)).unwrap();
    let no_tr: String = calib_real
        .lines()
        .filter(|l| !l.starts_with("Tr"))
        .map(|l| format!("{l}\n"))
        .collect();
    let c = d.join("calib.txt");
    std::fs::write(&c, &no_tr).unwrap();
    let e = read_calib(&c).unwrap_err();
    assert!(
        matches!(&e, DataError::MissingKey { key, .. } if key == "Tr"),
        "{e}"
    );
    assert!(msg(&e).contains("calib.txt") && msg(&e).contains("Tr"));
    // Tr after an empty line is not read (the parser stops there, like the reference)
    std::fs::write(
        &c,
        format!(
            "{no_tr}\n{}",
            calib_real.lines().find(|l| l.starts_with("Tr")).unwrap()
        ),
    )
    .unwrap();
    assert!(matches!(read_calib(&c), Err(DataError::MissingKey { .. })));
    std::fs::write(&c, calib_real.replacen("P2: 7", "P2: x", 1)).unwrap();
    assert!(
        matches!(read_calib(&c), Err(DataError::Parse { line: 3, .. })),
        "{:?}",
        read_calib(&c)
    );
    std::fs::write(&c, "P2: 1 2 3\n").unwrap();
    assert!(matches!(
        read_calib(&c),
        Err(DataError::Parse { line: 1, .. })
    ));
    std::fs::write(&c, [0xffu8, 0xfe, 0x00]).unwrap();
    assert!(read_calib(&c).is_err());
    let poses = d.join("poses.txt");
    std::fs::write(&poses, "1 0 0 0 0 1 0 0 0 0 1 0\n1 0 0\n").unwrap();
    assert!(matches!(
        read_poses(&poses),
        Err(DataError::Parse { line: 2, .. })
    ));

    // unknown raw label ids: 255, never a panic, for every u16
    let map = LearningMap::semantic_kitti();
    assert_eq!(map.to_class(65535), 255);
    assert_eq!(map.to_class(1000), 255);
    assert_eq!(
        map.remap_point_labels(&[u32::MAX, 0x0001_0000]),
        vec![255, 0]
    );

    // missing image / missing files
    let e = read_png(&p.image_2(&seq, "999999")).unwrap_err();
    assert!(
        matches!(e, DataError::NotFound { .. }) && msg(&e).contains("999999.png"),
        "{e}"
    );
    let e = read_calib(&d.join("nope").join("calib.txt")).unwrap_err();
    assert!(matches!(e, DataError::NotFound { .. }));
    // corrupt PNG
    let png = d.join("broken.png");
    let real_png = std::fs::read(p.image_2(&seq, &frame)).unwrap();
    std::fs::write(&png, &real_png[..5000]).unwrap();
    let e = read_png(&png).unwrap_err();
    assert!(
        matches!(e, DataError::Image { .. }) && msg(&e).contains("broken.png"),
        "{e}"
    );
    // label .npy with a bad value or shape
    let npy = d.join("x_1_1.npy");
    occ_data::formats::npy::write_npy(&npy, &[2, 2], &[0f32, 1.0, 2.0, 3.0]).unwrap();
    assert!(msg(&read_label_npy(&npy).unwrap_err()).contains("x_1_1.npy"));
    occ_data::formats::npy::write_npy(&npy, &[1, 1, 2], &[0f32, 1.5]).unwrap();
    assert!(read_label_npy(&npy).is_err());
    std::fs::write(&npy, b"garbage").unwrap();
    assert!(read_label_npy(&npy).is_err());
    // listing a sequence that does not exist
    assert!(matches!(
        list_frames(&root, "99"),
        Err(DataError::NotFound { .. })
    ));
}

/// A calibration that would project silently wrong is refused by `read_calib` and
/// `Calib::from_rows` alike, with the matrix named: `P2[:3,:3]` that is not a pinhole intrinsic
/// matrix (the camera is read from fx, fy, cx, cy alone), `Tr[:3,:3]` that is not a rotation. A
/// rotation written with 4 significant digits, KITTI's own numbers and P2's 4th column pass.
#[test]
fn calibrations_that_would_project_wrong_are_refused() {
    let p2 = [
        [721.5377, 0.0, 609.5593, 44.85728],
        [0.0, 721.5377, 172.854, 0.2163791],
        [0.0, 0.0, 1.0, 0.002745884],
    ];
    let (c, s) = (0.6_f64.cos(), 0.6_f64.sin());
    let tr = [
        [c, -s, 0.0, 0.1],
        [0.0, 0.0, -1.0, -0.08],
        [s, c, 0.0, -0.27],
    ];
    assert!(Calib::from_rows(p2, tr).is_ok());
    let round4 = |m: [[f64; 4]; 3]| m.map(|r| r.map(|v| (v * 1e4).round() / 1e4));
    assert!(Calib::from_rows(p2, round4(tr)).is_ok());

    let scaled = tr.map(|r| r.map(|v| v * 1000.0));
    let mut reflected = tr;
    reflected[1] = reflected[1].map(|v| -v);
    for (what, bad) in [
        ("scaled", scaled),
        ("reflected", reflected),
        ("zero", [[0.0; 4]; 3]),
    ] {
        let e = Calib::from_rows(p2, bad).unwrap_err();
        assert!(e.contains("Tr[:3,:3] must be a rotation"), "{what}: {e}");
    }
    let mut skew = p2;
    skew[0][1] = 2.0;
    let mut third_row = p2;
    third_row[2] = [0.0, 0.0, -1.0, 0.0];
    let scaled_p2 = p2.map(|r| r.map(|v| 2.0 * v));
    let mut negative_f = p2;
    negative_f[0][0] = -721.5377;
    for (what, bad) in [
        ("skew", skew),
        ("third row", third_row),
        ("scaled", scaled_p2),
        ("negative fx", negative_f),
        ("zero", [[0.0; 4]; 3]),
    ] {
        let e = Calib::from_rows(bad, tr).unwrap_err();
        assert!(e.contains("pinhole intrinsic matrix"), "{what}: {e}");
    }

    // The file reader gives the same refusal, naming the file.
    let tmp = TempDir::new("occ-data-test", "calib");
    let d = tmp.path();
    let row = |m: [[f64; 4]; 3]| {
        m.iter()
            .flatten()
            .map(|v| format!("{v:e}"))
            .collect::<Vec<_>>()
            .join(" ")
    };
    let path = d.join("calib.txt");
    std::fs::write(&path, format!("P2: {}\nTr: {}\n", row(p2), row(scaled))).unwrap();
    let e = msg(&read_calib(&path).unwrap_err());
    assert!(e.contains("calib.txt") && e.contains("rotation"), "{e}");
    std::fs::write(&path, format!("P2: {}\nTr: {}\n", row(p2), row(tr))).unwrap();
    assert_eq!(
        read_calib(&path).unwrap(),
        Calib::from_rows(p2, tr).unwrap()
    );
}
