//! Loading pretrained weights (torchvision ResNet checkpoints and any module stored with PyTorch key
//! names) from PyTorch `.pth`/`.pt` files and `.safetensors` files into burn modules.
//!
//! Formats:
//! - PyTorch: the zip format `torch.save` writes since torch 1.6 (`<name>/data.pkl` +
//!   `<name>/data/<key>`), read here with the workspace `zip` crate and a small pickle interpreter
//!   covering what `torch.save` emits (protocols 2-5: dicts, `OrderedDict`,
//!   `torch._utils._rebuild_tensor_v2` / `_rebuild_parameter`, persistent storages, memo, strided
//!   views at any offset; objects that are not tensors, such as numpy values in a checkpoint's
//!   `meta`, are skipped). Nested dicts are flattened with `.` (so `{"state_dict": {...}}` gives
//!   `state_dict.conv1.weight`). The legacy (pre-1.6, non-zip) format is not supported.
//!   Why not burn-store's `PytorchStore` (feature `pytorch`, checked at 0.21.0): it ignores the strides
//!   of a stored view, so a channels_last conv weight or a transposed tensor loads with its elements in
//!   the wrong order and no error; it fills a missing or short storage with zeros; and it rejects the
//!   whole file for pickle protocol 4/5 opcodes, for an object it does not know (a numpy scalar in
//!   `meta`) and for a one-entry int-keyed dict (an optimizer's `state`). `tests/data/pth_cases` has one
//!   file of each kind. Its feature would also add 38 crates (zip 8 with every codec, zstd's C library,
//!   tar, crypto) for the formats it has and this reader lacks: legacy and tar.
//! - safetensors: read with burn-store's `SafetensorsStore`.
//!
//! Key handling (burn-store's applier with its PyTorch adapter):
//! - file keys are matched to burn module paths (`layer1.0.conv1.weight`, `layer2.0.downsample.1.bias`,
//!   ...); the field names of [`crate::encoder::backbone::ResNet`] equal torchvision's, so no renaming is needed;
//! - batch norm `weight`/`bias` load into burn's `gamma`/`beta`; `running_mean`/`running_var` load as
//!   they are; burn-named files (`gamma`/`beta`) load too;
//! - tensors the model does not have (`fc.*`, `num_batches_tracked`, stages not built) are ignored and
//!   listed in [`LoadReport::unused`];
//! - [`LoadOptions::key_prefix`] selects a sub-module of a larger checkpoint (e.g. `img_backbone.`),
//!   [`LoadOptions::top_level_key`] a nested state dict of a `.pth` (e.g. `state_dict`);
//! - floating tensors (f16, bf16, f32, f64) are converted to the float dtype of the module's device
//!   (burn 0.21 device setting; `B::FloatElem` by default).
//!
//! A tensor the model needs that is absent, or present with another shape, is an error naming the file
//! and the key ([`WeightsError`]).

use std::cell::RefCell;
use std::collections::{BTreeSet, HashMap};
use std::fmt::Write as _;
use std::io::Read;
use std::path::{Path, PathBuf};
use std::rc::Rc;

use burn::module::{Module, ParamId};
use burn::store::{
    ApplyError, ModuleAdapter, ModuleSnapshot, ModuleStore, PyTorchToBurnAdapter, SafetensorsStore,
    TensorSnapshot, TensorSnapshotError,
};
use burn::tensor::backend::Backend;
use burn::tensor::{bf16, f16, get_device_settings, DType, Element, Shape, TensorData};
use thiserror::Error;

use crate::encoder::backbone::ResNet;

/// Namespace given to file keys outside [`LoadOptions::key_prefix`] so they never match a module path.
const IGNORED: &str = "__outside_prefix__";

/// Errors from loading weights; every variant names the file.
#[derive(Debug, Error)]
pub enum WeightsError {
    /// The file cannot be opened or read.
    #[error("weights file {path}: {source}")]
    Io {
        /// File.
        path: PathBuf,
        /// Cause.
        #[source]
        source: std::io::Error,
    },
    /// The file is not a readable PyTorch / safetensors checkpoint.
    #[error("weights file {path}: cannot parse as {format}: {message}")]
    Parse {
        /// File.
        path: PathBuf,
        /// `PyTorch` or `safetensors`.
        format: &'static str,
        /// What is wrong.
        message: String,
    },
    /// Options that do not apply (a top-level key that is absent or used with safetensors, an empty
    /// prefix).
    #[error("weights file {path}: {message}")]
    Options {
        /// File.
        path: PathBuf,
        /// Problem.
        message: String,
    },
    /// Tensors the model needs are not in the file.
    #[error("weights file {path}: {} tensor(s) missing: {}{}", keys.len(), list(keys), hint(unused))]
    MissingKeys {
        /// File.
        path: PathBuf,
        /// Missing file keys (PyTorch naming, with the prefix), each followed by the model parameter
        /// in parentheses when it is named differently.
        keys: Vec<String>,
        /// File keys that matched nothing, except BN `num_batches_tracked` counters (to spot a
        /// renamed key or a wrong prefix).
        unused: Vec<String>,
    },
    /// A tensor has another shape in the file than in the model.
    #[error("weights file {path}: key {key}: shape {found:?} in the file, the model expects {expected:?}")]
    ShapeMismatch {
        /// File.
        path: PathBuf,
        /// File key (with the model parameter in parentheses when named differently).
        key: String,
        /// Model shape.
        expected: Vec<usize>,
        /// File shape.
        found: Vec<usize>,
    },
    /// A tensor could not be decoded or converted.
    #[error("weights file {path}: key {key}: {message}")]
    Tensor {
        /// File.
        path: PathBuf,
        /// File key.
        key: String,
        /// Problem.
        message: String,
    },
}

