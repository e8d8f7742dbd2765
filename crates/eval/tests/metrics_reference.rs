//! The evaluator against an independent, literal implementation of the official formulas
//! (semantic-kitti-api `evaluate_completion.py` + `np_ioueval.py`; OpenOccupancy `fast_hist` +
//! `cm_to_ious`; Occ3D `Metric_mIoU`), written here per class with f64 counts, on seeded random data
//! and on real-shaped 256x256x32 frames, plus hand-computed tiny cases.

use occ_eval::{format_table, EvalMask, EvalReport, Evaluator, Protocol};
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;

struct Frame {
    pred: Vec<u8>,
    gt: Vec<u8>,
    mask: Option<Vec<u8>>,
}

/// Reference metrics for one protocol, computed class by class with f64 counters.
struct Reference {
    iou: Vec<f64>,
    miou: f64,
    completion_iou: f64,
    precision: f64,
    recall: f64,
    invalid: f64,
    evaluated: f64,
}

fn reference(protocol: Protocol, frames: &[Frame]) -> Reference {
    let (n, empty): (usize, u8) = match protocol {
        Protocol::SemanticKitti => (20, 0),
        Protocol::NuScenesOccupancy => (17, 0),
        Protocol::Occ3d => (18, 17),
    };
    let mut tp = vec![0f64; n];
    let mut pred_count = vec![0f64; n];
    let mut gt_count = vec![0f64; n];
    let (mut both_occ, mut pred_occ, mut gt_occ, mut both_empty, mut total) =
        (0f64, 0f64, 0f64, 0f64, 0f64);
    let mut invalid = 0f64;
    for f in frames {
        for i in 0..f.gt.len() {
            let g = f.gt[i];
            // Masks: SemanticKITTI drops GT 255 and invalid==1; OpenOccupancy drops GT 255;
            // Occ3D keeps mask_camera (cast to bool) and GT in [0, 18).
            let keep = match protocol {
                Protocol::SemanticKitti => g != 255 && f.mask.as_ref().is_none_or(|m| m[i] != 1),
                Protocol::NuScenesOccupancy => {
                    g != 255 && f.mask.as_ref().is_none_or(|m| m[i] != 0)
                }
                Protocol::Occ3d => (g as usize) < n && f.mask.as_ref().is_none_or(|m| m[i] != 0),
            };
            if !keep {
                continue;
            }
            let mut p = f.pred[i];
            if p as usize >= n {
                // Documented choice: a non-class prediction is scored as empty.
                p = empty;
                invalid += 1.0;
            }
            total += 1.0;
            pred_count[p as usize] += 1.0;
            gt_count[g as usize] += 1.0;
            if p == g {
                tp[p as usize] += 1.0;
            }
            let (po, go) = (p != empty, g != empty);
            if po && go {
                both_occ += 1.0;
            }
            if po {
                pred_occ += 1.0;
            }
            if go {
                gt_occ += 1.0;
            }
            if !po && !go {
                both_empty += 1.0;
            }
        }
    }
    let iou: Vec<f64> = (0..n)
        .map(|c| match protocol {
            Protocol::SemanticKitti => {
                let fp = pred_count[c] - tp[c];
                let fn_ = gt_count[c] - tp[c];
                tp[c] / (tp[c] + fp + fn_ + 1e-15)
            }
            _ => tp[c] / (pred_count[c] + gt_count[c] - tp[c]),
        })
        .collect();
    let miou = match protocol {
        Protocol::SemanticKitti => iou[1..20].iter().sum::<f64>() / 19.0,
        Protocol::NuScenesOccupancy => iou[1..17].iter().sum::<f64>() / 16.0,
        Protocol::Occ3d => {
            let v: Vec<f64> = iou[..17].iter().copied().filter(|x| !x.is_nan()).collect();
            v.iter().sum::<f64>() / v.len() as f64
        }
    };
    let eps = f32::EPSILON as f64;
    Reference {
        iou,
        miou,
        completion_iou: both_occ / (total - both_empty),
        precision: both_occ / (pred_occ + eps),
        recall: both_occ / (gt_occ + eps),
        invalid,
        evaluated: total,
    }
}

fn close(a: f64, b: f64) -> bool {
    (a.is_nan() && b.is_nan()) || (a - b).abs() <= 1e-6
}

