//! `sparseocc._native`: the Python extension module. A thin layer over the library crates: each
//! function converts its arguments, releases the GIL, calls the library function the CLI calls, and
//! converts the result; errors become `SparseOccError` (the library's message, naming the file and
//! the problem) or `ValueError` (an argument). The public Python API is `python/sparseocc/`.

use burn::backend::NdArray;
use indicatif::{ProgressBar, ProgressDrawTarget, ProgressStyle};
use numpy::{
    IntoPyArray, PyArray2, PyArrayMethods, PyReadonlyArray2, PyReadonlyArrayDyn,
    PyUntypedArrayMethods,
};
use occ_data::formats::occ3d::Occ3dLabels;
use occ_data::formats::semantic_kitti::Calib;
use occ_data::formats::voxels::{self, VoxelFile};
use occ_data::labels::LearningMap;
use occ_data::synthetic::{self, Preset, SynthConfig};
use occ_eval::{ConfusionMatrix, EvalMask, Evaluator, FolderOptions, Protocol};
use occ_geometry::VoxelGrid;
use occ_labels::IGNORE;
use occ_model::OccNet;
use occ_sparse::arrays::{conv3d_arrays, ArrayConvKind, ArrayConvSpec};
use occ_train::RunConfig;
use pyo3::create_exception;
use pyo3::exceptions::{PyException, PyValueError};
use pyo3::prelude::*;
use pyo3::types::{PyDict, PyTuple};
use std::path::PathBuf;
use std::sync::Mutex;

/// The inference backend (the CLI's default build): burn's NdArray on the CPU, f32.
type Cpu = NdArray<f32>;

create_exception!(
    sparseocc,
    SparseOccError,
    PyException,
    "An error of the sparseocc library: a bad file, a bad dataset folder or run, with the file and the problem in the message."
);

/// A library error as `SparseOccError` with its message (and its causes).
fn lib_err(e: impl std::fmt::Display) -> PyErr {
    SparseOccError::new_err(e.to_string())
}

fn value_err(msg: impl Into<String>) -> PyErr {
    PyValueError::new_err(msg.into())
}

/// A progress bar on stderr, like the CLI's (hidden when `show` is false or under CI).
fn bar(total: u64, msg: &str, show: bool) -> ProgressBar {
    let pb = ProgressBar::new(total);
    if !show || std::env::var_os("CI").is_some() {
        pb.set_draw_target(ProgressDrawTarget::hidden());
    }
    pb.set_style(
        ProgressStyle::with_template("{msg:>12} [{bar:30}] {pos}/{len} {per_sec} eta {eta}")
            .unwrap_or_else(|_| ProgressStyle::default_bar())
            .progress_chars("=> "),
    );
    pb.set_message(msg.to_string());
    pb
}

/// `value` (a serde value) as a Python object through `json.loads`, so that keys, order, `None`
/// for undefined metrics and every float are exactly what the CLI's `--json` files hold.
fn to_py<'py, T: serde::Serialize>(py: Python<'py>, value: &T) -> PyResult<Bound<'py, PyAny>> {
    let text = serde_json::to_string(value).map_err(lib_err)?;
    py.import("json")?.call_method1("loads", (text,))
}

fn protocol(dataset: &str) -> PyResult<Protocol> {
    dataset.parse::<Protocol>().map_err(value_err)
}

/// Values of an array in C order (whatever its memory layout), borrowed where the array is
/// C-contiguous (no copy), else copied in logical order.
///
/// The borrow outlives a released GIL in [`conv3d`]: like numpy's own functions that release the
/// GIL, the call reads the array while it runs, so another Python thread must not write it then.
fn c_order_cow<'a, T: numpy::Element + Copy>(
    a: &'a PyReadonlyArrayDyn<'_, T>,
) -> std::borrow::Cow<'a, [T]> {
    // `as_slice` also succeeds on Fortran-order arrays (it only asks for contiguity), whose memory
    // is not in C order: only a C-contiguous array is borrowed as it lies.
    if a.is_c_contiguous() {
        if let Ok(s) = a.as_slice() {
            return std::borrow::Cow::Borrowed(s);
        }
    }
    std::borrow::Cow::Owned(a.as_array().iter().copied().collect())
}