fn list(keys: &[String]) -> String {
    let mut s = keys.iter().take(12).cloned().collect::<Vec<_>>().join(", ");
    if keys.len() > 12 {
        let _ = write!(s, ", ... ({} more)", keys.len() - 12);
    }
    s
}

fn hint(unused: &[String]) -> String {
    if unused.is_empty() {
        String::new()
    } else {
        format!("; unused file keys include: {}", list(unused))
    }
}

/// Where in the file the module's tensors are.
#[derive(Debug, Clone, Default)]
pub struct LoadOptions {
    /// `.pth` only: key of a nested state dict (e.g. `"state_dict"`, `"model"`).
    pub top_level_key: Option<String>,
    /// Only file keys starting with this prefix are used, with the prefix removed
    /// (e.g. `"img_backbone."` for an mmdet-style detector checkpoint).
    pub key_prefix: Option<String>,
}

/// What a successful load did.
#[derive(Debug, Clone)]
pub struct LoadReport {
    /// Number of module tensors loaded (all of them: a partial load is an error).
    pub applied: usize,
    /// File keys (original naming) that the module does not use, sorted.
    pub unused: Vec<String>,
}

/// Checkpoint container format.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum WeightsFormat {
    /// `torch.save` zip archive.
    Pytorch,
    /// safetensors (`u64` header length, JSON header, raw data).
    Safetensors,
}

/// Detects the format from the first bytes: zip magic → PyTorch; `{` after an 8-byte length →
/// safetensors; anything else is a [`WeightsError::Parse`].
pub fn detect_format(path: &Path) -> Result<WeightsFormat, WeightsError> {
    let io = |source| WeightsError::Io {
        path: path.to_path_buf(),
        source,
    };
    let mut head = Vec::with_capacity(9);
    std::fs::File::open(path)
        .map_err(io)?
        .take(9)
        .read_to_end(&mut head)
        .map_err(io)?;
    if head.starts_with(b"PK\x03\x04") {
        return Ok(WeightsFormat::Pytorch);
    }
    if head.len() == 9 && head[8] == b'{' {
        return Ok(WeightsFormat::Safetensors);
    }
    Err(WeightsError::Parse {
        path: path.to_path_buf(),
        format: "PyTorch zip or safetensors",
        message: "unknown file signature (legacy non-zip torch.save files are not supported: \
                  re-save with torch >= 1.6)"
            .into(),
    })
}

/// Loads a torchvision-layout ResNet state dict (e.g. `resnet50-0676ba61.pth` or its safetensors
/// conversion) into `resnet`. See [`load_module`].
pub fn load_resnet<B: Backend>(
    resnet: &mut ResNet<B>,
    path: &Path,
    options: &LoadOptions,
) -> Result<LoadReport, WeightsError> {
    load_module(resnet, path, options)
}

