//! Table-driven bad-input tests of the `sparseocc` binary: one row per case (arguments, expected
//! exit status, substrings the error must contain), each checked for no panic, no abort and no
//! output left half-written; plus concurrent writers of one output and a training run killed with
//! SIGKILL and resumed. Everything runs on one tiny synthetic dataset (`synth`, kitti-small, one
//! frame per sequence) and the random-weights model of [`TINY`], so the whole file takes seconds.

use std::ffi::{OsStr, OsString};
use std::path::{Path, PathBuf};
use std::process::Stdio;

mod support;
use support::{bin, copy_dir, ok, run};

fn tmp(name: &str) -> PathBuf {
    support::tmp("bad", name)
}

/// A tiny SparseOcc++ on the kitti-small grid ([`support::tiny_config`]): 2 steps, a checkpoint
/// after each, no validation.
static TINY: std::sync::LazyLock<String> =
    std::sync::LazyLock::new(|| support::tiny_config(2, 1, &[]));

/// A small valid PNG whose header claims `w` x `h` pixels.
fn png_claiming(w: u32, h: u32) -> Vec<u8> {
    let img = occ_data::image::RgbImage {
        width: 4,
        height: 4,
        data: vec![9; 48],
    };
    occ_testdata::png_claiming_size(&occ_data::image::encode_png(&img).unwrap(), w, h)
}

/// Every file below `dir` (recursively).
fn files_below(dir: &Path) -> Vec<PathBuf> {
    let mut out = Vec::new();
    if let Ok(rd) = std::fs::read_dir(dir) {
        for e in rd.flatten() {
            let p = e.path();
            if p.is_dir() {
                out.extend(files_below(&p));
            }
            out.push(p);
        }
    }
    out
}

/// No output is half-written: no temporary files left below `dir`, and every JSON file there
/// parses.
fn assert_no_partial_output(dir: &Path, case: &str) {
    for p in files_below(dir) {
        let name = p.file_name().unwrap().to_string_lossy().into_owned();
        assert!(
            !name.contains(".tmp-") && !name.ends_with(".tmp"),
            "{case}: temporary {} left",
            p.display()
        );
        if name.ends_with(".json") && p.is_file() {
            let b = std::fs::read(&p).unwrap();
            assert!(
                serde_json::from_slice::<serde_json::Value>(&b).is_ok(),
                "{case}: {} is not valid JSON",
                p.display()
            );
        }
    }
}

/// One row: `args`, the expected exit status, substrings of stderr, and outputs that must not
/// exist afterwards.
struct Case {
    name: &'static str,
    args: Vec<OsString>,
    status: i32,
    want: Vec<String>,
    absent: Vec<PathBuf>,
}

fn os(args: &[&dyn AsRef<OsStr>]) -> Vec<OsString> {
    args.iter().map(|a| a.as_ref().to_os_string()).collect()
}

fn check_case(c: &Case, out_root: &Path) {
    let o = run(&c.args);
    let err = String::from_utf8_lossy(&o.stderr).into_owned();
    assert_eq!(
        o.status.code(),
        Some(c.status),
        "{}: exit status {:?} (no code = killed by a signal), expected {}:\n{err}",
        c.name,
        o.status,
        c.status
    );
    assert!(!err.contains("panicked"), "{}: panicked:\n{err}", c.name);
    if c.status != 0 {
        let line = err
            .lines()
            .find(|l| l.starts_with("error:"))
            .unwrap_or_else(|| panic!("{}: no error line:\n{err}", c.name));
        for w in &c.want {
            assert!(
                line.contains(w.as_str()),
                "{}: error without `{w}`: {line}",
                c.name
            );
        }
        // An OS error is printed once, not once per wrapping layer.
        for os_err in [
            "No such file or directory",
            "Is a directory",
            "Not a directory",
        ] {
            assert!(
                line.matches(os_err).count() <= 1,
                "{}: `{os_err}` repeated: {line}",
                c.name
            );
        }
    }
    for a in &c.absent {
        assert!(!a.exists(), "{}: {} was written", c.name, a.display());
    }
    assert_no_partial_output(out_root, c.name);
}

