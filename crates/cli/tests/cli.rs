//! End-to-end tests of the `sparseocc` binary on tiny synthetic data: train → checkpoint → resume →
//! infer (dataset and single image) → eval → bench, and the errors users get for bad input.

use std::path::{Path, PathBuf};

mod support;
use support::{fails, ok, p};

fn tmp(name: &str) -> PathBuf {
    support::tmp("cli", name)
}

/// A very small SparseOcc++ on the kitti-small grid ([`support::tiny_config`]).
static TINY: std::sync::LazyLock<String> =
    std::sync::LazyLock::new(|| support::tiny_config(3, 2, &["08"]));

/// `sparseocc infer --checkpoint RUN --data DATA --sequences 08 --out OUT EXTRA...`.
fn infer_08(run: &Path, data: &Path, out: &Path, extra: &[&str]) -> String {
    let mut args = vec![
        "infer",
        "--checkpoint",
        p(run),
        "--data",
        p(data),
        "--sequences",
        "08",
        "--out",
        p(out),
    ];
    args.extend_from_slice(extra);
    ok(&args)
}

#[test]
fn train_resume_infer_eval_and_bad_input() {
    let root = tmp("e2e");
    let data = root.join("data");
    ok(&["synth", "--out", p(&data), "--sequences", "00:2,08:1"]);
    let cfg = root.join("tiny.toml");
    std::fs::write(&cfg, TINY.as_str()).unwrap();
    let run_dir = root.join("run");

    // Train 3 steps (checkpoints at 2 and 3), then resume to 4.
    ok(&[
        "train",
        "--config",
        p(&cfg),
        "--data",
        p(&data),
        "--out",
        p(&run_dir),
    ]);
    for f in [
        "config.toml",
        "grid.json",
        "train_log.csv",
        "summary.json",
        "checkpoint/model.bin",
        "curves.png",
    ] {
        assert!(run_dir.join(f).exists(), "{f} missing");
    }
    let curves = occ_data::image::read_png(&run_dir.join("curves.png")).unwrap();
    assert_eq!((curves.width, curves.height), (1000, 600));
    let summary: serde_json::Value =
        serde_json::from_slice(&std::fs::read(run_dir.join("summary.json")).unwrap()).unwrap();
    let miou = summary["miou"].as_f64().expect("validation mIoU");
    assert!((0.0..=1.0).contains(&miou));
    let text = ok(&[
        "train",
        "--data",
        p(&data),
        "--out",
        p(&run_dir),
        "--resume",
        "--steps",
        "4",
    ]);
    assert!(text.contains("resumed from step 3"), "{text}");
    let log = std::fs::read_to_string(run_dir.join("train_log.csv")).unwrap();
    assert_eq!(log.lines().filter(|l| l.starts_with("step,")).count(), 1);
    assert!(log.lines().any(|l| l.starts_with("4,")), "{log}");

    // Infer on the held-out sequence; every frame gets a submission file; eval scores it.
    let pred = root.join("pred");
    infer_08(&run_dir, &data, &pred, &[]);
    let label = pred.join("sequences/08/predictions/000000.label");
    assert_eq!(std::fs::metadata(&label).unwrap().len(), 128 * 128 * 16 * 2);
    assert!(pred.join("renders/08_000000.png").exists());
    // The same with test-time mirror averaging, switched on and off on the command line.
    for flag in [&["--test-mirror"][..], &["--test-mirror", "false"][..]] {
        let pred_m = root.join("pred_mirror");
        infer_08(
            &run_dir,
            &data,
            &pred_m,
            &[&["--render", "0"][..], flag].concat(),
        );
        let label_m = pred_m.join("sequences/08/predictions/000000.label");
        assert_eq!(
            std::fs::metadata(&label_m).unwrap().len(),
            128 * 128 * 16 * 2
        );
        let summary_m: serde_json::Value =
            serde_json::from_slice(&std::fs::read(pred_m.join("summary.json")).unwrap()).unwrap();
        let on = flag.len() == 1;
        assert_eq!(summary_m["test_mirror"], serde_json::json!(on), "{flag:?}");
    }
    let json = root.join("eval.json");
    ok(&[
        "eval",
        "--dataset",
        "semantickitti",
        "--gt",
        p(&data),
        "--pred",
        p(&pred),
        "--sequences",
        "08",
        "--json",
        p(&json),
    ]);

    // Single camera image with its calibration.
    let single = root.join("single");
    let img = data.join("sequences/08/image_2/000000.png");
    let calib = data.join("sequences/08/calib.txt");
    ok(&[
        "infer",
        "--checkpoint",
        p(&run_dir.join("checkpoint")),
        "--image",
        p(&img),
        "--calib",
        p(&calib),
        "--out",
        p(&single),
    ]);
    assert!(single.join("000000.label").exists() && single.join("000000.png").exists());

    // Bad input: clear errors, no panics.
    let train_fails = |config: &Path, out: &str| {
        fails(&[
            "train",
            "--config",
            p(config),
            "--data",
            p(&data),
            "--out",
            p(&root.join(out)),
        ])
    };
    let e = train_fails(&root.join("nope.toml"), "r2");
    assert!(e.contains("nope.toml"), "{e}");
    let bad = root.join("bad.toml");
    std::fs::write(&bad, TINY.replace("depth = 18", "depth = 19")).unwrap();
    let e = train_fails(&bad, "r3");
    assert!(e.contains("bad.toml") && e.contains("19"), "{e}");
    std::fs::write(&bad, TINY.replace("[train]", "[train]\nlearning_rate = 1")).unwrap();
    let e = train_fails(&bad, "r4");
    assert!(e.contains("learning_rate"), "{e}");
    // A checkpoint whose config no longer matches its weights.
    let mism = root.join("mismatch");
    support::copy_file(
        &run_dir.join("checkpoint/model.bin"),
        &mism.join("checkpoint/model.bin"),
    );
    std::fs::copy(run_dir.join("grid.json"), mism.join("grid.json")).unwrap();
    let saved = std::fs::read_to_string(run_dir.join("config.toml")).unwrap();
    std::fs::write(
        mism.join("config.toml"),
        saved.replace("embed_dim = 16", "embed_dim = 24"),
    )
    .unwrap();
    let e = fails(&[
        "infer",
        "--checkpoint",
        p(&mism),
        "--data",
        p(&data),
        "--sequences",
        "08",
        "--out",
        p(&root.join("p2")),
    ]);
    assert!(e.contains("model.bin") && e.contains("config.toml"), "{e}");
    // An image that does not belong to the calibration (principal point outside it).
    let small = root.join("small.png");
    let rgb = occ_data::image::RgbImage {
        width: 200,
        height: 60,
        data: vec![90; 200 * 60 * 3],
    };
    occ_data::image::write_png(&small, &rgb).unwrap();
    let e = fails(&[
        "infer",
        "--checkpoint",
        p(&run_dir),
        "--image",
        p(&small),
        "--calib",
        p(&calib),
        "--out",
        p(&root.join("p3")),
    ]);
    assert!(e.contains("small.png") && e.contains("calibration"), "{e}");
    // Missing sequence folder.
    let e = fails(&[
        "infer",
        "--checkpoint",
        p(&run_dir),
        "--data",
        p(&data),
        "--sequences",
        "05",
        "--out",
        p(&root.join("p4")),
    ]);
    assert!(e.contains("05"), "{e}");
    // The demo refuses to train on its held-out street, and a reversed sequence range, before
    // writing anything.
    let demo_out = root.join("demo");
    let e = fails(&["demo", "--out", p(&demo_out), "--train", "00-09:1"]);
    assert!(e.contains("08") && e.contains("--val"), "{e}");
    let e = fails(&["demo", "--out", p(&demo_out), "--train", "07-03:2"]);
    assert!(e.contains("07-03:2"), "{e}");
    assert!(!demo_out.exists());
    let _ = std::fs::remove_dir_all(&root);
}