/// Loads every tensor of `module` from `path` (format detected with [`detect_format`]), matching
/// file keys (PyTorch naming) to module paths as described in the module docs. On error the module
/// may be partially updated.
pub fn load_module<B: Backend, M: Module<B>>(
    module: &mut M,
    path: &Path,
    options: &LoadOptions,
) -> Result<LoadReport, WeightsError> {
    let prefix = match options.key_prefix.as_deref() {
        Some("") => {
            return Err(WeightsError::Options {
                path: path.to_path_buf(),
                message: "key_prefix is empty (use None to load the keys as they are)".into(),
            })
        }
        p => p.unwrap_or(""),
    };
    let snapshots = match detect_format(path)? {
        WeightsFormat::Pytorch => read_pth(path, options.top_level_key.as_deref())?,
        WeightsFormat::Safetensors => {
            if options.top_level_key.is_some() {
                return Err(WeightsError::Options {
                    path: path.to_path_buf(),
                    message: "top_level_key applies to .pth files only (safetensors is flat)"
                        .into(),
                });
            }
            let mut store = SafetensorsStore::from_file(path).map_indices_contiguous(false);
            store
                .get_all_snapshots()
                .map_err(|e| WeightsError::Parse {
                    path: path.to_path_buf(),
                    format: "safetensors",
                    message: e.to_string(),
                })?
                .values()
                .cloned()
                .collect()
        }
    };
    // Key prefix: keys with it lose it, the others move under IGNORED.
    let snapshots: Vec<TensorSnapshot> = snapshots
        .into_iter()
        .map(|mut s| {
            let key = s.full_path();
            let new_key = match key.strip_prefix(prefix) {
                Some(rest) => rest.to_string(),
                None => format!("{IGNORED}.{key}"),
            };
            if new_key != key {
                s.path_stack = Some(new_key.split('.').map(str::to_string).collect());
            }
            s
        })
        .collect();
    let file_paths: BTreeSet<String> = snapshots.iter().map(|s| s.full_path()).collect();
    // burn 0.21 creates float tensors with the device's default dtype (a per-process device
    // setting, `B::FloatElem` unless changed): loaded tensors must match it.
    let dtype = module
        .devices()
        .first()
        .map(|d| DType::from(get_device_settings::<B>(d).float_dtype))
        .unwrap_or_else(<B::FloatElem as Element>::dtype);
    let adapter = PyTorchToBurnAdapter.chain(CastFloat { dtype });
    let result = module.apply(snapshots, None, Some(Box::new(adapter)), true);

    // File-side key of a module path: the burn name if the file has it, else the PyTorch norm name
    // (the applier's fallback). burn-store lists tensors matched through that fallback as unused,
    // so "unused" is recomputed from the applied paths.
    let file_side = |model_path: &str| -> String {
        if file_paths.contains(model_path) {
            model_path.to_string()
        } else if let Some(stem) = model_path.strip_suffix(".gamma") {
            format!("{stem}.weight")
        } else if let Some(stem) = model_path.strip_suffix(".beta") {
            format!("{stem}.bias")
        } else {
            model_path.to_string()
        }
    };
    let file_key = |model_path: &str| -> String {
        let key = file_side(model_path);
        if key == model_path {
            format!("{prefix}{key}")
        } else {
            format!("{prefix}{key} (model parameter {model_path})")
        }
    };
    let original_key = |p: &str| match p.strip_prefix(IGNORED).and_then(|r| r.strip_prefix('.')) {
        Some(rest) => rest.to_string(),
        None => format!("{prefix}{p}"),
    };
    let used: BTreeSet<String> = result.applied.iter().map(|p| file_side(p)).collect();
    let unused: Vec<String> = file_paths
        .iter()
        .filter(|k| !used.contains(*k))
        .map(|k| original_key(k))
        .collect::<BTreeSet<String>>()
        .into_iter()
        .collect();

    if let Some(err) = result.errors.first() {
        return Err(match err {
            ApplyError::ShapeMismatch {
                path: p,
                expected,
                found,
            } => WeightsError::ShapeMismatch {
                path: path.to_path_buf(),
                key: file_key(p),
                expected: expected.to_vec(),
                found: found.to_vec(),
            },
            ApplyError::DTypeMismatch { path: p, .. }
            | ApplyError::AdapterError { path: p, .. }
            | ApplyError::LoadError { path: p, .. } => WeightsError::Tensor {
                path: path.to_path_buf(),
                key: file_key(p),
                message: err.to_string(),
            },
        });
    }
    if !result.missing.is_empty() {
        let mut keys: Vec<String> = result.missing.iter().map(|(p, _)| file_key(p)).collect();
        keys.sort();
        return Err(WeightsError::MissingKeys {
            path: path.to_path_buf(),
            keys,
            unused: unused
                .iter()
                .filter(|k| !k.ends_with(".num_batches_tracked"))
                .cloned()
                .collect(),
        });
    }
    Ok(LoadReport {
        applied: result.applied.len(),
        unused,
    })
}

/// Converts floating tensors to the model's float dtype (integer tensors are left alone).
#[derive(Debug, Clone)]
struct CastFloat {
    dtype: DType,
}

impl ModuleAdapter for CastFloat {
    fn adapt(&self, snapshot: &TensorSnapshot) -> TensorSnapshot {
        if !snapshot.dtype.is_float() || snapshot.dtype == self.dtype {
            return snapshot.clone();
        }
        let data_fn = snapshot.clone_data_fn();
        let dtype = self.dtype;
        TensorSnapshot::from_closure(
            Rc::new(move || data_fn().map(|d| d.convert_dtype(dtype))),
            dtype,
            snapshot.shape.clone(),
            snapshot.path_stack.clone().unwrap_or_default(),
            snapshot.container_stack.clone().unwrap_or_default(),
            snapshot.tensor_id.unwrap_or_default(),
        )
    }

    fn clone_box(&self) -> Box<dyn ModuleAdapter> {
        Box::new(self.clone())
    }
}

// ---- PyTorch zip reader -----------------------------------------------------------------------

