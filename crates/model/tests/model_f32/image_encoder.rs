//! Image encoder (ResNet + FPN) and weight loading against the PyTorch reference in
//! `tests/data/resnet_tiny` (written by `scripts/make_resnet_fixture.py`; cases, files and shapes come
//! from its `manifest.json`).

use std::path::{Path, PathBuf};

use burn::backend::NdArray;
use burn::tensor::backend::Backend;
use burn::tensor::{Tensor, TensorData};
use occ_model::encoder::backbone::{ResNet, ResNetConfig};
use occ_model::encoder::fpn::{FpnConfig, ImageEncoder, ImageEncoderConfig};
use occ_model::encoder::weights::{load_module, load_resnet, LoadOptions, WeightsError};
use occ_testdata::{read_npy, TempDir};
use serde_json::Value;

type B32 = NdArray<f32>;

/// Reference outputs are float64 computations rounded to f32; the model runs in f32.
const TOL: f64 = 1e-4;

fn data_dir() -> PathBuf {
    crate::fixture_dir("resnet_tiny", "make_resnet_fixture.py")
}

fn manifest() -> Value {
    let path = data_dir().join("manifest.json");
    let text = std::fs::read_to_string(&path).unwrap_or_else(|e| panic!("{}: {e}", path.display()));
    serde_json::from_str(&text).unwrap_or_else(|e| panic!("{}: {e}", path.display()))
}

fn usizes(v: &Value) -> Vec<usize> {
    v.as_array()
        .expect("array")
        .iter()
        .map(|x| x.as_u64().expect("integer") as usize)
        .collect()
}

fn str_of<'a>(v: &'a Value, key: &str) -> &'a str {
    v[key]
        .as_str()
        .unwrap_or_else(|| panic!("manifest: {key} missing"))
}

fn input<Be: Backend>(file: &str) -> Tensor<Be, 4> {
    let (v, shape) = read_npy::<f32>(&data_dir().join(file));
    let shape: [usize; 4] = shape.try_into().expect("4-d input");
    // Tensor::from_data keeps the data's dtype: convert to the backend float type.
    let data = TensorData::new(v, shape).convert::<Be::FloatElem>();
    Tensor::from_data(data, &Default::default())
}

/// Max |got - reference| after checking the shape.
fn max_err<Be: Backend>(got: &Tensor<Be, 4>, file: &str) -> f64 {
    let (want, shape) = read_npy::<f32>(&data_dir().join(file));
    assert_eq!(got.dims().to_vec(), shape, "{file}: shape");
    let got: Vec<f64> = got
        .to_data()
        .convert::<f64>()
        .to_vec::<f64>()
        .expect("float data");
    got.iter()
        .zip(&want)
        .map(|(g, w)| (g - f64::from(*w)).abs())
        .fold(0.0, f64::max)
}

fn resnet_for<Be: Backend>(case: &Value) -> ResNet<Be> {
    ResNetConfig::new()
        .with_depth(case["depth"].as_u64().unwrap() as usize)
        .with_base_width(case["base_width"].as_u64().unwrap() as usize)
        .init(&Default::default())
        .expect("valid config")
}

/// Loads `weights` into a fresh backbone and checks every run's four stages.
fn check_case<Be: occ_model::ModelBackend>(case: &Value, weights: &str) -> f64 {
    let mut net = resnet_for::<Be>(case);
    let path = data_dir().join(weights);
    let report =
        load_resnet(&mut net, &path, &LoadOptions::default()).unwrap_or_else(|e| panic!("{e}"));
    // Only the classifier and the BN batch counters are left over.
    assert!(
        report.unused.iter().any(|k| k == "fc.weight"),
        "{:?}",
        report.unused
    );
    for k in &report.unused {
        assert!(
            k.starts_with("fc.") || k.ends_with(".num_batches_tracked"),
            "{weights}: unexpected unused key {k}"
        );
    }
    let mut worst = 0.0f64;
    for run in case["runs"].as_array().unwrap() {
        let outs = net.forward(input::<Be>(str_of(run, "input")));
        assert_eq!(net.strides(), usizes(&run["strides"]));
        let stages = run["stages"].as_array().unwrap();
        assert_eq!(outs.len(), stages.len());
        for (out, stage) in outs.iter().zip(stages) {
            assert_eq!(out.dims().to_vec(), usizes(&stage["shape"]));
            let err = max_err(out, str_of(stage, "file"));
            assert!(
                err <= TOL,
                "{weights} {}: max error {err}",
                str_of(stage, "file")
            );
            worst = worst.max(err);
        }
    }
    worst
}