fn check(protocol: Protocol, frames: &[Frame], label: &str) -> EvalReport {
    let mut ev = Evaluator::new(protocol);
    for (i, f) in frames.iter().enumerate() {
        let mask = match (&f.mask, protocol) {
            (None, _) => EvalMask::All,
            (Some(m), Protocol::SemanticKitti) => EvalMask::Invalid(m),
            (Some(m), _) => EvalMask::Visible(m),
        };
        ev.add_frame(&f.pred, &f.gt, mask, &format!("{label}/{i}"))
            .unwrap();
    }
    let r = ev.report();
    let want = reference(protocol, frames);
    assert_eq!(r.frames, frames.len() as u64);
    assert_eq!(r.evaluated_voxels as f64, want.evaluated, "{label}");
    assert_eq!(r.invalid_predictions as f64, want.invalid, "{label}");
    let names = protocol.class_names();
    for (name, got) in &r.per_class.0 {
        let c = names.iter().position(|n| n == name).unwrap();
        assert!(
            close(*got, want.iou[c]),
            "{label}: IoU {name}: {got} vs {}",
            want.iou[c]
        );
    }
    assert_eq!(r.per_class.0.len(), protocol.miou_classes().len());
    for (what, got, exp) in [
        ("mIoU", r.miou, want.miou),
        ("completion IoU", r.iou, want.completion_iou),
        ("precision", r.precision, want.precision),
        ("recall", r.recall, want.recall),
    ] {
        assert!(close(got, exp), "{label}: {what}: {got} vs {exp}");
    }
    r
}

/// A prediction that agrees with the GT with probability `agree`, else a random label (with a few
/// invalid values 255 / out of range when `invalid`).
fn random_frames(
    rng: &mut ChaCha8Rng,
    protocol: Protocol,
    n_frames: usize,
    len: usize,
    with_mask: bool,
) -> Vec<Frame> {
    let n = protocol.num_classes() as u8;
    (0..n_frames)
        .map(|_| {
            let agree = rng.random_range(0.0..0.9);
            let mut gt = Vec::with_capacity(len);
            let mut pred = Vec::with_capacity(len);
            for _ in 0..len {
                let g = if rng.random_bool(0.05) {
                    255
                } else if rng.random_bool(0.6) {
                    protocol.empty_class()
                } else {
                    rng.random_range(0..n)
                };
                let p = if rng.random_bool(0.01) {
                    if rng.random_bool(0.5) {
                        255
                    } else {
                        rng.random_range(n..=254)
                    }
                } else if g != 255 && rng.random_bool(agree) {
                    g
                } else {
                    rng.random_range(0..n)
                };
                gt.push(g);
                pred.push(p);
            }
            let mask = with_mask.then(|| (0..len).map(|_| rng.random_range(0..3u8)).collect());
            Frame { pred, gt, mask }
        })
        .collect()
}

#[test]
fn random_data_matches_reference_all_protocols() {
    let mut rng = ChaCha8Rng::seed_from_u64(3);
    for protocol in [
        Protocol::SemanticKitti,
        Protocol::NuScenesOccupancy,
        Protocol::Occ3d,
    ] {
        for (case, with_mask) in [(0, false), (1, true), (2, true)] {
            let frames = random_frames(&mut rng, protocol, 1 + case, 5000 + 1000 * case, with_mask);
            let r = check(protocol, &frames, &format!("{}-{case}", protocol.name()));
            assert!(
                r.invalid_predictions > 0,
                "invalid predictions must be exercised"
            );
            assert!(r.miou > 0.0 && r.miou < 1.0);
        }
    }
}