/// Reads every tensor of a `torch.save` zip archive as lazily decoded snapshots keyed by the
/// flattened dict path.
fn read_pth(path: &Path, top_level_key: Option<&str>) -> Result<Vec<TensorSnapshot>, WeightsError> {
    let parse = |message: String| WeightsError::Parse {
        path: path.to_path_buf(),
        format: "PyTorch",
        message,
    };
    let file = std::fs::File::open(path).map_err(|source| WeightsError::Io {
        path: path.to_path_buf(),
        source,
    })?;
    let mut archive =
        zip::ZipArchive::new(std::io::BufReader::new(file)).map_err(|e| parse(e.to_string()))?;
    let pkl_name = archive
        .file_names()
        .filter(|n| *n == "data.pkl" || n.ends_with("/data.pkl"))
        .min_by_key(|n| n.len())
        .map(str::to_string)
        .ok_or_else(|| parse("no data.pkl in the archive".into()))?;
    let root = &pkl_name[..pkl_name.len() - "data.pkl".len()];
    let read_entry = |archive: &mut zip::ZipArchive<_>, name: &str| -> Result<Vec<u8>, String> {
        let mut f = archive.by_name(name).map_err(|e| format!("{name}: {e}"))?;
        let mut bytes = Vec::new();
        f.read_to_end(&mut bytes)
            .map_err(|e| format!("{name}: {e}"))?;
        Ok(bytes)
    };
    if let Ok(order) = read_entry(&mut archive, &format!("{root}byteorder")) {
        if order.trim_ascii() != b"little" {
            return Err(parse(format!(
                "byte order {:?} is not supported (little only)",
                String::from_utf8_lossy(&order)
            )));
        }
    }
    let pkl = read_entry(&mut archive, &pkl_name).map_err(parse)?;
    let value = Unpickler::new(&pkl)
        .run()
        .map_err(|e| parse(format!("{pkl_name}: {e}")))?;
    let value = match top_level_key {
        None => value,
        Some(k) => dict_get(&value, k).ok_or_else(|| WeightsError::Options {
            path: path.to_path_buf(),
            message: format!("top_level_key {k:?} is not a key of the checkpoint's top-level dict"),
        })?,
    };
    let mut tensors = Vec::new();
    flatten(&value, String::new(), &mut tensors);
    if tensors.is_empty() && !matches!(value, Pv::Dict(_)) {
        return Err(parse("the pickled object is not a dict of tensors".into()));
    }
    let mut storages: HashMap<String, Rc<Vec<u8>>> = HashMap::new();
    let mut out = Vec::with_capacity(tensors.len());
    for (key, t) in tensors {
        let storage = match storages.get(&t.storage) {
            Some(s) => s.clone(),
            None => {
                let bytes = read_entry(&mut archive, &format!("{root}data/{}", t.storage))
                    .map_err(|e| parse(format!("storage of {key}: {e}")))?;
                let s = Rc::new(bytes);
                storages.insert(t.storage.clone(), s.clone());
                s
            }
        };
        out.push(snapshot(key, t, storage));
    }
    Ok(out)
}

fn dict_get(v: &Pv, key: &str) -> Option<Pv> {
    match v {
        Pv::Dict(d) => d
            .borrow()
            .iter()
            .find(|(k, _)| matches!(k, Pv::Str(s) if s == key))
            .map(|(_, v)| v.clone()),
        _ => None,
    }
}

/// Collects `(dotted key, tensor)` from nested dicts (string keys only; other leaves are skipped).
fn flatten(v: &Pv, prefix: String, out: &mut Vec<(String, Rc<TensorRef>)>) {
    match v {
        Pv::Tensor(t) if !prefix.is_empty() => out.push((prefix, t.clone())),
        Pv::Dict(d) => {
            for (k, v) in d.borrow().iter() {
                let name = match k {
                    Pv::Str(s) => s.clone(),
                    Pv::Int(i) => i.to_string(),
                    _ => continue,
                };
                let key = if prefix.is_empty() {
                    name
                } else {
                    format!("{prefix}.{name}")
                };
                flatten(v, key, out);
            }
        }
        _ => {}
    }
}

/// Element type of a torch storage, from its legacy class name (`torch.FloatStorage`, ...).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum StorageType {
    F64,
    F32,
    F16,
    Bf16,
    I64,
    I32,
    I16,
    I8,
    U8,
    Bool,
}

impl StorageType {
    fn from_class(name: &str) -> Option<Self> {
        Some(match name {
            "DoubleStorage" => Self::F64,
            "FloatStorage" => Self::F32,
            "HalfStorage" => Self::F16,
            "BFloat16Storage" => Self::Bf16,
            "LongStorage" => Self::I64,
            "IntStorage" => Self::I32,
            "ShortStorage" => Self::I16,
            "CharStorage" => Self::I8,
            "ByteStorage" => Self::U8,
            "BoolStorage" => Self::Bool,
            _ => return None,
        })
    }

    fn size(self) -> usize {
        match self {
            Self::F64 | Self::I64 => 8,
            Self::F32 | Self::I32 => 4,
            Self::F16 | Self::Bf16 | Self::I16 => 2,
            Self::I8 | Self::U8 | Self::Bool => 1,
        }
    }

    /// dtype of the decoded [`TensorData`] (floats keep theirs, integers are widened to i64).
    fn dtype(self) -> DType {
        match self {
            Self::F64 => DType::F64,
            Self::F32 => DType::F32,
            Self::F16 => DType::F16,
            Self::Bf16 => DType::BF16,
            Self::Bool => <bool as Element>::dtype(),
            _ => DType::I64,
        }
    }
}

/// A strided view of a storage (`_rebuild_tensor_v2(storage, offset, size, stride, ...)`).
#[derive(Debug)]
struct TensorRef {
    storage: String,
    kind: Result<StorageType, String>,
    offset: usize,
    shape: Vec<usize>,
    stride: Vec<usize>,
}