/// The loss of the first step of a fresh run (the initial weights on the first sample, before any
/// update).
fn first_loss(cfg: &Path, data: &Path, out: &Path) -> String {
    ok(&[
        "train",
        "--config",
        p(cfg),
        "--data",
        p(data),
        "--out",
        p(out),
        "--steps",
        "1",
        "--val-sequences",
        "",
    ]);
    let log = std::fs::read_to_string(out.join("train_log.csv")).unwrap();
    let line = log.lines().find(|l| l.starts_with("1,")).expect("step 1");
    line.split(',').nth(2).unwrap().to_string()
}

/// `train.seed` fixes the initial weights: two fresh runs of one config start from the same network
/// (the same first-step loss, to the digit), another seed from another one.
#[test]
fn train_seed_fixes_the_initial_weights() {
    let root = tmp("seed");
    let data = root.join("data");
    ok(&["synth", "--out", p(&data), "--sequences", "00:1"]);
    let cfg0 = root.join("seed0.toml");
    std::fs::write(&cfg0, TINY.replace("lr = 1e-3", "lr = 1e-3\nseed = 3")).unwrap();
    let cfg1 = root.join("seed1.toml");
    std::fs::write(&cfg1, TINY.replace("lr = 1e-3", "lr = 1e-3\nseed = 4")).unwrap();
    let a = first_loss(&cfg0, &data, &root.join("a"));
    let b = first_loss(&cfg0, &data, &root.join("b"));
    let c = first_loss(&cfg1, &data, &root.join("c"));
    assert_eq!(a, b, "same seed, different first losses");
    assert_ne!(a, c, "seeds 3 and 4 gave the same first loss {a}");
    let _ = std::fs::remove_dir_all(&root);
}