#[test]
fn bad_input_table() {
    let root = tmp("table");
    let data = root.join("data");
    ok(&[
        OsStr::new("synth"),
        OsStr::new("--out"),
        data.as_os_str(),
        OsStr::new("--sequences"),
        OsStr::new("00:1,08:1"),
    ]);
    let cfg = root.join("tiny.toml");
    std::fs::write(&cfg, TINY.as_str()).unwrap();
    let out = root.join("out");
    std::fs::create_dir_all(&out).unwrap();
    let calib = data.join("sequences/08/calib.txt");
    let gt_label = data.join("sequences/08/voxels/000000.label");

    // Predictions = the ground truth (a valid submission folder).
    let pred = root.join("pred");
    support::copy_file(
        &gt_label,
        &pred.join("sequences/08/predictions/000000.label"),
    );

    // Bad configs: one line changed in TINY.
    let bad_cfg = |name: &str, from: &str, to: &str| -> PathBuf {
        assert!(TINY.contains(from), "{from}");
        let p = root.join(name);
        std::fs::write(&p, TINY.replacen(from, to, 1)).unwrap();
        p
    };
    // Hostile and contradicting images.
    let huge = root.join("huge.png");
    std::fs::write(&huge, png_claiming(100_000, 100_000)).unwrap();
    let small = root.join("small.png");
    occ_data::image::write_png(
        &small,
        &occ_data::image::RgbImage {
            width: 200,
            height: 60,
            data: vec![90; 200 * 60 * 3],
        },
    )
    .unwrap();
    // A dataset whose image of 08 contradicts its calibration.
    let data_small = root.join("data_small");
    copy_dir(&data, &data_small);
    std::fs::copy(&small, data_small.join("sequences/08/image_2/000000.png")).unwrap();
    // A dataset whose image of 08 claims 100000x100000 pixels.
    let data_huge = root.join("data_huge");
    copy_dir(&data, &data_huge);
    std::fs::copy(&huge, data_huge.join("sequences/08/image_2/000000.png")).unwrap();
    // A calibration whose Tr scales the points (not a rotation): the projection would be silently
    // wrong.
    let data_bad_tr = root.join("data_bad_tr");
    copy_dir(&data, &data_bad_tr);
    let bad_tr_calib = data_bad_tr.join("sequences/08/calib.txt");
    let scaled: String = std::fs::read_to_string(&bad_tr_calib)
        .unwrap()
        .lines()
        .map(|l| match l.strip_prefix("Tr:") {
            Some(v) => {
                let v: Vec<String> = v
                    .split_whitespace()
                    .map(|x| format!("{:e}", x.parse::<f64>().unwrap() * 1000.0))
                    .collect();
                format!("Tr: {}\n", v.join(" "))
            }
            None => format!("{l}\n"),
        })
        .collect();
    std::fs::write(&bad_tr_calib, scaled).unwrap();
    // A labelled frame without its image.
    let data_noimg = root.join("data_noimg");
    copy_dir(&data, &data_noimg);
    std::fs::remove_file(data_noimg.join("sequences/08/image_2/000000.png")).unwrap();
    // A validation frame whose label file is cut short.
    let data_trunc = root.join("data_trunc");
    copy_dir(&data, &data_trunc);
    let trunc = data_trunc.join("sequences/08/voxels/000000.label");
    let full = std::fs::read(&trunc).unwrap();
    std::fs::write(&trunc, &full[..full.len() - 100]).unwrap();
    // A validation frame whose image is cut short (an interrupted copy), and a JPEG cut in half:
    // both refused from the file's structure, before a pixel is decoded.
    let data_cut_img = root.join("data_cut_img");
    copy_dir(&data, &data_cut_img);
    let cut_img = data_cut_img.join("sequences/08/image_2/000000.png");
    let full_img = std::fs::read(&cut_img).unwrap();
    std::fs::write(&cut_img, &full_img[..full_img.len() * 2 / 3]).unwrap();
    // A labelled training frame without its mask of unobserved voxels.
    let data_no_invalid = root.join("data_no_invalid");
    copy_dir(&data, &data_no_invalid);
    std::fs::remove_file(data_no_invalid.join("sequences/00/voxels/000000.invalid")).unwrap();
    let jpeg = std::fs::read(
        Path::new(env!("CARGO_MANIFEST_DIR")).join("../data/tests/data/pattern_420.jpg"),
    )
    .unwrap();
    let cut_jpeg = root.join("cut.jpg");
    std::fs::write(&cut_jpeg, &jpeg[..jpeg.len() / 2]).unwrap();
    // Ground truth with ids outside the learning map, and a ground truth that is a folder.
    let gt_unknown = root.join("gt_unknown");
    copy_dir(&data, &gt_unknown);
    let n = std::fs::metadata(&gt_label).unwrap().len() as usize / 2;
    let unknown: Vec<u8> = (0..n).flat_map(|_| 300u16.to_le_bytes()).collect();
    std::fs::write(gt_unknown.join("sequences/08/voxels/000000.label"), unknown).unwrap();
    let gt_dir = root.join("gt_dir");
    copy_dir(&data, &gt_dir);
    std::fs::create_dir_all(gt_dir.join("sequences/08/voxels/000001.label")).unwrap();
    // A run folder without a checkpoint, and one with a truncated model.bin.
    let no_ck = root.join("no_ck");
    std::fs::create_dir_all(&no_ck).unwrap();
    std::fs::write(no_ck.join("config.toml"), TINY.as_str()).unwrap();
    let bad_json = root.join("bad.json");
    std::fs::write(&bad_json, "{ not json").unwrap();

    // A command that must fail with status 1, naming `want` and leaving nothing at `absent`.
    let fails =
        |name: &'static str, args: Vec<OsString>, want: Vec<String>, absent: PathBuf| Case {
            name,
            args,
            status: 1,
            want,
            absent: vec![absent],
        };
    // A command line that clap refuses (status 2), naming `want`; its `--json out/json` is not
    // written.
    let usage = |name: &'static str, args: &[&dyn AsRef<OsStr>], want: Vec<String>, json: &str| {
        let mut args = os(args);
        args.extend(os(&[&"--json", &out.join(json)]));
        Case {
            status: 2,
            ..fails(name, args, want, out.join(json))
        }
    };
    // `train --config cfg --data d --out out/o` and `extra`, refused before anything is written
    // into the run folder.
    let train_data =
        |name: &'static str, d: &Path, extra: &[&dyn AsRef<OsStr>], want: Vec<String>, o: &str| {
            let run = out.join(o);
            let mut args = os(&[&"train", &"--config", &cfg, &"--data", &d, &"--out", &run]);
            args.extend(os(extra));
            fails(name, args, want, run)
        };
    // `infer` with random weights, `input` and `--out out/o`.
    let infer = |input: &[&dyn AsRef<OsStr>], o: &str| {
        let mut args = os(&[&"infer", &"--config", &cfg, &"--random-weights"]);
        args.extend(os(input));
        args.extend(os(&[&"--out", &out.join(o)]));
        args
    };
    let summary = |o: &str| out.join(o).join("summary.json");
    let infer_img = |name: &'static str, img: &Path, want: Vec<String>, o: &str| {
        let input = infer(&[&"--image", &img, &"--calib", &calib], o);
        fails(name, input, want, summary(o))
    };
    let infer_data = |name: &'static str, d: &Path, seqs: &str, want: Vec<String>, o: &str| {
        let input = infer(
            &[&"--data", &d, &"--sequences", &seqs, &"--render", &"0"],
            o,
        );
        fails(name, input, want, summary(o))
    };
    let viz_image = |name: &'static str, image: &Path, want: Vec<String>, o: &str| {
        let args = os(&[
            &"viz",
            &"--labels",
            &gt_label,
            &"--image",
            &image,
            &"--calib",
            &calib,
            &"--out",
            &out.join(o),
        ]);
        fails(name, args, want, out.join(o))
    };
    let train_cfg = |name: &'static str, c: PathBuf, want: &[&str], o: &str| {
        let mut want: Vec<String> = want.iter().map(|s| s.to_string()).collect();
        want.push(c.file_name().unwrap().to_string_lossy().into_owned());
        Case {
            name,
            args: os(&[
                &"train",
                &"--config",
                &c,
                &"--data",
                &data,
                &"--out",
                &out.join(o),
            ]),
            status: 1,
            want,
            // Nothing is written into the run folder.
            absent: vec![out.join(o)],
        }
    };
    let eval = |name: &'static str, gt: &Path, seqs: &str, want: &[&str], json: &str| Case {
        name,
        args: os(&[
            &"eval",
            &"--gt",
            &gt,
            &"--pred",
            &pred,
            &"--sequences",
            &seqs,
            &"--json",
            &out.join(json),
        ]),
        status: 1,
        want: want.iter().map(|s| s.to_string()).collect(),
        absent: vec![out.join(json)],
    };
    let s = |x: &str| x.to_string();
    let cases = vec![
        // Configs: harmful numbers, wrong types, unknown keys at every level.
        train_cfg(
            "negative clip_norm",
            bad_cfg(
                "neg_clip.toml",
                "checkpoint_every = 1",
                "checkpoint_every = 1\nclip_norm = -1.0",
            ),
            &["train.clip_norm"],
            "r1",
        ),
        train_cfg(
            "NaN clip_norm",
            bad_cfg(
                "nan_clip.toml",
                "checkpoint_every = 1",
                "checkpoint_every = 1\nclip_norm = nan",
            ),
            &["train.clip_norm"],
            "r2",
        ),
        train_cfg(
            "NaN min_lr_ratio",
            bad_cfg(
                "nan_min.toml",
                "checkpoint_every = 1",
                "checkpoint_every = 1\nmin_lr_ratio = nan",
            ),
            &["train.min_lr_ratio"],
            "r3",
        ),
        train_cfg(
            "infinite lr",
            bad_cfg("inf_lr.toml", "lr = 1e-3", "lr = inf"),
            &["train.lr"],
            "r4",
        ),
        train_cfg(
            "NaN weight_decay",
            bad_cfg("nan_wd.toml", "lr = 1e-3", "lr = 1e-3\nweight_decay = nan"),
            &["train.weight_decay"],
            "r5",
        ),
        train_cfg(
            "lr of the wrong type",
            bad_cfg("fast.toml", "lr = 1e-3", "lr = \"fast\""),
            &["train.lr", "fast"],
            "r6",
        ),
        train_cfg(
            "unknown key in [model.sparseocc_pp]",
            bad_cfg(
                "pp_key.toml",
                "embed_dim = 16",
                "embed_dim = 16\nembed_dims = 16",
            ),
            &["model.sparseocc_pp.embed_dims", "unknown"],
            "r7",
        ),
        train_cfg(
            "unknown key in [model.encoder.resnet]",
            bad_cfg("resnet_key.toml", "depth = 18", "depth = 18\nlayers = 3"),
            &["model.encoder.resnet.layers", "unknown"],
            "r8",
        ),
        train_cfg(
            "a sequence listed twice",
            bad_cfg(
                "twice.toml",
                "train_sequences = [\"00\"]",
                "train_sequences = [\"00\", \"00\"]",
            ),
            &["data.train_sequences", "twice"],
            "r9",
        ),
        train_cfg(
            "not TOML",
            bad_cfg("broken.toml", "[train]", "[train"),
            &[],
            "r10",
        ),
        // Resume without a checkpoint: an error, and the run folder is left as it was.
        Case {
            name: "resume without checkpoint",
            args: os(&[&"train", &"--data", &data, &"--out", &no_ck, &"--resume"]),
            status: 1,
            want: vec![s("no_ck"), s("--resume"), s("no checkpoint")],
            absent: vec![
                no_ck.join("train_log.csv"),
                no_ck.join("checkpoint"),
                no_ck.join("grid.json"),
            ],
        },
        Case {
            name: "resume into a missing run",
            args: os(&[
                &"train",
                &"--config",
                &cfg,
                &"--data",
                &data,
                &"--out",
                &out.join("never"),
                &"--resume",
            ]),
            status: 1,
            want: vec![s("never"), s("no checkpoint")],
            absent: vec![out.join("never")],
        },
        // Images: a header claiming 100000x100000 pixels, in every reader path.
        infer_img(
            "infer --image huge",
            &huge,
            vec![s("huge.png"), s("100000x100000")],
            "i1",
        ),
        infer_img(
            "infer --image contradicting its calibration",
            &small,
            vec![s("small.png"), s("calibration")],
            "i2",
        ),
        infer_data(
            "infer --data with a huge image",
            &data_huge,
            "08",
            vec![s("000000.png"), s("100000x100000")],
            "i3",
        ),
        infer_data(
            "infer --data with an image contradicting the calibration",
            &data_small,
            "08",
            vec![s("000000.png"), s("calib.txt")],
            "i4",
        ),
        infer_data(
            "infer --data with a calibration whose Tr is not a rotation",
            &data_bad_tr,
            "08",
            vec![s("08/calib.txt"), s("must be a rotation")],
            "i10",
        ),
        infer_data(
            "infer --data with a labelled frame without its image",
            &data_noimg,
            "08",
            vec![s("000000.png"), s("no image")],
            "i7",
        ),
        infer_data(
            "infer --data with a missing sequence",
            &data,
            "05",
            vec![s("05")],
            "i5",
        ),
        viz_image(
            "viz --image huge",
            &huge,
            vec![s("huge.png"), s("100000x100000")],
            "v1.png",
        ),
        viz_image(
            "viz --image contradicting its calibration",
            &small,
            vec![s("small.png"), s("calibration")],
            "v2.png",
        ),
        // Every training and validation frame is checked before the first step: nothing is
        // written.
        train_data(
            "train on a dataset with a huge image",
            &data_huge,
            &[&"--sequences", &"08"],
            vec![s("000000.png"), s("100000x100000")],
            "t_huge",
        ),
        train_data(
            "train with a truncated validation label",
            &data_trunc,
            &[&"--sequences", &"00", &"--val-sequences", &"08"],
            vec![s("08/voxels/000000.label"), s("bytes")],
            "t_trunc",
        ),
        train_data(
            "train with a truncated validation image",
            &data_cut_img,
            &[&"--sequences", &"00", &"--val-sequences", &"08"],
            vec![s("08/image_2/000000.png"), s("truncated")],
            "t_cut_img",
        ),
        train_data(
            "train on a labelled frame without its .invalid",
            &data_no_invalid,
            &[&"--sequences", &"00", &"--val-sequences", &""],
            vec![s("00/voxels/000000.invalid"), s("missing")],
            "t_no_invalid",
        ),
        infer_img(
            "infer --image with a JPEG cut in half",
            &cut_jpeg,
            vec![s("cut.jpg"), s("truncated")],
            "i9",
        ),
        infer_data(
            "infer --data with a truncated label",
            &data_trunc,
            "08",
            vec![s("000000.label"), s("bytes")],
            "i8",
        ),
        // Eval: contradicting options and bad ground truth.
        eval(
            "duplicate sequences",
            &data,
            "8,08",
            &["08", "twice"],
            "e1.json",
        ),
        eval(
            "ground-truth ids outside the learning map",
            &gt_unknown,
            "08",
            &["000000.label", "learning map"],
            "e2.json",
        ),
        eval(
            "a ground-truth frame that is a folder",
            &gt_dir,
            "08",
            &["000001.label", "not a file"],
            "e3.json",
        ),
        eval("a missing sequence", &data, "05", &["05"], "e4.json"),
        Case {
            name: "eval of a missing prediction folder",
            args: os(&[
                &"eval",
                &"--gt",
                &data,
                &"--pred",
                &root.join("no_pred"),
                &"--json",
                &out.join("e5.json"),
            ]),
            status: 1,
            want: vec![s("no_pred"), s("missing prediction")],
            absent: vec![out.join("e5.json")],
        },
        Case {
            name: "infer from a run without weights",
            args: os(&[
                &"infer",
                &"--checkpoint",
                &no_ck,
                &"--image",
                &small,
                &"--calib",
                &calib,
                &"--out",
                &out.join("i6"),
            ]),
            status: 1,
            want: vec![s("no_ck")],
            absent: vec![out.join("i6/summary.json")],
        },
        Case {
            name: "bench with a config that is not TOML",
            args: os(&[&"bench", &"--config", &bad_json]),
            status: 1,
            want: vec![s("bad.json")],
            absent: vec![],
        },
        // Options that would make a check or a benchmark vacuous: a usage error (status 2) naming
        // the option, before anything runs.
        usage(
            "check-backend with a NaN tolerance",
            &[&"check-backend", &"--tol", &"nan"],
            vec![s("--tol"), s("finite number above 0")],
            "cb1.json",
        ),
        usage(
            "check-backend counting compiles of no frame after the warm-up",
            &[&"check-backend", &"--frames", &"1"],
            vec![s("--frames"), s("2..")],
            "cb2.json",
        ),
        usage(
            "bench of 0 frames",
            &[&"bench", &"--config", &cfg, &"--frames", &"0"],
            vec![s("--frames"), s("1..")],
            "b1.json",
        ),
        // Good input still works, written to a path with spaces and non-UTF-8 bytes.
        Case {
            name: "eval to an odd path",
            args: {
                use std::os::unix::ffi::OsStrExt;
                let odd = out.join(OsStr::from_bytes(b"odd dir \xff\xfe/r\xe9port 1.json"));
                os(&[
                    &"eval",
                    &"--gt",
                    &data,
                    &"--pred",
                    &pred,
                    &"--sequences",
                    &"08",
                    &"--json",
                    &odd,
                ])
            },
            status: 0,
            want: vec![],
            absent: vec![],
        },
    ];
    for c in &cases {
        check_case(c, &out);
    }
    {
        use std::os::unix::ffi::OsStrExt;
        let odd = out.join(OsStr::from_bytes(b"odd dir \xff\xfe/r\xe9port 1.json"));
        let v: serde_json::Value = serde_json::from_slice(&std::fs::read(&odd).unwrap()).unwrap();
        // Predictions = ground truth: completion IoU 1.
        assert!((v["iou"].as_f64().unwrap() - 1.0).abs() < 1e-9, "{v}");
    }
    // The run folder of the failed resume holds only what it held before.
    let mut left: Vec<String> = std::fs::read_dir(&no_ck)
        .unwrap()
        .map(|e| e.unwrap().file_name().to_string_lossy().into_owned())
        .collect();
    left.sort();
    assert_eq!(left, vec!["config.toml".to_string()]);
    let _ = std::fs::remove_dir_all(&root);
}