/// Values of an array in C order (whatever its memory layout), always a copy.
fn c_order<T: numpy::Element + Copy>(a: &PyReadonlyArrayDyn<'_, T>) -> Vec<T> {
    c_order_cow(a).into_owned()
}

/// A class array (any integer dtype, passed as int64) as bytes: values outside 0..=255 become
/// 255, which no protocol has as a class (an invalid prediction, an ignored ground-truth voxel).
fn class_bytes(a: &PyReadonlyArrayDyn<'_, i64>) -> Vec<u8> {
    a.as_array()
        .iter()
        .map(|&v| u8::try_from(v).unwrap_or(IGNORE))
        .collect()
}

#[pyfunction]
#[pyo3(signature = (gt_root, pred_root, dataset = "semantickitti", sequences = None, progress = true))]
fn evaluate<'py>(
    py: Python<'py>,
    gt_root: PathBuf,
    pred_root: PathBuf,
    dataset: &str,
    sequences: Option<Vec<String>>,
    progress: bool,
) -> PyResult<Bound<'py, PyAny>> {
    let protocol = protocol(dataset)?;
    let report = py
        .detach(|| {
            let pb = bar(0, "eval", progress);
            let tick = || pb.inc(1);
            let opts = FolderOptions {
                sequences: sequences.as_deref(),
                on_frame: Some(&tick),
                ..Default::default()
            };
            let r = occ_eval::score_folder(protocol, &gt_root, &pred_root, &opts);
            pb.finish_and_clear();
            r
        })
        .map_err(|e| {
            lib_err(format!(
                "scoring {} against {}: {e}",
                pred_root.display(),
                gt_root.display()
            ))
        })?;
    to_py(py, &report)
}

#[pyfunction]
#[pyo3(signature = (pred, gt, invalid = None, visible = None, dataset = "semantickitti"))]
fn confusion<'py>(
    py: Python<'py>,
    pred: PyReadonlyArrayDyn<'py, i64>,
    gt: PyReadonlyArrayDyn<'py, i64>,
    invalid: Option<PyReadonlyArrayDyn<'py, i64>>,
    visible: Option<PyReadonlyArrayDyn<'py, i64>>,
    dataset: &str,
) -> PyResult<Bound<'py, PyArray2<u64>>> {
    let protocol = protocol(dataset)?;
    if pred.shape() != gt.shape() {
        return Err(value_err(format!(
            "pred has shape {:?} but gt {:?}",
            pred.shape(),
            gt.shape()
        )));
    }
    let mask = match (&invalid, &visible) {
        (Some(_), Some(_)) => return Err(value_err("give invalid or visible, not both")),
        (Some(m), None) | (None, Some(m)) => {
            if m.shape() != gt.shape() {
                return Err(value_err(format!(
                    "{} has shape {:?} but gt {:?}",
                    if invalid.is_some() {
                        "invalid"
                    } else {
                        "visible"
                    },
                    m.shape(),
                    gt.shape()
                )));
            }
            Some(class_bytes(m))
        }
        (None, None) => None,
    };
    let (p, g) = (class_bytes(&pred), class_bytes(&gt));
    let is_invalid = invalid.is_some();
    let conf = py
        .detach(|| {
            let mut ev = Evaluator::new(protocol);
            let m = match (&mask, is_invalid) {
                (None, _) => EvalMask::All,
                (Some(m), true) => EvalMask::Invalid(m),
                (Some(m), false) => EvalMask::Visible(m),
            };
            ev.add_frame(&p, &g, m, "arrays")?;
            Ok::<_, occ_eval::EvalError>(ev.confusion().to_rows())
        })
        .map_err(lib_err)?;
    let n = conf.len();
    let flat: Vec<u64> = conf.into_iter().flatten().collect();
    flat.into_pyarray(py).reshape([n, n])
}