/// [`TINY`] on the six-camera Occ3D layout (synthetic `surround` data at 160x64).
fn tiny_occ3d() -> String {
    TINY.replace("num_classes = 20", "num_classes = 18")
        .replace("full_dims = [128, 128, 16]", "full_dims = [200, 200, 16]")
        .replace(
            "train_sequences = [\"00\"]\nval_sequences = [\"08\"]",
            "format = \"occ3d\"\ntrain_sequences = [\"*\"]\nval_sequences = [\"scene-b\"]",
        )
}

#[test]
fn surround_occ3d_train_infer_eval() {
    let root = tmp("surround");
    let data = root.join("data");
    ok(&[
        "synth",
        "--preset",
        "surround",
        "--out",
        p(&data),
        "--sequences",
        "a:2,b:1",
        "--image-size",
        "160x64",
    ]);
    let cfg = root.join("occ3d.toml");
    let text = tiny_occ3d();
    assert!(text.contains("format = \"occ3d\""));
    std::fs::write(&cfg, text).unwrap();
    let run = root.join("run");
    let text = ok(&[
        "train",
        "--config",
        p(&cfg),
        "--data",
        p(&data),
        "--out",
        p(&run),
    ]);
    // "*" trains on every scene but the validation one.
    assert!(text.contains("on 2 frames"), "{text}");
    let summary: serde_json::Value =
        serde_json::from_slice(&std::fs::read(run.join("summary.json")).unwrap()).unwrap();
    assert!(summary["iou"].as_f64().is_some(), "{summary}");
    // Inference over both scenes writes Occ3D labels.npz per sample; the official folder scorer
    // reproduces the score infer reports.
    let pred = root.join("pred");
    ok(&[
        "infer",
        "--checkpoint",
        p(&run),
        "--data",
        p(&data),
        "--sequences",
        "scene-a,scene-b",
        "--out",
        p(&pred),
        "--render",
        "1",
    ]);
    let n_npz = walk(&pred)
        .iter()
        .filter(|f| f.ends_with("labels.npz"))
        .count();
    assert_eq!(n_npz, 3);
    assert!(pred.join("renders").read_dir().unwrap().count() == 1);
    let infer: serde_json::Value =
        serde_json::from_slice(&std::fs::read(pred.join("summary.json")).unwrap()).unwrap();
    let json = root.join("eval.json");
    ok(&[
        "eval",
        "--dataset",
        "occ3d",
        "--gt",
        p(&data),
        "--pred",
        p(&pred),
        "--json",
        p(&json),
    ]);
    let ev: serde_json::Value = serde_json::from_slice(&std::fs::read(&json).unwrap()).unwrap();
    assert_eq!(ev["iou"], infer["iou"], "{ev} vs {infer}");
    assert_eq!(ev["miou"], infer["miou"]);
    // A camera image that does not match its sample_data size is a clear error naming the file.
    let front = walk(&data.join("samples").join("CAM_FRONT"))
        .into_iter()
        .next()
        .unwrap();
    let img = occ_data::image::RgbImage::new(100, 50);
    occ_data::image::write_png(Path::new(&front), &img).unwrap();
    let e = fails(&[
        "infer",
        "--checkpoint",
        p(&run),
        "--data",
        p(&data),
        "--sequences",
        "scene-a",
        "--out",
        p(&root.join("pred2")),
    ]);
    assert!(e.contains("CAM_FRONT") && e.contains("100x50"), "{e}");
    let _ = std::fs::remove_dir_all(&root);
}