#[test]
fn torchvision_layout_checkpoints_reproduce_pytorch_stage_outputs() {
    let m = manifest();
    let mut checked = 0;
    for case in m["cases"].as_array().unwrap() {
        for w in case["weights"].as_array().unwrap() {
            let err = check_case::<B32>(case, w.as_str().unwrap());
            eprintln!("{}: max |err| {err:.2e}", w.as_str().unwrap());
            checked += 1;
        }
    }
    assert!(checked >= 3, "manifest lists too few checkpoints");
}

#[test]
fn image_encoder_matches_pytorch_fpn_at_odd_size() {
    let m = manifest();
    let case = m["cases"]
        .as_array()
        .unwrap()
        .iter()
        .find(|c| c.get("fpn").is_some())
        .expect("a case with an FPN reference");
    let fpn = &case["fpn"];
    let run = &case["runs"][fpn["run"].as_u64().unwrap() as usize];
    let cfg = ImageEncoderConfig::new(
        ResNetConfig::new()
            .with_depth(case["depth"].as_u64().unwrap() as usize)
            .with_base_width(case["base_width"].as_u64().unwrap() as usize),
        FpnConfig::new().with_out_channels(fpn["out_channels"].as_u64().unwrap() as usize),
    );
    let mut enc: ImageEncoder<B32> = cfg.init(&Default::default()).unwrap();
    let dir = data_dir();
    let backbone = dir.join(case["weights"][0].as_str().unwrap());
    load_resnet(&mut enc.backbone, &backbone, &LoadOptions::default()).unwrap();
    let report = load_module(
        &mut enc.neck,
        &dir.join(str_of(fpn, "weights")),
        &LoadOptions::default(),
    )
    .unwrap_or_else(|e| panic!("{e}"));
    assert!(report.unused.is_empty(), "{:?}", report.unused);
    let outs = enc.forward(input::<B32>(str_of(run, "input")));
    assert_eq!(enc.strides(), vec![4, 8, 16, 32]);
    let refs = fpn["outputs"].as_array().unwrap();
    assert_eq!(outs.len(), refs.len());
    for (out, r) in outs.iter().zip(refs) {
        let err = max_err(out, str_of(r, "file"));
        assert!(err <= TOL, "{}: max error {err}", str_of(r, "file"));
    }

    // The same neck weights nested in a training checkpoint {"meta": {...}, "state_dict": {...}}:
    // selected by top_level_key, or equivalently by the flattened key prefix.
    let ckpt = dir.join(str_of(fpn, "checkpoint"));
    let top = str_of(fpn, "checkpoint_top_level_key");
    for opts in [
        LoadOptions {
            top_level_key: Some(top.to_string()),
            ..Default::default()
        },
        LoadOptions {
            key_prefix: Some(format!("{top}.")),
            ..Default::default()
        },
    ] {
        let mut enc2: ImageEncoder<B32> = cfg.init(&Default::default()).unwrap();
        load_resnet(&mut enc2.backbone, &backbone, &LoadOptions::default()).unwrap();
        load_module(&mut enc2.neck, &ckpt, &opts).unwrap_or_else(|e| panic!("{opts:?}: {e}"));
        let outs2 = enc2.forward(input::<B32>(str_of(run, "input")));
        for (out, r) in outs2.iter().zip(refs) {
            assert!(max_err(out, str_of(r, "file")) <= TOL, "{opts:?}");
        }
    }
    let bad = LoadOptions {
        top_level_key: Some("no_such_key".into()),
        ..Default::default()
    };
    let err = load_module(&mut enc.neck, &ckpt, &bad).unwrap_err();
    assert!(matches!(err, WeightsError::Options { .. }), "{err}");
    // Without selecting the nested dict nothing matches.
    let err = load_module(&mut enc.neck, &ckpt, &LoadOptions::default()).unwrap_err();
    assert!(matches!(err, WeightsError::MissingKeys { .. }), "{err}");
}