#[pyfunction]
#[pyo3(signature = (confusion, dataset = "semantickitti", frames = 1))]
fn report<'py>(
    py: Python<'py>,
    confusion: PyReadonlyArray2<'py, u64>,
    dataset: &str,
    frames: u64,
) -> PyResult<Bound<'py, PyAny>> {
    let protocol = protocol(dataset)?;
    let rows: Vec<Vec<u64>> = confusion
        .as_array()
        .rows()
        .into_iter()
        .map(|r| r.to_vec())
        .collect();
    let conf = ConfusionMatrix::from_rows(&rows)
        .ok_or_else(|| value_err("confusion must be a square matrix"))?;
    let ev =
        Evaluator::from_confusion(protocol, conf, frames).map_err(|e| value_err(e.to_string()))?;
    to_py(py, &ev.report())
}

#[pyfunction]
fn class_names(dataset: &str) -> PyResult<Vec<&'static str>> {
    Ok(protocol(dataset)?.class_names().to_vec())
}

#[pyfunction]
#[pyo3(signature = (out, preset = "kitti-small", sequences = "00:20,08:5", seed = 0, image_size = None, progress = true))]
fn synth<'py>(
    py: Python<'py>,
    out: PathBuf,
    preset: &str,
    sequences: &str,
    seed: u64,
    image_size: Option<(usize, usize)>,
    progress: bool,
) -> PyResult<Bound<'py, PyAny>> {
    let preset: Preset = preset
        .parse()
        .map_err(|e: occ_data::DataError| value_err(e.to_string()))?;
    let mut cfg = SynthConfig::new(
        preset,
        seed,
        synthetic::parse_sequences(sequences).map_err(|e| value_err(e.to_string()))?,
    );
    cfg.image_size = image_size;
    let summary = py
        .detach(|| {
            let pb = bar(1, "synth", progress);
            let r = synthetic::generate(&out, &cfg, &mut |done, total| {
                pb.set_length(total as u64);
                pb.set_position(done as u64);
            });
            pb.finish_and_clear();
            let s = r?;
            synthetic::write_summary(&out, &s)?;
            Ok::<_, occ_data::DataError>(s)
        })
        .map_err(|e| lib_err(format!("generating into {}: {e}", out.display())))?;
    to_py(py, &summary)
}

#[pyfunction]
#[pyo3(signature = (path, learning = false))]
fn read_voxels<'py>(py: Python<'py>, path: PathBuf, learning: bool) -> PyResult<Bound<'py, PyAny>> {
    let file = py.detach(|| voxels::read_voxels(&path)).map_err(lib_err)?;
    Ok(match file {
        VoxelFile::KittiLabel { raw, grid } => {
            if learning {
                let c = LearningMap::semantic_kitti().remap(&raw);
                c.into_pyarray(py).reshape(grid.dims)?.into_any()
            } else {
                raw.into_pyarray(py).reshape(grid.dims)?.into_any()
            }
        }
        VoxelFile::KittiBits { bits, grid } => {
            let b: Vec<bool> = bits.into_iter().map(|v| v != 0).collect();
            b.into_pyarray(py).reshape(grid.dims)?.into_any()
        }
        VoxelFile::Occ3d(l) => {
            let d = PyDict::new(py);
            d.set_item("semantics", l.semantics.into_pyarray(py).reshape(l.dims)?)?;
            d.set_item("mask_lidar", l.mask_lidar.into_pyarray(py).reshape(l.dims)?)?;
            d.set_item(
                "mask_camera",
                l.mask_camera.into_pyarray(py).reshape(l.dims)?,
            )?;
            d.into_any()
        }
    })
}

fn dims3(shape: &[usize], what: &str) -> PyResult<[usize; 3]> {
    match shape {
        [x, y, z] => Ok([*x, *y, *z]),
        _ => Err(value_err(format!(
            "{what} must be a 3D array [X, Y, Z], got shape {shape:?}"
        ))),
    }
}

/// A grid of `dims` for the writers (they check the value count against it; the file itself
/// stores no shape).
fn grid_of(dims: [usize; 3]) -> VoxelGrid {
    VoxelGrid {
        dims,
        ..VoxelGrid::semantic_kitti()
    }
}

