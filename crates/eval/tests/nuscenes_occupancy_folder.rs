//! nuScenes-Occupancy (OpenOccupancy) folder scoring on small temporary folders written with
//! `write_sparse_occupancy`, checked against a hand computation of docs/evaluation.md §3
//! (`iou = tp/(p+g-tp)`, mIoU over classes 1..=16, SC IoU on `label != 0`, GT 255 ignored).

mod common;

use common::{counting_frames, gt_and_pred, with_sequences};
use occ_data::formats::nuscenes_occupancy::{write_sparse_occupancy, DIMS};
use occ_eval::{score_nuscenes_occupancy_folder, EvalError, FolderOptions, Protocol};
use occ_testdata::TempDir;
use std::path::Path;

const N: usize = DIMS[0] * DIMS[1] * DIMS[2];

/// Flat index of voxel `(x, y, z)` of the dense `[x][y][z]` grid.
fn idx(x: usize, y: usize, z: usize) -> usize {
    (x * DIMS[1] + y) * DIMS[2] + z
}

/// A dense grid (0 = empty) with the listed voxels set.
fn grid(voxels: &[(usize, u8)]) -> Vec<u8> {
    let mut g = vec![0u8; N];
    for &(i, c) in voxels {
        g[i] = c;
    }
    g
}

/// Write `root/scene_<scene>/occupancy/<token>.npy`.
fn write_frame(root: &Path, scene: &str, token: &str, dense: &[u8]) {
    let dir = root.join(format!("scene_{scene}")).join("occupancy");
    std::fs::create_dir_all(&dir).unwrap();
    write_sparse_occupancy(&dir.join(format!("{token}.npy")), dense).unwrap();
}

fn close(a: f64, b: f64) -> bool {
    (a - b).abs() < 1e-12
}

const CAR: u8 = 4;
const VEG: u8 = 16;
const BARRIER: u8 = 1;
const NOISE: u8 = 255;