// ---- corrupted copies -------------------------------------------------------------------------

struct StEntry {
    name: String,
    dtype: String,
    shape: Vec<usize>,
    data: Vec<u8>,
}

fn read_safetensors(path: &Path) -> Vec<StEntry> {
    let bytes = std::fs::read(path).unwrap();
    let n = u64::from_le_bytes(bytes[..8].try_into().unwrap()) as usize;
    let header: serde_json::Map<String, Value> = serde_json::from_slice(&bytes[8..8 + n]).unwrap();
    let body = &bytes[8 + n..];
    let mut entries: Vec<(usize, StEntry)> = header
        .into_iter()
        .filter(|(k, _)| k != "__metadata__")
        .map(|(name, v)| {
            let off = usizes(&v["data_offsets"]);
            let e = StEntry {
                name,
                dtype: v["dtype"].as_str().unwrap().to_string(),
                shape: usizes(&v["shape"]),
                data: body[off[0]..off[1]].to_vec(),
            };
            (off[0], e)
        })
        .collect();
    entries.sort_by_key(|(o, _)| *o);
    entries.into_iter().map(|(_, e)| e).collect()
}

fn write_safetensors(path: &Path, entries: &[StEntry]) {
    let mut header = serde_json::Map::new();
    let mut off = 0;
    for e in entries {
        let end = off + e.data.len();
        header.insert(
            e.name.clone(),
            serde_json::json!({"dtype": e.dtype, "shape": e.shape, "data_offsets": [off, end]}),
        );
        off = end;
    }
    let mut h = serde_json::to_vec(&Value::Object(header)).unwrap();
    while !h.len().is_multiple_of(8) {
        h.push(b' ');
    }
    let mut out = (h.len() as u64).to_le_bytes().to_vec();
    out.extend_from_slice(&h);
    for e in entries {
        out.extend_from_slice(&e.data);
    }
    std::fs::write(path, out).unwrap();
}

fn fixture_file(ext: &str) -> (Value, PathBuf) {
    let m = manifest();
    for case in m["cases"].as_array().unwrap() {
        for w in case["weights"].as_array().unwrap() {
            let w = w.as_str().unwrap();
            if w.ends_with(ext) {
                return (case.clone(), data_dir().join(w));
            }
        }
    }
    panic!("manifest has no {ext} checkpoint");
}

fn load_err(case: &Value, path: &Path) -> WeightsError {
    let mut net = resnet_for::<B32>(case);
    match load_resnet(&mut net, path, &LoadOptions::default()) {
        Ok(r) => panic!(
            "{} loaded ({} tensors) but should fail",
            path.display(),
            r.applied
        ),
        Err(e) => e,
    }
}