/// `.label` ids: uint16 raw ids as they are, or with `learning` the 20 learning classes (uint8,
/// 255 = ignore), mapped back to raw ids as in a submission.
fn label_values(a: &Bound<'_, PyAny>, learning: bool) -> PyResult<(Vec<u16>, [usize; 3])> {
    if learning {
        let a: PyReadonlyArrayDyn<'_, i64> = a.extract()?;
        let dims = dims3(a.shape(), "labels")?;
        let v = c_order(&a);
        if let Some((i, &c)) = v
            .iter()
            .enumerate()
            .find(|(_, &c)| !(0..20).contains(&c) && c != i64::from(IGNORE))
        {
            return Err(value_err(format!(
                "learning class {c} at flat index {i} is not 0..=19 or 255"
            )));
        }
        let c: Vec<u8> = v.into_iter().map(|c| c as u8).collect();
        Ok((LearningMap::semantic_kitti().inverse_remap(&c), dims))
    } else {
        let a: PyReadonlyArrayDyn<'_, i64> = a.extract()?;
        let dims = dims3(a.shape(), "labels")?;
        let v = c_order(&a);
        let mut out = Vec::with_capacity(v.len());
        for (i, x) in v.into_iter().enumerate() {
            out.push(u16::try_from(x).map_err(|_| {
                value_err(format!(
                    "raw label {x} at flat index {i} does not fit a uint16 .label file"
                ))
            })?);
        }
        Ok((out, dims))
    }
}

fn u8_values(a: &Bound<'_, PyAny>, what: &str) -> PyResult<(Vec<u8>, [usize; 3])> {
    let a: PyReadonlyArrayDyn<'_, i64> = a.extract()?;
    let dims = dims3(a.shape(), what)?;
    let mut out = Vec::with_capacity(a.len());
    for (i, x) in c_order(&a).into_iter().enumerate() {
        out.push(u8::try_from(x).map_err(|_| {
            value_err(format!("{what} value {x} at flat index {i} is not 0..=255"))
        })?);
    }
    Ok((out, dims))
}

/// The arrays of an Occ3D `labels.npz`.
const OCC3D_KEYS: [&str; 3] = ["semantics", "mask_lidar", "mask_camera"];

#[pyfunction]
#[pyo3(signature = (path, data, learning = false))]
fn write_voxels(
    py: Python<'_>,
    path: PathBuf,
    data: &Bound<'_, PyAny>,
    learning: bool,
) -> PyResult<()> {
    let kind = voxels::VoxelFileKind::of(&path).map_err(lib_err)?;
    if kind != voxels::VoxelFileKind::Occ3d && data.cast::<PyDict>().is_ok() {
        return Err(value_err(format!(
            "{}: a SemanticKITTI voxel file is written from one [X, Y, Z] array; a dict is for an Occ3D labels.npz",
            path.display()
        )));
    }
    let file = match kind {
        voxels::VoxelFileKind::KittiLabel => {
            let (raw, dims) = label_values(data, learning)?;
            VoxelFile::KittiLabel {
                raw,
                grid: grid_of(dims),
            }
        }
        voxels::VoxelFileKind::KittiBits => {
            let (bits, dims) = u8_values(data, "bits")?;
            VoxelFile::KittiBits {
                bits,
                grid: grid_of(dims),
            }
        }
        voxels::VoxelFileKind::Occ3d => {
            let d = data
                .cast::<PyDict>()
                .map_err(|_| value_err("an Occ3D labels.npz is written from a dict with 'semantics' (and optionally 'mask_lidar', 'mask_camera')"))?;
            // A misspelt mask would otherwise be left out and written as all ones.
            for key in d.keys() {
                let key: String = key.extract().unwrap_or_else(|_| format!("{key}"));
                if !OCC3D_KEYS.contains(&key.as_str()) {
                    return Err(value_err(format!(
                        "{}: unknown key '{key}' (an Occ3D labels.npz holds {})",
                        path.display(),
                        OCC3D_KEYS.join(", ")
                    )));
                }
            }
            let sem = d
                .get_item("semantics")?
                .ok_or_else(|| value_err("the dict has no 'semantics'"))?;
            let (semantics, dims) = u8_values(&sem, "semantics")?;
            let mask = |key: &str| -> PyResult<Vec<u8>> {
                match d.get_item(key)? {
                    None => Ok(vec![1; semantics.len()]),
                    Some(m) => {
                        let (m, md) = u8_values(&m, key)?;
                        if md != dims {
                            return Err(value_err(format!(
                                "{key} has shape {md:?} but semantics {dims:?}"
                            )));
                        }
                        Ok(m)
                    }
                }
            };
            VoxelFile::Occ3d(Occ3dLabels {
                mask_lidar: mask("mask_lidar")?,
                mask_camera: mask("mask_camera")?,
                semantics,
                dims,
            })
        }
    };
    py.detach(|| voxels::write_voxels(&path, &file))
        .map_err(lib_err)
}