fn snapshot(key: String, t: Rc<TensorRef>, storage: Rc<Vec<u8>>) -> TensorSnapshot {
    let dtype = t.kind.as_ref().map_or(DType::F32, |k| k.dtype());
    let shape = Shape::from(t.shape.clone());
    let path_stack = key.split('.').map(str::to_string).collect();
    TensorSnapshot::from_closure(
        Rc::new(move || decode(&t, &storage).map_err(TensorSnapshotError::DataError)),
        dtype,
        shape,
        path_stack,
        Vec::new(),
        ParamId::new(),
    )
}

/// Gathers the view's elements in C order and decodes them (little endian).
fn decode(t: &TensorRef, storage: &[u8]) -> Result<TensorData, String> {
    let kind = t.kind.clone()?;
    let size = kind.size();
    let numel_storage = storage.len() / size;
    let numel: usize = t.shape.iter().product();
    let mut indices = Vec::with_capacity(numel);
    if numel > 0 {
        let last = t
            .shape
            .iter()
            .zip(&t.stride)
            .try_fold(t.offset, |acc, (&n, &s)| {
                acc.checked_add((n - 1).checked_mul(s)?)
            })
            .ok_or("view index overflows")?;
        if last >= numel_storage {
            return Err(format!(
                "view (offset {}, shape {:?}, stride {:?}) exceeds its storage of {numel_storage} elements",
                t.offset, t.shape, t.stride
            ));
        }
        let mut idx = vec![0usize; t.shape.len()];
        for _ in 0..numel {
            let flat = t.offset + idx.iter().zip(&t.stride).map(|(i, s)| i * s).sum::<usize>();
            indices.push(flat);
            for d in (0..idx.len()).rev() {
                idx[d] += 1;
                if idx[d] < t.shape[d] {
                    break;
                }
                idx[d] = 0;
            }
        }
    }
    let el = |i: usize| &storage[i * size..(i + 1) * size];
    let shape = t.shape.clone();
    Ok(match kind {
        StorageType::F64 => TensorData::new(
            indices
                .iter()
                .map(|&i| f64::from_le_bytes(el(i).try_into().unwrap_or([0; 8])))
                .collect::<Vec<f64>>(),
            shape,
        ),
        StorageType::F32 => TensorData::new(
            indices
                .iter()
                .map(|&i| f32::from_le_bytes(el(i).try_into().unwrap_or([0; 4])))
                .collect::<Vec<f32>>(),
            shape,
        ),
        StorageType::F16 => TensorData::new(
            indices
                .iter()
                .map(|&i| f16::from_le_bytes([el(i)[0], el(i)[1]]))
                .collect::<Vec<f16>>(),
            shape,
        ),
        StorageType::Bf16 => TensorData::new(
            indices
                .iter()
                .map(|&i| bf16::from_le_bytes([el(i)[0], el(i)[1]]))
                .collect::<Vec<bf16>>(),
            shape,
        ),
        StorageType::Bool => TensorData::new(
            indices
                .iter()
                .map(|&i| el(i)[0] != 0)
                .collect::<Vec<bool>>(),
            shape,
        ),
        _ => TensorData::new(
            indices
                .iter()
                .map(|&i| {
                    let b = el(i);
                    match kind {
                        StorageType::I64 => i64::from_le_bytes(b.try_into().unwrap_or([0; 8])),
                        StorageType::I32 => {
                            i64::from(i32::from_le_bytes(b.try_into().unwrap_or([0; 4])))
                        }
                        StorageType::I16 => i64::from(i16::from_le_bytes([b[0], b[1]])),
                        StorageType::I8 => i64::from(b[0] as i8),
                        _ => i64::from(b[0]),
                    }
                })
                .collect::<Vec<i64>>(),
            shape,
        ),
    })
}

/// Pickle values (the subset `torch.save` produces); dicts and lists are shared like Python objects.
/// (Scalar payloads are only read through `Debug` in error messages.)
#[allow(dead_code)]
#[derive(Debug, Clone)]
enum Pv {
    None,
    Bool(bool),
    Int(i64),
    Float(f64),
    Str(String),
    Bytes(Vec<u8>),
    Tuple(Rc<Vec<Pv>>),
    List(Rc<RefCell<Vec<Pv>>>),
    Dict(Rc<RefCell<Vec<(Pv, Pv)>>>),
    Global(Rc<(String, String)>),
    Storage(Rc<(String, Result<StorageType, String>)>),
    Tensor(Rc<TensorRef>),
    /// Anything else (reduced objects of unknown classes); ignored.
    Opaque,
    Mark,
}

fn new_dict() -> Pv {
    Pv::Dict(Rc::new(RefCell::new(Vec::new())))
}

struct Unpickler<'a> {
    data: &'a [u8],
    pos: usize,
    stack: Vec<Pv>,
    memo: HashMap<u64, Pv>,
}

impl<'a> Unpickler<'a> {
    fn new(data: &'a [u8]) -> Self {
        Self {
            data,
            pos: 0,
            stack: Vec::new(),
            memo: HashMap::new(),
        }
    }