#[test]
fn safetensors_missing_key_and_wrong_shape_are_clear_errors() {
    let (case, src) = fixture_file(".safetensors");
    let tmp = TempDir::new("occ-model-weights", "st");
    let entries = read_safetensors(&src);

    // Missing running variance and missing BN weight (reported under the PyTorch name).
    for (drop_key, model_name) in [
        ("layer2.0.bn1.running_var", None),
        ("layer1.1.bn2.weight", Some("layer1.1.bn2.gamma")),
    ] {
        let kept: Vec<StEntry> = read_safetensors(&src)
            .into_iter()
            .filter(|e| e.name != drop_key)
            .collect();
        assert_eq!(
            kept.len() + 1,
            entries.len(),
            "{drop_key} not in the fixture"
        );
        let path = tmp.0.join("missing.safetensors");
        write_safetensors(&path, &kept);
        let err = load_err(&case, &path);
        let msg = err.to_string();
        match &err {
            WeightsError::MissingKeys { path: p, keys, .. } => {
                assert_eq!(p, &path);
                assert_eq!(keys.len(), 1, "{keys:?}");
                assert!(keys[0].starts_with(drop_key), "{keys:?}");
                if let Some(m) = model_name {
                    assert!(keys[0].contains(m), "{keys:?}");
                }
            }
            other => panic!("expected MissingKeys, got {other}"),
        }
        assert!(
            msg.contains(&path.display().to_string()) && msg.contains(drop_key),
            "{msg}"
        );
        eprintln!("{msg}");
    }

    // Same number of elements, transposed shape: [C_out, C_in, 3, 3] → [C_in, C_out, 3, 3].
    let key = "layer3.0.conv1.weight";
    let mut bad = read_safetensors(&src);
    let e = bad
        .iter_mut()
        .find(|e| e.name == key)
        .expect("key in fixture");
    let original = e.shape.clone();
    e.shape.swap(0, 1);
    assert_ne!(e.shape, original);
    let found = e.shape.clone();
    let path = tmp.0.join("shape.safetensors");
    write_safetensors(&path, &bad);
    let err = load_err(&case, &path);
    let msg = err.to_string();
    match err {
        WeightsError::ShapeMismatch {
            path: p,
            key: k,
            expected,
            found: f,
        } => {
            assert_eq!(p, path);
            assert_eq!(k, key);
            assert_eq!(expected, original);
            assert_eq!(f, found);
        }
        other => panic!("expected ShapeMismatch, got {other}"),
    }
    assert!(
        msg.contains(&path.display().to_string()) && msg.contains(key),
        "{msg}"
    );
    eprintln!("{msg}");

    // Intact copy through the same writer loads (the corruption, not the writer, caused the errors).
    let path = tmp.0.join("intact.safetensors");
    write_safetensors(&path, &entries);
    let mut net = resnet_for::<B32>(&case);
    load_resnet(&mut net, &path, &LoadOptions::default()).unwrap();
}

#[test]
fn f64_checkpoint_is_converted_to_the_model_dtype() {
    // Without the conversion the f64 weights would meet the f32 input in conv2d and panic.
    let (case, src) = fixture_file(".safetensors");
    let tmp = TempDir::new("occ-model-weights", "f64");
    let entries: Vec<StEntry> = read_safetensors(&src)
        .into_iter()
        .map(|mut e| {
            if e.dtype == "F32" {
                e.data = e
                    .data
                    .chunks_exact(4)
                    .flat_map(|c| {
                        f64::from(f32::from_le_bytes([c[0], c[1], c[2], c[3]])).to_le_bytes()
                    })
                    .collect();
                e.dtype = "F64".into();
            }
            e
        })
        .collect();
    let path = tmp.0.join("f64.safetensors");
    write_safetensors(&path, &entries);
    let mut net = resnet_for::<B32>(&case);
    load_resnet(&mut net, &path, &LoadOptions::default()).unwrap_or_else(|e| panic!("{e}"));
    let run = &case["runs"][0];
    let outs = net.forward(input::<B32>(str_of(run, "input")));
    for (out, stage) in outs.iter().zip(run["stages"].as_array().unwrap()) {
        assert!(max_err(out, str_of(stage, "file")) <= TOL);
    }
}