/// Many pairs of `eval --json SAME.json` at once: the file is always one complete report, and no
/// run fails on its rename.
#[test]
fn concurrent_writers_of_one_output() {
    let root = tmp("concurrent");
    let data = root.join("data");
    ok(&[
        OsStr::new("synth"),
        OsStr::new("--out"),
        data.as_os_str(),
        OsStr::new("--sequences"),
        OsStr::new("08:1"),
    ]);
    let pred = root.join("pred");
    support::copy_file(
        &data.join("sequences/08/voxels/000000.label"),
        &pred.join("sequences/08/predictions/000000.label"),
    );
    let out = root.join("out");
    std::fs::create_dir_all(&out).unwrap();
    let json = out.join("same.json");
    let pairs = std::env::var("SPARSEOCC_CONCURRENT_PAIRS")
        .ok()
        .and_then(|v| v.parse().ok())
        .unwrap_or(25usize);
    for _ in 0..pairs {
        let children: Vec<_> = (0..2)
            .map(|_| {
                bin()
                    .args([OsStr::new("eval"), OsStr::new("--gt"), data.as_os_str()])
                    .args([OsStr::new("--pred"), pred.as_os_str()])
                    .args([OsStr::new("--json"), json.as_os_str()])
                    .stdout(Stdio::null())
                    .stderr(Stdio::piped())
                    .spawn()
                    .unwrap()
            })
            .collect();
        for c in children {
            let o = c.wait_with_output().unwrap();
            assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
        }
        let v: serde_json::Value = serde_json::from_slice(&std::fs::read(&json).unwrap())
            .expect("complete JSON after a concurrent pair");
        assert_eq!(v["frames"], serde_json::json!(1));
        assert_no_partial_output(&out, "concurrent eval");
    }
    let _ = std::fs::remove_dir_all(&root);
}