    fn take(&mut self, n: usize) -> Result<&'a [u8], String> {
        let end = self
            .pos
            .checked_add(n)
            .filter(|&e| e <= self.data.len())
            .ok_or_else(|| format!("truncated pickle at byte {}", self.pos))?;
        let s = &self.data[self.pos..end];
        self.pos = end;
        Ok(s)
    }

    fn u8(&mut self) -> Result<u8, String> {
        Ok(self.take(1)?[0])
    }

    fn le<const N: usize>(&mut self) -> Result<[u8; N], String> {
        let b = self.take(N)?;
        let mut a = [0u8; N];
        a.copy_from_slice(b);
        Ok(a)
    }

    fn line(&mut self) -> Result<String, String> {
        let rest = &self.data[self.pos..];
        let n = rest
            .iter()
            .position(|&b| b == b'\n')
            .ok_or("unterminated text line in pickle")?;
        let s = String::from_utf8_lossy(&rest[..n]).into_owned();
        self.pos += n + 1;
        Ok(s)
    }

    fn pop(&mut self) -> Result<Pv, String> {
        self.stack
            .pop()
            .ok_or_else(|| "pickle stack underflow".to_string())
    }

    fn top(&mut self) -> Result<&mut Pv, String> {
        self.stack
            .last_mut()
            .ok_or_else(|| "pickle stack underflow".to_string())
    }

    /// Pops everything above the topmost mark (and the mark).
    fn pop_mark(&mut self) -> Result<Vec<Pv>, String> {
        let m = self
            .stack
            .iter()
            .rposition(|v| matches!(v, Pv::Mark))
            .ok_or("pickle MARK missing")?;
        let items = self.stack.split_off(m + 1);
        self.stack.pop();
        Ok(items)
    }

    fn str_of(&mut self, n: usize) -> Result<Pv, String> {
        let b = self.take(n)?;
        Ok(Pv::Str(
            String::from_utf8(b.to_vec()).map_err(|e| format!("invalid UTF-8 in pickle: {e}"))?,
        ))
    }

    fn memo_get(&self, k: u64) -> Result<Pv, String> {
        self.memo
            .get(&k)
            .cloned()
            .ok_or_else(|| format!("pickle memo {k} missing"))
    }

    fn run(mut self) -> Result<Pv, String> {
        loop {
            let at = self.pos;
            let op = self.u8()?;
            match op {
                0x80 => {
                    self.u8()?; // PROTO
                }
                0x95 => {
                    self.take(8)?; // FRAME
                }
                b'.' => return self.pop(), // STOP
                b'(' => self.stack.push(Pv::Mark),
                b'}' => self.stack.push(new_dict()),
                b']' => self.stack.push(Pv::List(Rc::new(RefCell::new(Vec::new())))),
                b')' => self.stack.push(Pv::Tuple(Rc::new(Vec::new()))),
                b'N' => self.stack.push(Pv::None),
                0x88 => self.stack.push(Pv::Bool(true)),
                0x89 => self.stack.push(Pv::Bool(false)),
                b'K' => {
                    let v = self.u8()?;
                    self.stack.push(Pv::Int(i64::from(v)))
                }
                b'M' => {
                    let v = u16::from_le_bytes(self.le()?);
                    self.stack.push(Pv::Int(i64::from(v)))
                }
                b'J' => {
                    let v = i32::from_le_bytes(self.le()?);
                    self.stack.push(Pv::Int(i64::from(v)))
                }
                0x8a => {
                    // LONG1: little-endian two's complement of n bytes.
                    let n = self.u8()? as usize;
                    let b = self.take(n)?;
                    if n > 8 {
                        return Err(format!("integer of {n} bytes at {at}"));
                    }
                    let mut v: i64 = 0;
                    for (i, &x) in b.iter().enumerate() {
                        v |= i64::from(x) << (8 * i);
                    }
                    if n > 0 && n < 8 && b[n - 1] & 0x80 != 0 {
                        v -= 1i64 << (8 * n);
                    }
                    self.stack.push(Pv::Int(v))
                }
                b'I' | b'L' => {
                    let l = self.line()?;
                    let t = l.trim_end_matches('L');
                    let v = match t {
                        "01" => Pv::Bool(true),
                        "00" => Pv::Bool(false),
                        _ => Pv::Int(t.parse().map_err(|_| format!("bad int {l:?} at {at}"))?),
                    };
                    self.stack.push(v)
                }
                b'G' => {
                    let v = f64::from_be_bytes(self.le()?);
                    self.stack.push(Pv::Float(v))
                }
                b'F' => {
                    let l = self.line()?;
                    let v = l.parse().map_err(|_| format!("bad float {l:?} at {at}"))?;
                    self.stack.push(Pv::Float(v))
                }
                b'X' => {
                    let n = u32::from_le_bytes(self.le()?) as usize;
                    let v = self.str_of(n)?;
                    self.stack.push(v)
                }
                0x8c => {
                    let n = self.u8()? as usize;
                    let v = self.str_of(n)?;
                    self.stack.push(v)
                }
                0x8d => {
                    let n = usize::try_from(u64::from_le_bytes(self.le()?))
                        .map_err(|_| "string too long")?;
                    let v = self.str_of(n)?;
                    self.stack.push(v)
                }
                b'T' | b'B' => {
                    let n = u32::from_le_bytes(self.le()?) as usize;
                    let b = self.take(n)?.to_vec();
                    self.stack.push(Pv::Bytes(b))
                }
                b'U' | b'C' => {
                    let n = self.u8()? as usize;
                    let b = self.take(n)?.to_vec();
                    self.stack.push(Pv::Bytes(b))
                }
                b'V' => {
                    let l = self.line()?;
                    self.stack.push(Pv::Str(l))
                }
                b'c' => {
                    let module = self.line()?;
                    let name = self.line()?;
                    self.stack.push(Pv::Global(Rc::new((module, name))))
                }
                0x93 => {
                    // STACK_GLOBAL
                    let name = self.pop()?;
                    let module = self.pop()?;
                    match (module, name) {
                        (Pv::Str(m), Pv::Str(n)) => self.stack.push(Pv::Global(Rc::new((m, n)))),
                        _ => return Err(format!("STACK_GLOBAL without strings at {at}")),
                    }
                }
                b't' => {
                    let items = self.pop_mark()?;
                    self.stack.push(Pv::Tuple(Rc::new(items)))
                }
                0x85..=0x87 => {
                    let n = (op - 0x84) as usize;
                    if self.stack.len() < n {
                        return Err("pickle stack underflow".into());
                    }
                    let items = self.stack.split_off(self.stack.len() - n);
                    self.stack.push(Pv::Tuple(Rc::new(items)))
                }
                b'l' => {
                    let items = self.pop_mark()?;
                    self.stack.push(Pv::List(Rc::new(RefCell::new(items))))
                }
                b'd' => {
                    let items = self.pop_mark()?;
                    let d = new_dict();
                    set_items(&d, items)?;
                    self.stack.push(d)
                }
                b'a' => {
                    let v = self.pop()?;
                    if let Pv::List(l) = self.top()? {
                        l.borrow_mut().push(v)
                    }
                }
                b'e' => {
                    let items = self.pop_mark()?;
                    if let Pv::List(l) = self.top()? {
                        l.borrow_mut().extend(items)
                    }
                }
                b's' => {
                    let v = self.pop()?;
                    let k = self.pop()?;
                    let d = self.top()?.clone();
                    set_items(&d, vec![k, v])?;
                }
                b'u' => {
                    let items = self.pop_mark()?;
                    let d = self.top()?.clone();
                    set_items(&d, items)?;
                }
                0x8f => self.stack.push(Pv::Opaque), // EMPTY_SET
                0x90 => {
                    self.pop_mark()?; // ADDITEMS
                }
                0x91 => {
                    self.pop_mark()?; // FROZENSET
                    self.stack.push(Pv::Opaque)
                }
                b'0' => {
                    self.pop()?;
                }
                b'1' => {
                    self.pop_mark()?;
                }
                b'2' => {
                    let v = self.top()?.clone();
                    self.stack.push(v)
                }
                b'q' => {
                    let k = u64::from(self.u8()?);
                    let v = self.top()?.clone();
                    self.memo.insert(k, v);
                }
                b'r' => {
                    let k = u64::from(u32::from_le_bytes(self.le()?));
                    let v = self.top()?.clone();
                    self.memo.insert(k, v);
                }
                b'p' => {
                    let l = self.line()?;
                    let k = l.parse().map_err(|_| format!("bad PUT {l:?}"))?;
                    let v = self.top()?.clone();
                    self.memo.insert(k, v);
                }
                0x94 => {
                    let k = self.memo.len() as u64;
                    let v = self.top()?.clone();
                    self.memo.insert(k, v);
                }
                b'h' => {
                    let k = u64::from(self.u8()?);
                    let v = self.memo_get(k)?;
                    self.stack.push(v)
                }
                b'j' => {
                    let k = u64::from(u32::from_le_bytes(self.le()?));
                    let v = self.memo_get(k)?;
                    self.stack.push(v)
                }
                b'g' => {
                    let l = self.line()?;
                    let k = l.parse().map_err(|_| format!("bad GET {l:?}"))?;
                    let v = self.memo_get(k)?;
                    self.stack.push(v)
                }
                b'Q' => {
                    let pid = self.pop()?;
                    let v = persistent_load(&pid).map_err(|e| format!("{e} at {at}"))?;
                    self.stack.push(v)
                }
                b'R' => {
                    let args = self.pop()?;
                    let callable = self.pop()?;
                    let v = reduce(&callable, &args).map_err(|e| format!("{e} at {at}"))?;
                    self.stack.push(v)
                }
                0x81 => {
                    // NEWOBJ: cls.__new__(cls, *args)
                    let _args = self.pop()?;
                    let cls = self.pop()?;
                    let v = match &cls {
                        Pv::Global(g) if g.1 == "OrderedDict" || g.1 == "dict" => new_dict(),
                        _ => Pv::Opaque,
                    };
                    self.stack.push(v)
                }
                0x92 => {
                    // NEWOBJ_EX
                    self.pop()?;
                    self.pop()?;
                    self.pop()?;
                    self.stack.push(Pv::Opaque)
                }
                b'b' => {
                    // BUILD: state is applied to the object; irrelevant for tensors and dicts here.
                    self.pop()?;
                }
                _ => return Err(format!("unsupported pickle opcode 0x{op:02x} at byte {at}")),
            }
        }
    }
}