/// Rewrites a torch zip checkpoint, replacing equal-length key strings inside `data.pkl` (all pairs
/// at once, each must occur exactly once), so the pickle stays valid.
fn rewrite_pth(src: &Path, dst: &Path, pairs: &[(&str, &str)]) {
    use std::io::{Read, Write};
    let mut archive = zip::ZipArchive::new(std::fs::File::open(src).unwrap()).unwrap();
    let mut writer = zip::ZipWriter::new(std::fs::File::create(dst).unwrap());
    let opts =
        zip::write::SimpleFileOptions::default().compression_method(zip::CompressionMethod::Stored);
    for i in 0..archive.len() {
        let mut f = archive.by_index(i).unwrap();
        let name = f.name().to_string();
        let mut bytes = Vec::new();
        f.read_to_end(&mut bytes).unwrap();
        if name.ends_with("data.pkl") {
            let original = bytes.clone();
            for (from, to) in pairs {
                assert_eq!(from.len(), to.len());
                let hits: Vec<usize> = original
                    .windows(from.len())
                    .enumerate()
                    .filter(|(_, w)| *w == from.as_bytes())
                    .map(|(i, _)| i)
                    .collect();
                assert_eq!(hits.len(), 1, "{from} in data.pkl");
                bytes[hits[0]..hits[0] + to.len()].copy_from_slice(to.as_bytes());
            }
        }
        writer.start_file(name, opts).unwrap();
        writer.write_all(&bytes).unwrap();
    }
    writer.finish().unwrap();
}

#[test]
fn pth_missing_key_and_wrong_shape_are_clear_errors() {
    let (case, src) = fixture_file(".pth");
    let tmp = TempDir::new("occ-model-weights", "pth");

    let renamed = tmp.0.join("missing.pth");
    let key = "layer4.1.bn2.running_mean";
    rewrite_pth(&src, &renamed, &[(key, "layer4.1.bn2.running_meXn")]);
    let err = load_err(&case, &renamed);
    let msg = err.to_string();
    match &err {
        WeightsError::MissingKeys { keys, unused, .. } => {
            assert_eq!(keys, &vec![key.to_string()]);
            assert!(
                unused.iter().any(|k| k == "layer4.1.bn2.running_meXn"),
                "{unused:?}"
            );
        }
        other => panic!("expected MissingKeys, got {other}"),
    }
    assert!(
        msg.contains(&renamed.display().to_string()) && msg.contains(key),
        "{msg}"
    );

    // Swap the names of two tensors of different shapes.
    let (a, b) = ("layer1.0.conv1.weight", "layer2.0.conv1.weight");
    let swapped = tmp.0.join("swapped.pth");
    rewrite_pth(&src, &swapped, &[(a, b), (b, a)]);
    let err = load_err(&case, &swapped);
    match &err {
        WeightsError::ShapeMismatch {
            path,
            key,
            expected,
            found,
        } => {
            assert_eq!(path, &swapped);
            assert!(key == a || key == b, "{key}");
            assert_ne!(expected, found);
        }
        other => panic!("expected ShapeMismatch, got {other}"),
    }

    // The unmodified rewrite loads.
    let same = tmp.0.join("same.pth");
    rewrite_pth(&src, &same, &[]);
    let mut net = resnet_for::<B32>(&case);
    load_resnet(&mut net, &same, &LoadOptions::default()).unwrap();
}