#[test]
fn nuscenes_occupancy_folder_matches_hand_computation() {
    let (gt_dir, pred_dir) = gt_and_pred("occ-eval-nuscocc", "basic");
    // The ground truth sits below `GT/nuScenes-Occupancy/`, as in the OpenOccupancy download.
    let gt_base = gt_dir.0.join("nuScenes-Occupancy");

    // Frame A: car a1..a3, vegetation b1 b2, noise n1 (ignored).
    let (a1, a2, a3) = (idx(10, 20, 5), idx(10, 21, 5), idx(11, 20, 6));
    let (b1, b2) = (idx(300, 300, 1), idx(300, 301, 2));
    let (n1, e1) = (idx(0, 0, 0), idx(511, 511, 39));
    let gt_a = grid(&[
        (a1, CAR),
        (a2, CAR),
        (a3, CAR),
        (b1, VEG),
        (b2, VEG),
        (n1, NOISE),
    ]);
    // a3 missed, b1 called car, e1 a false car, n1 predicted car on GT noise (ignored).
    let pred_a = grid(&[
        (a1, CAR),
        (a2, CAR),
        (b1, CAR),
        (b2, VEG),
        (e1, CAR),
        (n1, CAR),
    ]);
    write_frame(&gt_base, "s1", "lidar_a", &gt_a);
    write_frame(&pred_dir.0, "s1", "lidar_a", &pred_a);

    // Frame B: barrier c1, car d1 predicted as noise (invalid -> empty), a false barrier e2, and
    // one correctly predicted voxel f_c of every class 1..=16.
    let (c1, d1, e2) = (idx(100, 100, 10), idx(100, 101, 10), idx(200, 5, 3));
    let f: Vec<(usize, u8)> = (1..=16u8)
        .map(|c| (idx(400, 10 + c as usize, 20), c))
        .collect();
    let mut gt_b_vox = vec![(c1, BARRIER), (d1, CAR)];
    gt_b_vox.extend_from_slice(&f);
    let mut pred_b_vox = vec![(c1, BARRIER), (d1, NOISE), (e2, BARRIER)];
    pred_b_vox.extend_from_slice(&f);
    write_frame(&gt_base, "s2", "lidar_b", &grid(&gt_b_vox));
    write_frame(&pred_dir.0, "s2", "lidar_b", &grid(&pred_b_vox));

    let (r, frames_seen) =
        counting_frames(|opts| score_nuscenes_occupancy_folder(&gt_dir.0, &pred_dir.0, opts));
    let r = r.unwrap();

    // Confusion conf[pred][gt] (non-empty-empty cells):
    //   car/car 2+1 (a1, a2, f4), car/veg 1 (b1), veg/veg 1+1 (b2, f16), car/empty 1 (e1),
    //   empty/car 2 (a3, d1), barrier/barrier 1+1 (c1, f1), barrier/empty 1 (e2),
    //   c/c 1 for the other 13 classes.
    assert_eq!(r.dataset, Protocol::NuScenesOccupancy);
    assert_eq!(r.frames, 2);
    assert_eq!(frames_seen, 2);
    assert_eq!(
        r.evaluated_voxels,
        2 * N as u64 - 1,
        "GT noise n1 is ignored"
    );
    assert_eq!(r.invalid_predictions, 1, "d1 predicted as noise");
    assert_eq!(r.confusion[CAR as usize][CAR as usize], 3);
    assert_eq!(r.confusion[CAR as usize][VEG as usize], 1);
    assert_eq!(r.confusion[0][CAR as usize], 2);
    assert_eq!(r.confusion[CAR as usize][0], 1);
    assert_eq!(r.confusion[BARRIER as usize][0], 1);

    // Per class tp/(p+g-tp): car tp 3, p 5, g 5; vegetation tp 2, p 2, g 3;
    // barrier tp 2, p 3, g 2; every other class 1/(1+1-1).
    let car = 3.0 / (5.0 + 5.0 - 3.0);
    let veg = 2.0 / (2.0 + 3.0 - 2.0);
    let barrier = 2.0 / (3.0 + 2.0 - 2.0);
    assert!(close(r.per_class.get("car").unwrap(), car));
    assert!(close(r.per_class.get("vegetation").unwrap(), veg));
    assert!(close(r.per_class.get("barrier").unwrap(), barrier));
    assert_eq!(r.per_class.0.len(), 16, "classes 1..=16");
    assert!(r.per_class.get("empty").is_none());
    for (name, iou) in &r.per_class.0 {
        if !["car", "vegetation", "barrier"].contains(&name.as_str()) {
            assert!(close(*iou, 1.0), "{name}: {iou}");
        }
    }
    let miou = (13.0 + car + veg + barrier) / 16.0;
    assert!(close(r.miou, miou), "mIoU {} vs {miou}", r.miou);

    // SC IoU (label != 0): both occupied 3+1+2+2+13 = 21; union adds car/empty, barrier/empty and
    // the two empty/car voxels: 25. Predicted occupied 23, GT occupied 23.
    assert!(close(r.iou, 21.0 / 25.0), "IoU {}", r.iou);
    let eps = f64::from(f32::EPSILON);
    assert!(close(r.precision, 21.0 / (23.0 + eps)));
    assert!(close(r.recall, 21.0 / (23.0 + eps)));
}

#[test]
fn nuscenes_occupancy_missing_prediction_is_an_error() {
    let (gt_dir, pred_dir) = gt_and_pred("occ-eval-nuscocc", "missing");
    let g = grid(&[(idx(1, 2, 3), CAR)]);
    write_frame(&gt_dir.0, "s1", "lidar_a", &g);
    write_frame(&gt_dir.0, "s1", "lidar_b", &g);
    write_frame(&gt_dir.0, "s2", "lidar_c", &g);
    write_frame(&pred_dir.0, "s1", "lidar_a", &g);
    // A prediction written for the right token but in the wrong scene does not count.
    write_frame(&pred_dir.0, "s1", "lidar_c", &g);
    let err = score_nuscenes_occupancy_folder(&gt_dir.0, &pred_dir.0, &FolderOptions::default())
        .unwrap_err();
    match err {
        EvalError::MissingPrediction { path, gt, count } => {
            assert_eq!(count, 2);
            assert_eq!(
                path,
                pred_dir
                    .0
                    .join("scene_s1")
                    .join("occupancy")
                    .join("lidar_b.npy")
            );
            assert_eq!(
                gt,
                gt_dir
                    .0
                    .join("scene_s1")
                    .join("occupancy")
                    .join("lidar_b.npy")
            );
        }
        other => panic!("expected MissingPrediction, got {other}"),
    }

    // An empty ground-truth folder has no frames.
    let empty = TempDir::new("occ-eval-nuscocc", "gt-empty");
    let err = score_nuscenes_occupancy_folder(&empty.0, &pred_dir.0, &FolderOptions::default())
        .unwrap_err();
    assert!(matches!(err, EvalError::NoFrames { .. }), "{err}");
}