#[pyfunction]
fn read_image<'py>(py: Python<'py>, path: PathBuf) -> PyResult<Bound<'py, PyAny>> {
    let img = py
        .detach(|| occ_data::image::read_image(&path))
        .map_err(lib_err)?;
    Ok(img
        .data
        .into_pyarray(py)
        .reshape([img.height, img.width, 3])?
        .into_any())
}

/// An int or a sequence of three ints.
#[derive(FromPyObject)]
enum Triple {
    One(usize),
    Three([usize; 3]),
}

impl Triple {
    fn get(self) -> [usize; 3] {
        match self {
            Triple::One(v) => [v; 3],
            Triple::Three(v) => v,
        }
    }
}

#[pyfunction]
#[pyo3(signature = (coords, feats, weight, spatial_shape, kernel, stride = Triple::One(1), padding = Triple::One(0), dilation = Triple::One(1), subm = false, transposed = false, batch_size = None))]
#[allow(clippy::too_many_arguments)]
fn conv3d<'py>(
    py: Python<'py>,
    coords: PyReadonlyArrayDyn<'py, i64>,
    feats: PyReadonlyArrayDyn<'py, f32>,
    weight: PyReadonlyArrayDyn<'py, f32>,
    spatial_shape: Triple,
    kernel: Triple,
    stride: Triple,
    padding: Triple,
    dilation: Triple,
    subm: bool,
    transposed: bool,
    batch_size: Option<usize>,
) -> PyResult<Bound<'py, PyTuple>> {
    let (cs, fs, ws) = (coords.shape(), feats.shape(), weight.shape());
    if cs.len() != 2 || cs[1] != 4 {
        return Err(value_err(format!(
            "coords must be [N, 4] (batch, x, y, z), got shape {cs:?}"
        )));
    }
    if fs.len() != 2 || fs[0] != cs[0] {
        return Err(value_err(format!(
            "feats must be [N={}, Cin], got shape {fs:?}",
            cs[0]
        )));
    }
    let kernel = kernel.get();
    if ws.len() != 5 || ws[1..4] != kernel || ws[4] != fs[1] {
        return Err(value_err(format!(
            "weight must be [Cout, {}, {}, {}, Cin={}] (spconv's layout), got shape {ws:?}",
            kernel[0], kernel[1], kernel[2], fs[1]
        )));
    }
    if subm && transposed {
        return Err(value_err("subm and transposed exclude each other"));
    }
    let (c_in, c_out) = (fs[1], ws[0]);
    let mut sites = Vec::with_capacity(cs[0]);
    let c = c_order_cow(&coords);
    for (row, r) in c.chunks_exact(4).enumerate() {
        let mut s = [0i32; 4];
        for (d, &v) in s.iter_mut().zip(r) {
            *d = i32::try_from(v)
                .map_err(|_| value_err(format!("coords row {row}: {r:?} does not fit int32")))?;
        }
        sites.push(s);
    }
    let (f, w) = (c_order_cow(&feats), c_order_cow(&weight));
    let spec = ArrayConvSpec {
        spatial_shape: spatial_shape.get(),
        kernel,
        stride: stride.get(),
        padding: padding.get(),
        dilation: dilation.get(),
        kind: ArrayConvKind::from_flags(subm, transposed),
        batch_size,
    };
    let out = py
        .detach(|| conv3d_arrays(sites, &f, c_in, &w, c_out, &spec))
        .map_err(|e| value_err(e.to_string()))?;
    let m = out.coords.len();
    let oc: Vec<i32> = out.coords.into_iter().flatten().collect();
    let oc = oc.into_pyarray(py).reshape([m, 4])?;
    let of = out.feats.into_pyarray(py).reshape([m, c_out])?;
    PyTuple::new(py, [oc.into_any(), of.into_any()])
}