#[test]
fn real_shaped_frames_match_reference() {
    // Two 256x256x32 SemanticKITTI-like frames: a ground layer, objects, invalid masks.
    let mut rng = ChaCha8Rng::seed_from_u64(5);
    let (nx, ny, nz) = (256usize, 256usize, 32usize);
    let mut frames = Vec::new();
    for _ in 0..2 {
        let mut gt = vec![0u8; nx * ny * nz];
        for x in 0..nx {
            for y in 0..ny {
                let idx = (x * ny + y) * nz;
                gt[idx] = [9, 11, 17, 10][(x / 40 + y / 50) % 4];
                if (x / 8 + y / 8) % 7 == 0 {
                    for z in 1..rng.random_range(2..12) {
                        gt[idx + z] = [1, 13, 15, 18][(x / 64) % 4];
                    }
                }
            }
        }
        for v in gt.iter_mut() {
            if rng.random_bool(0.02) {
                *v = 255;
            }
        }
        let pred: Vec<u8> = gt
            .iter()
            .map(|&g| {
                if rng.random_bool(0.7) && g != 255 {
                    g
                } else if rng.random_bool(0.5) {
                    0
                } else {
                    rng.random_range(0..20)
                }
            })
            .collect();
        let invalid: Vec<u8> = (0..gt.len())
            .map(|i| u8::from((i / 4096) % 5 == 0))
            .collect();
        frames.push(Frame {
            pred,
            gt,
            mask: Some(invalid),
        });
    }
    let r = check(Protocol::SemanticKitti, &frames, "kitti-256");
    assert!(r.evaluated_voxels > 3_000_000);
    // The same frames scored by nuScenes-Occupancy / Occ3D rules (labels are in range for both).
    let clipped: Vec<Frame> = frames
        .iter()
        .map(|f| Frame {
            pred: f.pred.iter().map(|&p| p.min(16)).collect(),
            gt: f
                .gt
                .iter()
                .map(|&g| if g == 255 { g } else { g.min(16) })
                .collect(),
            mask: f.mask.as_ref().map(|m| m.iter().map(|&v| 1 - v).collect()),
        })
        .collect();
    check(Protocol::NuScenesOccupancy, &clipped, "nusc-256");
    check(Protocol::Occ3d, &clipped, "occ3d-256");
}

#[test]
fn hand_computed_semantic_kitti() {
    // np_ioueval.py's own example: 7x7 grid, GT square [2:4,2:4]=1, prediction square [3:5,3:5]=1.
    let mut gt = vec![0u8; 49];
    let mut pred = vec![0u8; 49];
    for r in 2..4 {
        for c in 2..4 {
            gt[r * 7 + c] = 1;
        }
    }
    for r in 3..5 {
        for c in 3..5 {
            pred[r * 7 + c] = 1;
        }
    }
    let mut ev = Evaluator::new(Protocol::SemanticKitti);
    ev.add_frame(&pred, &gt, EvalMask::All, "squares").unwrap();
    let r = ev.report();
    // class 1: TP 1, FP 3, FN 3 -> 1/7. Classes 2..19 absent -> 0 (with the 1e-15). mIoU = (1/7)/19.
    assert!((r.per_class.get("car").unwrap() - 1.0 / 7.0).abs() < 1e-12);
    assert_eq!(r.per_class.get("bicycle"), Some(0.0));
    assert!((r.miou - 1.0 / 7.0 / 19.0).abs() < 1e-12);
    // Completion: occupied TP 1, pred occupied 4, GT occupied 4; total 49, empty-empty 42.
    assert!((r.iou - 1.0 / 7.0).abs() < 1e-12);
    assert!((r.precision - 0.25).abs() < 1e-6);
    assert!((r.recall - 0.25).abs() < 1e-6);
    let c = ev.confusion();
    assert_eq!(
        (c.get(0, 0), c.get(1, 1), c.get(1, 0), c.get(0, 1)),
        (42, 1, 3, 3)
    );

    // Masks: GT 255 and invalid==1 are excluded; invalid==2 is kept (only ==1 excludes).
    let gt = [1u8, 1, 255, 2, 0, 0];
    let pred = [1u8, 2, 1, 2, 255, 3];
    let invalid = [0u8, 0, 0, 1, 2, 0];
    let mut ev = Evaluator::new(Protocol::SemanticKitti);
    ev.add_frame(&pred, &gt, EvalMask::Invalid(&invalid), "masked")
        .unwrap();
    let r = ev.report();
    assert_eq!(r.evaluated_voxels, 4);
    assert_eq!(r.invalid_predictions, 1); // pred 255 at a kept voxel -> scored as empty
                                          // car: TP 1, FN 1 (pred bicycle) -> 1/2; bicycle: FP 1 -> 0; motorcycle: FP 1 -> 0.
    assert!((r.per_class.get("car").unwrap() - 0.5).abs() < 1e-12);
    assert_eq!(r.per_class.get("bicycle"), Some(0.0));
    // Completion: occupied TP = 2 (car/car, bicycle/car), pred occ 3, GT occ 2; empty-empty 1.
    assert!((r.iou - 2.0 / 3.0).abs() < 1e-12);
    assert!((r.precision - 2.0 / 3.0).abs() < 1e-6);
    assert!((r.recall - 1.0).abs() < 1e-6);
}