#[test]
fn nuscenes_occupancy_noise_is_ignored_in_gt_and_invalid_in_prediction() {
    let (a, n, e) = (idx(5, 5, 5), idx(6, 6, 6), idx(7, 7, 7));
    let gt = grid(&[(a, CAR), (n, NOISE)]);
    let score = |pred: &[u8]| {
        let (gt_dir, pred_dir) = gt_and_pred("occ-eval-nuscocc", "noise");
        write_frame(&gt_dir.0, "s", "lidar", &gt);
        write_frame(&pred_dir.0, "s", "lidar", pred);
        score_nuscenes_occupancy_folder(&gt_dir.0, &pred_dir.0, &FolderOptions::default()).unwrap()
    };
    // Whatever is predicted on the GT-noise voxel, it is not evaluated.
    let base = score(&grid(&[(a, CAR)]));
    let on_noise_car = score(&grid(&[(a, CAR), (n, CAR)]));
    let on_noise_noise = score(&grid(&[(a, CAR), (n, NOISE)]));
    for r in [&base, &on_noise_car, &on_noise_noise] {
        assert_eq!(r.evaluated_voxels, N as u64 - 1);
        assert_eq!(r.invalid_predictions, 0);
        assert_eq!(r.confusion, base.confusion);
        assert!(close(r.iou, 1.0));
        assert!(close(r.per_class.get("car").unwrap(), 1.0));
    }
    // Predicted noise on an evaluated voxel is invalid and scored as empty: on a GT-empty voxel
    // nothing changes but the counter; on the car voxel it is a missed car.
    let noise_on_empty = score(&grid(&[(a, CAR), (e, NOISE)]));
    assert_eq!(noise_on_empty.invalid_predictions, 1);
    assert_eq!(noise_on_empty.confusion, base.confusion);
    let noise_on_car = score(&grid(&[(a, NOISE)]));
    assert_eq!(noise_on_car.invalid_predictions, 1);
    assert_eq!(noise_on_car.confusion[0][CAR as usize], 1);
    assert_eq!(noise_on_car.confusion[CAR as usize][CAR as usize], 0);
    assert!(close(noise_on_car.per_class.get("car").unwrap(), 0.0));
    assert!(close(noise_on_car.iou, 0.0));
}

/// `sequences` selects scenes by token (`s2`) or folder name (`scene_s2`); only their frames are
/// scored (so a scene without predictions may be left out), and an unknown scene is an error.
#[test]
fn nuscenes_occupancy_sequences_select_scenes() {
    let (gt_dir, pred_dir) = gt_and_pred("occ-eval-nuscocc", "seq");
    let g = grid(&[(idx(1, 2, 3), CAR)]);
    write_frame(&gt_dir.0, "s1", "lidar_a", &g);
    write_frame(&gt_dir.0, "s2", "lidar_b", &g);
    write_frame(&gt_dir.0, "s2", "lidar_c", &g);
    // Only scene s2 is predicted (one miss): scoring s2 alone must work and count its two frames.
    write_frame(&pred_dir.0, "s2", "lidar_b", &g);
    write_frame(&pred_dir.0, "s2", "lidar_c", &grid(&[]));
    for name in ["s2", "scene_s2"] {
        let r = with_sequences(&[name], |opts| {
            score_nuscenes_occupancy_folder(&gt_dir.0, &pred_dir.0, opts)
        })
        .unwrap();
        assert_eq!(r.frames, 2, "{name}");
        assert!(close(r.recall, 1.0 / (2.0 + f64::from(f32::EPSILON))));
    }
    // Without the selection the unpredicted scene s1 is a missing prediction.
    assert!(matches!(
        score_nuscenes_occupancy_folder(&gt_dir.0, &pred_dir.0, &FolderOptions::default()),
        Err(EvalError::MissingPrediction { .. })
    ));
    let err = with_sequences(&["s9"], |opts| {
        score_nuscenes_occupancy_folder(&gt_dir.0, &pred_dir.0, opts)
    })
    .unwrap_err();
    assert!(err.to_string().contains("scene_s9"), "{err}");
    assert!(matches!(
        with_sequences(&["s2", "scene_s2"], |opts| score_nuscenes_occupancy_folder(
            &gt_dir.0,
            &pred_dir.0,
            opts
        )),
        Err(EvalError::InvalidOptions(_))
    ));
}