/// A trained network loaded from a training run folder.
#[pyclass(module = "sparseocc._native", name = "Model", frozen)]
struct Model {
    net: Mutex<OccNet<Cpu>>,
    cfg: RunConfig,
    grid: VoxelGrid,
    run_dir: PathBuf,
}

impl Model {
    /// A prediction's classes as an `[X, Y, Z]` uint8 array.
    fn classes_array<'py>(
        &self,
        py: Python<'py>,
        pred: occ_train::infer::Prediction,
    ) -> PyResult<Bound<'py, PyAny>> {
        Ok(pred
            .classes
            .into_pyarray(py)
            .reshape(self.grid.dims)?
            .into_any())
    }

    /// Runs `f` on the network (one prediction at a time: the network is behind a mutex).
    fn with_net<R>(
        &self,
        f: impl FnOnce(&OccNet<Cpu>) -> Result<R, occ_train::TrainError>,
    ) -> Result<R, occ_train::TrainError> {
        let net = self.net.lock().map_err(|_| {
            occ_train::TrainError::Data("the model was poisoned by an earlier panic".into())
        })?;
        f(&net)
    }
}

/// `calib`: a path to a KITTI `calib.txt`, or a dict with the 3x4 `P2` and `Tr` matrices.
fn read_calib_arg(calib: &Bound<'_, PyAny>) -> PyResult<Calib> {
    if let Ok(d) = calib.cast::<PyDict>() {
        let m = |key: &str| -> PyResult<[[f64; 4]; 3]> {
            let v = d
                .get_item(key)?
                .ok_or_else(|| value_err(format!("calib has no '{key}'")))?;
            // Any array-like of numbers (an integer array, nested lists), as numpy reads it.
            let bad = |_| value_err(format!("calib['{key}'] must be a 3x4 array of numbers"));
            let a = calib
                .py()
                .import("numpy")?
                .call_method1("asarray", (v, "float64"))
                .map_err(bad)?;
            let a: PyReadonlyArrayDyn<'_, f64> = a.extract().map_err(bad)?;
            let vals = c_order(&a);
            if vals.len() != 12 {
                return Err(value_err(format!(
                    "calib['{key}'] must be 3x4 (12 values), got shape {:?}",
                    a.shape()
                )));
            }
            Ok(std::array::from_fn(|r| {
                std::array::from_fn(|c| vals[r * 4 + c])
            }))
        };
        return Calib::from_rows(m("P2")?, m("Tr")?).map_err(value_err);
    }
    let path: PathBuf = calib.extract().map_err(|_| {
        value_err("calib must be a path to calib.txt or a dict {'P2': 3x4, 'Tr': 3x4}")
    })?;
    occ_data::formats::semantic_kitti::read_calib(&path).map_err(lib_err)
}

#[pymethods]
impl Model {
    /// Loads a training run (`config.toml`, `grid.json`, `checkpoint/`), or its `checkpoint/`.
    #[staticmethod]
    fn load(py: Python<'_>, run_dir: PathBuf) -> PyResult<Self> {
        let (cfg, grid, net) = py
            .detach(|| occ_train::trainer::load_run::<Cpu>(&run_dir, &Default::default()))
            .map_err(lib_err)?;
        Ok(Model {
            net: Mutex::new(net),
            cfg,
            grid,
            run_dir,
        })
    }