/// Non-ground recall by hand: GT car (1), car, road (9), building (13), terrain (17), fence (14);
/// predicted road, empty, road, road, empty, fence. The ground classes (road, terrain) do not count;
/// of the other four GT voxels, car/road, building/road and fence/fence are predicted occupied (the
/// class need not match): 3 of 4. Restricted to
/// {road, terrain}: road/road is occupied, terrain/empty is not: 1 of 2.
#[test]
fn hand_computed_non_ground_recall() {
    use occ_eval::SEMANTIC_KITTI_GROUND_CLASSES;
    let gt = [1u8, 1, 9, 13, 17, 14];
    let pred = [9u8, 0, 9, 9, 0, 14];
    let mut ev = Evaluator::new(Protocol::SemanticKitti);
    ev.add_frame(&pred, &gt, EvalMask::All, "ng").unwrap();
    let r = ev.report();
    assert!((r.non_ground_recall(&SEMANTIC_KITTI_GROUND_CLASSES) - 0.75).abs() < 1e-12);
    assert!((r.occupied_recall_of(&[9, 17]) - 0.5).abs() < 1e-12);
    assert!(r.occupied_recall_of(&[2]).is_nan());
}

#[test]
fn hand_computed_occ3d_and_nuscenes() {
    // Occ3D: classes 0 (others), 4 (car), 17 (free). Camera mask drops the last voxel.
    let gt = [4u8, 4, 17, 17, 0, 4];
    let pred = [4u8, 17, 4, 17, 0, 0];
    let cam = [1u8, 1, 1, 1, 1, 0];
    let mut ev = Evaluator::new(Protocol::Occ3d);
    ev.add_frame(&pred, &gt, EvalMask::Visible(&cam), "occ3d")
        .unwrap();
    let r = ev.report();
    // car: TP 1, pred 2, gt 2 -> 1/3; others: 1/1; absent classes NaN and skipped by nanmean.
    assert!((r.per_class.get("car").unwrap() - 1.0 / 3.0).abs() < 1e-12);
    assert_eq!(r.per_class.get("others"), Some(1.0));
    assert!(r.per_class.get("bus").unwrap().is_nan());
    assert!(
        r.per_class.get("free").is_none(),
        "free is not an mIoU class"
    );
    assert!((r.miou - (1.0 + 1.0 / 3.0) / 2.0).abs() < 1e-12);
    // Geometry vs free: occupied-occupied 2 (car, others), total 5, free-free 1 -> 2/4.
    assert!((r.iou - 0.5).abs() < 1e-12);

    // nuScenes-Occupancy: an absent class makes the official np.mean NaN.
    let mut ev = Evaluator::new(Protocol::NuScenesOccupancy);
    ev.add_frame(&[4, 0, 4], &[4, 4, 255], EvalMask::All, "nusc")
        .unwrap();
    let r = ev.report();
    assert!((r.per_class.get("car").unwrap() - 0.5).abs() < 1e-12);
    assert!(r.miou.is_nan());
    assert!((r.iou - 0.5).abs() < 1e-12);
    // With every class 1..16 present and predicted exactly, mIoU is 1.
    let gt: Vec<u8> = (0..17).collect();
    let mut ev = Evaluator::new(Protocol::NuScenesOccupancy);
    ev.add_frame(&gt, &gt, EvalMask::All, "all").unwrap();
    assert_eq!(ev.report().miou, 1.0);
}