fn set_items(d: &Pv, items: Vec<Pv>) -> Result<(), String> {
    if !items.len().is_multiple_of(2) {
        return Err("odd number of dict items".into());
    }
    if let Pv::Dict(d) = d {
        let mut d = d.borrow_mut();
        let mut it = items.into_iter();
        while let (Some(k), Some(v)) = (it.next(), it.next()) {
            d.push((k, v));
        }
    }
    Ok(())
}

/// `('storage', torch.FloatStorage, key, location, numel)` → storage reference.
fn persistent_load(pid: &Pv) -> Result<Pv, String> {
    let Pv::Tuple(t) = pid else {
        return Err("persistent id is not a tuple".into());
    };
    match (t.first(), t.get(1), t.get(2)) {
        (Some(Pv::Str(tag)), Some(class), Some(Pv::Str(key))) if tag == "storage" => {
            let kind = match class {
                Pv::Global(g) => StorageType::from_class(&g.1)
                    .ok_or_else(|| format!("unsupported storage type {}.{}", g.0, g.1)),
                _ => Err("storage type is not a class".to_string()),
            };
            Ok(Pv::Storage(Rc::new((key.clone(), kind))))
        }
        _ => Err(format!("unsupported persistent id {pid:?}")),
    }
}

fn as_usizes(v: &Pv) -> Result<Vec<usize>, String> {
    match v {
        Pv::Tuple(t) => t
            .iter()
            .map(|x| match x {
                Pv::Int(i) => usize::try_from(*i).map_err(|_| format!("negative size {i}")),
                _ => Err("non-integer size".to_string()),
            })
            .collect(),
        _ => Err("size is not a tuple".into()),
    }
}