/// Every file below `dir` (paths as strings).
fn walk(dir: &Path) -> Vec<String> {
    let mut out = Vec::new();
    let mut stack = vec![dir.to_path_buf()];
    while let Some(d) = stack.pop() {
        for e in std::fs::read_dir(&d).unwrap().flatten() {
            let path = e.path();
            if path.is_dir() {
                stack.push(path);
            } else {
                out.push(path.to_string_lossy().into_owned());
            }
        }
    }
    out.sort();
    out
}

#[test]
fn bench_reports_every_model_on_the_same_input() {
    let root = tmp("bench");
    let cfg = root.join("tiny.toml");
    let tiny = TINY.to_string()
        + "\n"
        + r#"
[model.sparseocc]
lss_channels = 8
lss_mid_channels = 8
dbound = [2.0, 58.0, 2.0]
propagator_channels = [8, 8, 8, 8]
completion_layers = [1, 1, 1, 1]
decoder_channels = 8
norm_groups = 4
num_queries = 4
decoder_layers = 1
num_heads = 2
ffn_channels = 16
num_points = 256

[model.dense]
lss_channels = 8
lss_mid_channels = 8
dbound = [2.0, 58.0, 2.0]
encoder_channels = [8]
"#;
    // The [model.sparseocc] / [model.dense] tables must come inside [model]: move [train]/[data] last.
    let (head, tail) = tiny.split_at(tiny.find("[train]").unwrap());
    let (train_data, extra) = tail.split_at(tail.find("\n[model.sparseocc]").unwrap());
    std::fs::write(&cfg, format!("{head}{extra}\n{train_data}")).unwrap();
    let json = root.join("bench.json");
    let text = ok(&[
        "bench",
        "--config",
        p(&cfg),
        "--frames",
        "1",
        "--warmup",
        "0",
        "--json",
        p(&json),
    ]);
    assert!(
        text.contains("sparseocc++") && text.contains("dense"),
        "{text}"
    );
    let v: serde_json::Value = serde_json::from_slice(&std::fs::read(&json).unwrap()).unwrap();
    let results = v["results"].as_array().unwrap();
    assert_eq!(results.len(), 3);
    assert!(v["sgemm_gflops"].as_f64().unwrap() > 0.0);
    for r in results {
        assert!(r["median_ms"].as_f64().unwrap() > 0.0);
        assert!(r["peak_rss_mib"].as_f64().unwrap() > 0.0);
        assert!(!r["profile_ms"].as_array().unwrap().is_empty());
        // FLOPs: every model counts work, the stages add up to the total, and so do the ops; every
        // model runs the image encoder's conv2d and sparse (or all-active) 3D convs.
        let total = r["gflops"].as_f64().unwrap();
        assert!(
            total > 0.0 && r["gflops_per_s"].as_f64().unwrap() > 0.0,
            "{r}"
        );
        let stages = r["profile_stages"].as_array().unwrap();
        let by_stage: f64 = stages.iter().map(|s| s["gflops"].as_f64().unwrap()).sum();
        assert!((by_stage - total).abs() <= 1e-9 * total, "{r}");
        let ops = r["gflops_by_op"].as_array().unwrap();
        let by_op: f64 = ops.iter().map(|o| o[1].as_f64().unwrap()).sum();
        assert!((by_op - total).abs() <= 1e-9 * total, "{r}");
        for op in ["conv2d", "sparse_conv", "linear"] {
            assert!(
                ops.iter()
                    .any(|o| o[0] == op && o[1].as_f64().unwrap() > 0.0),
                "{op} missing: {r}"
            );
        }
        let enc = stages.iter().find(|s| s["stage"] == "encoder").unwrap();
        assert!(enc["gflops"].as_f64().unwrap() > 0.0, "{r}");
    }
    let _ = std::fs::remove_dir_all(&root);
}

#[test]
fn check_backend_agrees_with_itself_on_the_cpu() {
    let text = ok(&["check-backend"]);
    assert!(text.contains("agrees with the NdArray reference"), "{text}");
}

/// A CPU build has no CUDA compiler: `check-cuda-source` says how to build one, with status 1.
#[cfg(not(feature = "cuda-source"))]
#[test]
fn check_cuda_source_asks_for_the_cuda_build() {
    let text = support::fails_status_1(&["check-cuda-source"]);
    assert!(text.contains("--features cuda"), "{text}");
}