/// Rows of `train_log.csv`: (header count, steps in order).
fn log_steps(run: &Path) -> (usize, Vec<usize>) {
    let log = std::fs::read_to_string(run.join("train_log.csv")).unwrap_or_default();
    let headers = log.lines().filter(|l| l.starts_with("step,")).count();
    let steps = log
        .lines()
        .filter_map(|l| l.split(',').next()?.parse().ok())
        .collect();
    (headers, steps)
}

/// A training run killed with SIGKILL at different moments (during steps and checkpoint saves)
/// always resumes from its last complete checkpoint, and its log holds each step once.
#[test]
fn sigkill_during_training_then_resume() {
    let root = tmp("kill");
    let data = root.join("data");
    ok(&[
        OsStr::new("synth"),
        OsStr::new("--out"),
        data.as_os_str(),
        OsStr::new("--sequences"),
        OsStr::new("00:1"),
    ]);
    let cfg = root.join("tiny.toml");
    let steps = 6usize;
    std::fs::write(&cfg, TINY.replace("steps = 2", &format!("steps = {steps}"))).unwrap();
    let run_dir = root.join("run");
    let train_args = |resume: bool| {
        let mut a: Vec<OsString> = os(&[
            &"train",
            &"--config",
            &cfg,
            &"--data",
            &data,
            &"--out",
            &run_dir,
        ]);
        if resume {
            a.push("--resume".into());
        }
        a
    };
    let state_step = || -> Option<usize> {
        let t = std::fs::read_to_string(run_dir.join("checkpoint/state.json")).ok()?;
        let v: serde_json::Value = serde_json::from_str(&t).ok()?;
        v["step"].as_u64().map(|s| s as usize)
    };
    // Each trial: start (resuming once a checkpoint exists), wait until this process has logged a
    // new step, then SIGKILL it after a random 0-500 ms (during the next step or a checkpoint save).
    let mut resumed_kills = 0;
    let mut seed = 0x9E37_79B9_7F4A_7C15u64 ^ std::process::id() as u64;
    for trial in 0..15 {
        let resume = run_dir.join("checkpoint").exists() || run_dir.join("checkpoint.old").exists();
        let base = state_step().unwrap_or(0);
        let mut child = bin()
            .args(train_args(resume))
            .stdout(Stdio::null())
            .stderr(Stdio::null())
            .spawn()
            .unwrap();
        let t0 = std::time::Instant::now();
        let mut finished = None;
        loop {
            if let Some(st) = child.try_wait().unwrap() {
                finished = Some(st);
                break;
            }
            // A resumed run: kill once it has logged a step past its checkpoint. A fresh run: once
            // its first checkpoint exists (the log may still hold a killed fresh run's rows, and a
            // fresh run killed before any checkpoint has nothing to resume, correctly).
            let (_, logged) = log_steps(&run_dir);
            let progressed = if resume {
                logged.last().is_some_and(|&s| s > base)
            } else {
                state_step().is_some()
            };
            if progressed {
                break;
            }
            assert!(
                t0.elapsed().as_secs() < 300,
                "trial {trial}: no step in 300 s"
            );
            std::thread::sleep(std::time::Duration::from_millis(20));
        }
        if finished.is_none() {
            seed ^= seed << 13;
            seed ^= seed >> 7;
            seed ^= seed << 17;
            std::thread::sleep(std::time::Duration::from_millis(seed % 500));
            finished = child.try_wait().unwrap();
        }
        let done = match finished {
            Some(st) => {
                assert!(st.success(), "trial {trial}: training failed");
                true
            }
            None => {
                child.kill().unwrap(); // SIGKILL
                child.wait().unwrap();
                resumed_kills += usize::from(resume);
                false
            }
        };
        // Whatever the moment, the run folder is consistent: no log row repeated or out of order,
        // and the checkpoint (if any) is complete.
        let (headers, logged) = log_steps(&run_dir);
        assert!(headers <= 1, "trial {trial}: {headers} headers");
        assert!(
            logged.windows(2).all(|w| w[1] == w[0] + 1),
            "trial {trial}: log steps {logged:?}"
        );
        if done {
            break;
        }
    }
    // Resume to the end (a no-op if the last trial finished).
    if state_step() != Some(steps) {
        let t = ok(&train_args(true));
        assert!(t.contains("resumed from step"), "{t}");
    }
    assert!(resumed_kills > 0, "no resumed run was killed");
    assert_eq!(state_step(), Some(steps));
    let (headers, logged) = log_steps(&run_dir);
    assert_eq!(headers, 1);
    assert_eq!(logged, (1..=steps).collect::<Vec<_>>());
    assert!(!run_dir.join("checkpoint.old").exists());
    assert_no_partial_output(&run_dir, "after kill and resume");

    // A kill between the two renames of a save leaves only `checkpoint.old`: resume recovers it.
    std::fs::rename(run_dir.join("checkpoint"), run_dir.join("checkpoint.old")).unwrap();
    let t = ok(&train_args(true));
    assert!(t.contains(&format!("resumed from step {steps}")), "{t}");
    assert!(run_dir.join("checkpoint/state.json").exists());
    assert!(!run_dir.join("checkpoint.old").exists());
    let (headers, logged) = log_steps(&run_dir);
    assert_eq!(headers, 1);
    assert_eq!(logged, (1..=steps).collect::<Vec<_>>());

    // A truncated model.bin is an error naming it, without a multi-line burn dump.
    let model = run_dir.join("checkpoint/model.bin");
    let bytes = std::fs::read(&model).unwrap();
    std::fs::write(&model, &bytes[..bytes.len() / 2]).unwrap();
    let o = run(&train_args(true));
    let err = String::from_utf8_lossy(&o.stderr).into_owned();
    assert_eq!(o.status.code(), Some(1), "{err}");
    assert!(
        err.contains("model.bin") && err.contains("truncated"),
        "{err}"
    );
    assert!(
        !err.contains("panicked") && !err.contains("backward-compat"),
        "{err}"
    );
    assert_eq!(
        err.lines().filter(|l| l.starts_with("error:")).count(),
        1,
        "{err}"
    );
    let _ = std::fs::remove_dir_all(&root);
}