    /// One camera image `[H, W, 3]` uint8 RGB with its calibration -> classes `[X, Y, Z]` uint8.
    #[pyo3(signature = (image, calib, test_mirror = None))]
    fn predict<'py>(
        &self,
        py: Python<'py>,
        image: &Bound<'py, PyAny>,
        calib: &Bound<'py, PyAny>,
        test_mirror: Option<bool>,
    ) -> PyResult<Bound<'py, PyAny>> {
        let image: PyReadonlyArrayDyn<'py, u8> = image.extract().map_err(|_| {
            let got = match image.getattr("dtype") {
                Ok(d) => format!("dtype {d}"),
                Err(_) => format!("a {}", image.get_type()),
            };
            value_err(format!(
                "image must be an [H, W, 3] uint8 RGB numpy array (as read_image returns), got \
                 {got}; an image of floats in [0, 1] is (img * 255).round().astype(np.uint8)"
            ))
        })?;
        let s = image.shape();
        if s.len() != 3 || s[2] != 3 || s[0] == 0 || s[1] == 0 {
            return Err(value_err(format!(
                "image must be [H, W, 3] uint8 RGB, got shape {s:?}"
            )));
        }
        let img = occ_data::image::RgbImage {
            width: s[1],
            height: s[0],
            data: c_order(&image),
        };
        let cal = read_calib_arg(calib)?;
        let test_mirror = test_mirror.unwrap_or(self.cfg.data.test_mirror);
        let pred = py
            .detach(|| {
                let sample = occ_train::infer::sample_from_image(
                    &img,
                    &cal,
                    &self.cfg.data.pipeline(),
                    "image",
                )?;
                self.with_net(|net| {
                    occ_train::infer::predict_sample(
                        net,
                        &sample,
                        self.grid,
                        &Default::default(),
                        test_mirror,
                    )
                })
            })
            .map_err(lib_err)?;
        self.classes_array(py, pred)
    }

    /// One frame of a dataset folder (the run's data layout) -> classes `[X, Y, Z]` uint8.
    #[pyo3(signature = (data_root, sequence, frame, test_mirror = None))]
    fn predict_frame<'py>(
        &self,
        py: Python<'py>,
        data_root: PathBuf,
        sequence: &str,
        frame: &str,
        test_mirror: Option<bool>,
    ) -> PyResult<Bound<'py, PyAny>> {
        let test_mirror = test_mirror.unwrap_or(self.cfg.data.test_mirror);
        let needs_points = self.cfg.model.needs_points_at_test();
        let pred = py
            .detach(|| {
                self.with_net(|net| {
                    occ_train::infer::predict_dataset_frame(
                        net,
                        &self.cfg.data,
                        needs_points,
                        &data_root,
                        sequence,
                        frame,
                        self.grid,
                        &Default::default(),
                        test_mirror,
                    )
                })
            })
            .map_err(lib_err)?;
        self.classes_array(py, pred)
    }

    /// The grid the model predicts, `(X, Y, Z)`.
    #[getter]
    fn grid_shape(&self) -> (usize, usize, usize) {
        let [x, y, z] = self.grid.dims;
        (x, y, z)
    }

    /// Voxel edge in metres and the grid's minimum corner in the frame of the labels.
    #[getter]
    fn voxel_size_m(&self) -> f64 {
        self.grid.voxel_size_m
    }

    #[getter]
    fn origin_m(&self) -> (f64, f64, f64) {
        let [x, y, z] = self.grid.origin_m;
        (x, y, z)
    }

    /// `sparseocc++`, `sparseocc` or `dense`.
    #[getter]
    fn kind(&self) -> &'static str {
        self.cfg.model.kind.name()
    }

    /// Class names of the predicted ids (the run's dataset protocol).
    #[getter]
    fn class_names(&self) -> Vec<&'static str> {
        self.cfg.data.format.protocol().class_names().to_vec()
    }

    fn __repr__(&self) -> String {
        format!(
            "Model(kind='{}', grid={:?}, run='{}')",
            self.cfg.model.kind.name(),
            self.grid.dims,
            self.run_dir.display()
        )
    }
}

#[pymodule]
fn _native(m: &Bound<'_, PyModule>) -> PyResult<()> {
    m.add("__version__", env!("CARGO_PKG_VERSION"))?;
    m.add("SparseOccError", m.py().get_type::<SparseOccError>())?;
    m.add_function(wrap_pyfunction!(evaluate, m)?)?;
    m.add_function(wrap_pyfunction!(confusion, m)?)?;
    m.add_function(wrap_pyfunction!(report, m)?)?;
    m.add_function(wrap_pyfunction!(class_names, m)?)?;
    m.add_function(wrap_pyfunction!(synth, m)?)?;
    m.add_function(wrap_pyfunction!(read_voxels, m)?)?;
    m.add_function(wrap_pyfunction!(write_voxels, m)?)?;
    m.add_function(wrap_pyfunction!(conv3d, m)?)?;
    m.add_function(wrap_pyfunction!(read_image, m)?)?;
    m.add_class::<Model>()?;
    Ok(())
}