#[test]
fn key_prefix_selects_a_submodule_of_a_larger_checkpoint() {
    let (case, src) = fixture_file(".safetensors");
    let tmp = TempDir::new("occ-model-weights", "prefix");
    let mut entries: Vec<StEntry> = read_safetensors(&src)
        .into_iter()
        .map(|mut e| {
            e.name = format!("img_backbone.{}", e.name);
            e
        })
        .collect();
    // Keys outside the prefix, one of them with a model path name and a wrong shape: must be ignored.
    entries.push(StEntry {
        name: "conv1.weight".into(),
        dtype: "F32".into(),
        shape: vec![1],
        data: vec![0; 4],
    });
    entries.push(StEntry {
        name: "img_neck.lateral_convs.0.conv.weight".into(),
        dtype: "F32".into(),
        shape: vec![1],
        data: vec![0; 4],
    });
    let path = tmp.0.join("detector.safetensors");
    write_safetensors(&path, &entries);

    let opts = LoadOptions {
        key_prefix: Some("img_backbone.".into()),
        ..Default::default()
    };
    let mut net = resnet_for::<B32>(&case);
    let report = load_resnet(&mut net, &path, &opts).unwrap_or_else(|e| panic!("{e}"));
    assert!(report.unused.iter().any(|k| k == "conv1.weight"));
    assert!(report
        .unused
        .iter()
        .any(|k| k == "img_neck.lateral_convs.0.conv.weight"));
    assert!(report.unused.iter().any(|k| k == "img_backbone.fc.weight"));
    let run = &case["runs"][0];
    let outs = net.forward(input::<B32>(str_of(run, "input")));
    let stage = &run["stages"][3];
    assert!(max_err(&outs[3], str_of(stage, "file")) <= TOL);

    // Without the prefix nothing matches: a clear missing-keys error with a hint.
    let mut net = resnet_for::<B32>(&case);
    let err = load_resnet(&mut net, &path, &LoadOptions::default()).unwrap_err();
    assert!(matches!(
        err,
        WeightsError::ShapeMismatch { .. } | WeightsError::MissingKeys { .. }
    ));

    // A wrong prefix is reported as missing keys, with the file's keys as a hint.
    let opts = LoadOptions {
        key_prefix: Some("backbone.".into()),
        ..Default::default()
    };
    let mut net = resnet_for::<B32>(&case);
    match load_resnet(&mut net, &path, &opts).unwrap_err() {
        WeightsError::MissingKeys { keys, unused, .. } => {
            assert!(
                keys.iter().any(|k| k == "backbone.conv1.weight"),
                "{keys:?}"
            );
            assert!(!unused.is_empty());
        }
        other => panic!("expected MissingKeys, got {other}"),
    }
}

#[test]
fn unreadable_files_are_errors_not_panics() {
    let (case, _) = fixture_file(".safetensors");
    let tmp = TempDir::new("occ-model-weights", "bad");
    let mut net = resnet_for::<B32>(&case);
    let missing = tmp.0.join("does_not_exist.pth");
    assert!(matches!(
        load_resnet(&mut net, &missing, &LoadOptions::default()),
        Err(WeightsError::Io { .. })
    ));
    let garbage = tmp.0.join("garbage.pth");
    std::fs::write(&garbage, b"this is not a checkpoint at all").unwrap();
    let err = load_resnet(&mut net, &garbage, &LoadOptions::default()).unwrap_err();
    assert!(matches!(err, WeightsError::Parse { .. }), "{err}");
    assert!(err.to_string().contains(&garbage.display().to_string()));
    let (_, st) = fixture_file(".safetensors");
    let opts = LoadOptions {
        top_level_key: Some("state_dict".into()),
        ..Default::default()
    };
    assert!(matches!(
        load_resnet(&mut net, &st, &opts),
        Err(WeightsError::Options { .. })
    ));
}

/// Timing of a full-width ResNet-18 (base 64) + FPN 256 on one KITTI-sized image; run by hand:
/// `cargo test --release -p occ-model --test image_encoder -- --ignored --nocapture`.
#[test]
#[ignore]
fn resnet18_base64_forward_time_370x1226() {
    let cfg = ImageEncoderConfig::new(ResNetConfig::new(), FpnConfig::new());
    let enc: ImageEncoder<B32> = cfg.init(&Default::default()).unwrap();
    let x = Tensor::<B32, 4>::ones([1, 3, 370, 1226], &Default::default());
    let t0 = std::time::Instant::now();
    let feats = enc.backbone.forward(x.clone());
    let dims: Vec<[usize; 4]> = feats.iter().map(|t| t.dims()).collect();
    let _ = feats[3].to_data();
    let backbone_s = t0.elapsed().as_secs_f64();
    let t1 = std::time::Instant::now();
    let outs = enc.forward(x);
    for t in &outs {
        let _ = t.to_data();
    }
    let encoder_s = t1.elapsed().as_secs_f64();
    eprintln!("ResNet-18 base 64, [1,3,370,1226]: backbone {backbone_s:.2} s, backbone+FPN(256) {encoder_s:.2} s; stages {dims:?}");
}