#[test]
fn merge_json_roundtrip_and_table() {
    let mut rng = ChaCha8Rng::seed_from_u64(9);
    let frames = random_frames(&mut rng, Protocol::Occ3d, 4, 3000, true);
    let mut whole = Evaluator::new(Protocol::Occ3d);
    let mut a = Evaluator::new(Protocol::Occ3d);
    let mut b = Evaluator::new(Protocol::Occ3d);
    for (i, f) in frames.iter().enumerate() {
        let m = EvalMask::Visible(f.mask.as_ref().unwrap());
        whole.add_frame(&f.pred, &f.gt, m, "f").unwrap();
        if i % 2 == 0 { &mut a } else { &mut b }
            .add_frame(&f.pred, &f.gt, m, "f")
            .unwrap();
    }
    a.merge(&b).unwrap();
    assert_eq!(a, whole);
    assert!(a.merge(&Evaluator::new(Protocol::SemanticKitti)).is_err());

    // JSON: class order kept, NaN as null, and the report can be rebuilt and merged.
    let mut ev = Evaluator::new(Protocol::Occ3d);
    ev.add_frame(&[4, 17], &[4, 17], EvalMask::All, "t")
        .unwrap();
    let r = ev.report();
    let json = serde_json::to_string(&r).unwrap();
    let v: serde_json::Value = serde_json::from_str(&json).unwrap();
    assert_eq!(v["dataset"], "occ3d");
    assert!(v["per_class"]["barrier"].is_null());
    assert_eq!(v["per_class"]["car"], 1.0);
    let keys: Vec<&str> = {
        let start = json.find("\"per_class\"").unwrap();
        let obj = &json[start..json[start..].find('}').unwrap() + start];
        obj.split('"').skip(3).step_by(2).collect()
    };
    assert_eq!(keys[0], "others");
    assert_eq!(keys[4], "car");
    assert_eq!(keys.len(), 17);
    let back: EvalReport = serde_json::from_str(&json).unwrap();
    assert_eq!(back.per_class.0.len(), 17);
    assert!(back.per_class.get("bus").unwrap().is_nan());
    assert_eq!(Evaluator::from_report(&back).unwrap(), ev);

    let table = format_table(&whole.report());
    assert!(table.contains("vegetation") && table.contains("mIoU") && table.contains("warning"));
    assert_eq!(table.lines().filter(|l| l.starts_with("car ")).count(), 1);
}

#[test]
fn size_mismatch_is_an_error() {
    let mut ev = Evaluator::new(Protocol::SemanticKitti);
    let e = ev
        .add_frame(&[0, 1], &[0], EvalMask::All, "seq08/000000")
        .unwrap_err();
    assert!(e.to_string().contains("seq08/000000"), "{e}");
    assert!(ev
        .add_frame(&[0], &[0], EvalMask::Invalid(&[0, 0]), "x")
        .is_err());
    assert_eq!(ev.frames(), 0);
}

/// Counts whose sum does not fit a `u64` (every metric would be taken from wrapped sums: an mIoU
/// of -1 was reported) are refused when a matrix is taken in, from arrays, from a report's JSON
/// or by a merge; the largest sum that fits is still scored.
#[test]
fn counts_that_overflow_are_refused() {
    use occ_eval::ConfusionMatrix;
    let n = Protocol::SemanticKitti.num_classes();
    let rows = |v: u64| vec![vec![v; n]; n];
    let over = ConfusionMatrix::from_rows(&rows(1 << 63)).unwrap();
    let e = Evaluator::from_confusion(Protocol::SemanticKitti, over, 1).unwrap_err();
    assert!(e.to_string().contains("2^64 - 1"), "{e}");

    let mut fits = rows(0);
    fits[1][1] = u64::MAX - 7;
    fits[0][0] = 7;
    let conf = ConfusionMatrix::from_rows(&fits).unwrap();
    let ev = Evaluator::from_confusion(Protocol::SemanticKitti, conf, 1).unwrap();
    let r = ev.report();
    assert_eq!(r.per_class.get("car"), Some(1.0));
    assert_eq!(r.iou, 1.0);

    let mut json = r.clone();
    json.confusion[2][2] = 1;
    assert!(Evaluator::from_report(&json).is_err());

    let mut one = rows(0);
    one[1][1] = 1;
    let one = ConfusionMatrix::from_rows(&one).unwrap();
    let mut full = ev.clone();
    let e = full
        .merge(&Evaluator::from_confusion(Protocol::SemanticKitti, one, 1).unwrap())
        .unwrap_err();
    assert!(e.to_string().contains("more than 2^64 - 1"), "{e}");
    assert_eq!(full, ev, "a refused merge adds nothing");
}
