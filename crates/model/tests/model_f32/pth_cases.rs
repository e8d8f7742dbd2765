//! The forms of `torch.save` files the `.pth` reader must decode (`tests/data/pth_cases`, written by
//! `scripts/make_pth_cases_fixture.py`; loads, options and expected values come from its `manifest.json`):
//! half / bfloat16 / float64 storages, strided and offset views of one shared storage (a channels_last
//! conv weight among them), pickle protocol 4, a training checkpoint with Python objects that are not
//! tensors, and the legacy non-zip format, which is rejected.

use std::collections::BTreeMap;
use std::path::PathBuf;

use burn::backend::NdArray;
use burn::module::{Module, Param};
use burn::nn::conv::{Conv2d, Conv2dConfig};
use burn::store::ModuleSnapshot;
use burn::tensor::backend::Backend;
use burn::tensor::Tensor;
use occ_model::encoder::weights::{load_module, LoadOptions, LoadReport, WeightsError};
use serde_json::Value;

type B32 = NdArray<f32>;

fn data_dir() -> PathBuf {
    crate::fixture_dir("pth_cases", "make_pth_cases_fixture.py")
}

/// `a`, `b`, `c`, `d`: four `[2, 3]` tensors.
#[derive(Module, Debug)]
struct Four<B: Backend> {
    a: Param<Tensor<B, 2>>,
    b: Param<Tensor<B, 2>>,
    c: Param<Tensor<B, 2>>,
    d: Param<Tensor<B, 2>>,
}

/// The views of `views.pth`.
#[derive(Module, Debug)]
struct Views<B: Backend> {
    conv: Conv2d<B>,
    transposed: Param<Tensor<B, 2>>,
    strided: Param<Tensor<B, 2>>,
    offset: Param<Tensor<B, 2>>,
}

fn zeros<const D: usize>(shape: [usize; D]) -> Param<Tensor<B32, D>> {
    Param::from_tensor(Tensor::zeros(shape, &Default::default()))
}

/// Loads `load` (a manifest entry) into `module`; on success checks every module tensor against the
/// manifest's values (the module must have exactly the listed tensors) and the unused keys.
fn check<M: Module<B32>>(mut module: M, load: &Value) -> Result<LoadReport, WeightsError> {
    let path = data_dir().join(load["file"].as_str().expect("file"));
    let opt = |k: &str| load.get(k).and_then(Value::as_str).map(str::to_string);
    let opts = LoadOptions {
        top_level_key: opt("top_level_key"),
        key_prefix: opt("key_prefix"),
    };
    let report = load_module(&mut module, &path, &opts)?;
    let want = load["tensors"].as_object().expect("tensors");
    let got: BTreeMap<String, (Vec<usize>, Vec<f32>)> = module
        .collect(None, None, false)
        .into_iter()
        .map(|s| {
            let data = s.to_data().expect("module tensor");
            (
                s.full_path(),
                (data.shape.to_vec(), data.to_vec::<f32>().expect("f32 data")),
            )
        })
        .collect();
    assert_eq!(
        got.keys().collect::<Vec<_>>(),
        want.keys().collect::<Vec<_>>(),
        "{load}: module tensors vs manifest"
    );
    for (key, w) in want {
        let shape: Vec<usize> = serde_json::from_value(w["shape"].clone()).unwrap();
        let values: Vec<f32> = serde_json::from_value(w["values"].clone()).unwrap();
        assert_eq!(got[key].0, shape, "{} {key}: shape", path.display());
        assert_eq!(got[key].1, values, "{} {key}: values", path.display());
    }
    let unused: Vec<String> = serde_json::from_value(load["unused"].clone()).unwrap();
    assert_eq!(report.unused, unused, "{}: unused keys", path.display());
    Ok(report)
}

#[test]
fn pth_dtypes_views_protocols_and_checkpoints_load_exactly() {
    let text = std::fs::read_to_string(data_dir().join("manifest.json")).unwrap();
    let manifest: Value = serde_json::from_str(&text).unwrap();
    let loads = manifest["loads"].as_array().unwrap();
    let mut loaded = 0;
    for load in loads {
        let result = match load["module"].as_str().unwrap() {
            "four" => check(
                Four {
                    a: zeros([2, 3]),
                    b: zeros([2, 3]),
                    c: zeros([2, 3]),
                    d: zeros([2, 3]),
                },
                load,
            ),
            "views" => check(
                Views {
                    conv: Conv2dConfig::new([3, 2], [2, 2]).init(&Default::default()),
                    transposed: zeros([4, 3]),
                    strided: zeros([2, 3]),
                    offset: zeros([2, 3]),
                },
                load,
            ),
            other => panic!("manifest: unknown module {other}"),
        };
        match (load.get("error").and_then(Value::as_str), result) {
            (None, Ok(report)) => {
                assert_eq!(report.applied, load["tensors"].as_object().unwrap().len());
                loaded += 1;
            }
            (None, Err(e)) => panic!("{e}"),
            (Some("Parse"), Err(e @ WeightsError::Parse { .. })) => {
                let file = load["file"].as_str().unwrap();
                assert!(e.to_string().contains(file), "{e}");
                eprintln!("{e}");
            }
            (Some(want), result) => panic!("{load}: expected a {want} error, got {result:?}"),
        }
    }
    assert!(loaded >= 5, "manifest lists too few loads");
}