fn reduce(callable: &Pv, args: &Pv) -> Result<Pv, String> {
    let Pv::Global(g) = callable else {
        return Ok(Pv::Opaque);
    };
    let empty = Vec::new();
    let args: &[Pv] = match args {
        Pv::Tuple(t) => t,
        _ => &empty,
    };
    match (g.0.as_str(), g.1.as_str()) {
        ("collections", "OrderedDict") | ("builtins", "dict") | ("__builtin__", "dict") => {
            Ok(new_dict())
        }
        ("torch._utils", "_rebuild_tensor_v2") | ("torch._utils", "_rebuild_tensor") => {
            let (Some(Pv::Storage(s)), Some(Pv::Int(offset)), Some(size), Some(stride)) =
                (args.first(), args.get(1), args.get(2), args.get(3))
            else {
                return Err(format!("unexpected arguments to {}", g.1));
            };
            let shape = as_usizes(size)?;
            let stride = as_usizes(stride)?;
            if shape.len() != stride.len() {
                return Err(format!(
                    "size {shape:?} and stride {stride:?} differ in rank"
                ));
            }
            Ok(Pv::Tensor(Rc::new(TensorRef {
                storage: s.0.clone(),
                kind: s.1.clone(),
                offset: usize::try_from(*offset).map_err(|_| "negative storage offset")?,
                shape,
                stride,
            })))
        }
        ("torch._utils", "_rebuild_parameter")
        | ("torch._utils", "_rebuild_parameter_with_state") => match args.first() {
            Some(t @ Pv::Tensor(_)) => Ok(t.clone()),
            _ => Err("parameter without tensor".into()),
        },
        _ => Ok(Pv::Opaque),
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn strided_views_are_gathered_in_c_order() {
        // Storage 0..12 as f32, view = transpose of a [3, 4] matrix starting at offset 0.
        let storage: Vec<u8> = (0..12).flat_map(|i| (i as f32).to_le_bytes()).collect();
        let t = TensorRef {
            storage: "0".into(),
            kind: Ok(StorageType::F32),
            offset: 0,
            shape: vec![4, 3],
            stride: vec![1, 4],
        };
        let d = decode(&t, &storage).unwrap();
        let v = d.to_vec::<f32>().unwrap();
        assert_eq!(v, vec![0., 4., 8., 1., 5., 9., 2., 6., 10., 3., 7., 11.]);
        // Out-of-range view is an error, not a panic.
        let bad = TensorRef {
            offset: 1,
            shape: vec![12],
            stride: vec![1],
            ..t
        };
        assert!(decode(&bad, &storage).is_err());
    }

    #[test]
    fn pickle_errors_do_not_panic() {
        for bytes in [
            &b""[..],
            b"\x80\x02",
            b"\x80\x02X\xff\xff\xff\xff",
            b"\x80\x02t.",
            b"\xff",
        ] {
            assert!(Unpickler::new(bytes).run().is_err());
        }
        // A protocol-2 pickle of {'a': 1, 'b': [2.5]} parses.
        let p = b"\x80\x02}q\x00(X\x01\x00\x00\x00aq\x01K\x01X\x01\x00\x00\x00bq\x02]q\x03G@\x04\x00\x00\x00\x00\x00\x00au.";
        let v = Unpickler::new(p).run().unwrap();
        assert!(matches!(dict_get(&v, "a"), Some(Pv::Int(1))));
        match dict_get(&v, "b") {
            Some(Pv::List(l)) => assert!(matches!(l.borrow()[0], Pv::Float(x) if x == 2.5)),
            other => panic!("{other:?}"),
        }
    }
}
