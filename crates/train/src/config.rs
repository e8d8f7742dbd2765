//! Run configuration files (`configs/*.toml`): `[model]` ([`OccNetConfig`]), `[train]`
//! ([`TrainConfig`]) and `[data]` ([`DataConfig`]).

/// The demo's built-in run configuration (`configs/synthetic_tiny.toml`, built into the binary).
pub const SYNTHETIC_TINY: &str = include_str!("../../../configs/synthetic_tiny.toml");

use crate::dataset::DatasetFormat;
use crate::trainer::TrainConfig;
use crate::TrainError;
use occ_data::image::ImagePipelineConfig;
use occ_model::OccNetConfig;
use serde::{Deserialize, Serialize};
use std::path::Path;

/// Input pipeline settings.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct DataConfig {
    /// Dataset layout: `semantic_kitti` (default; one front camera), `occ3d` (Occ3D-nuScenes
    /// `gts/` + nuScenes tables and six cameras) or `nuscenes_occupancy` (OpenOccupancy GT +
    /// nuScenes tables and six cameras).
    #[serde(default)]
    pub format: DatasetFormat,
    /// Ground-truth folder below the data root (default `gts` for Occ3D, `nuScenes-Occupancy` for
    /// nuScenes-Occupancy; unused for SemanticKITTI).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub gt_dir: Option<String>,
    /// nuScenes table folder below the data root (default: the synthetic data's, else the first
    /// of `v1.0-trainval`, `v1.0-mini`, `v1.0-test` that exists).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub nuscenes_version: Option<String>,
    /// Network input width (SemanticKITTI: 1280).
    pub image_width: usize,
    /// Network input height (SemanticKITTI: 384).
    pub image_height: usize,
    /// Training sequences (SemanticKITTI: 00-07, 09, 10), or scene names for the nuScenes layouts,
    /// where `"*"` stands for every scene not listed in `val_sequences`.
    #[serde(default)]
    pub train_sequences: Vec<String>,
    /// Validation sequences (SemanticKITTI: 08), or nuScenes scene names.
    #[serde(default)]
    pub val_sequences: Vec<String>,
    /// Training augmentation: resize offset range added to `image_width / W`.
    #[serde(default = "resize_lim")]
    pub resize_lim: (f64, f64),
    /// Training augmentation: horizontal flip probability.
    #[serde(default = "flip")]
    pub flip_prob: f64,
    /// Training augmentation: rotation range (degrees).
    #[serde(default = "rot")]
    pub rot_lim_deg: (f64, f64),
    /// Training augmentation: probability of mirroring the whole sample across the grid's x-z centre
    /// plane (image flipped, cameras re-folded, labels along y, LiDAR points; MonoScene's `fliplr`,
    /// `crate::mirror`). Default 0 (off); applied only when `train.augment` is on.
    #[serde(default)]
    pub mirror_prob: f64,
    /// Training augmentation: translate the whole sample in the ground plane by a whole number of
    /// voxels drawn uniformly within `±(x, y)` (labels moved, cameras re-folded, image unchanged;
    /// BEVDet's BEV augmentation, `crate::shift`). Default `(0, 0)` (off); applied only when
    /// `train.augment` is on.
    #[serde(default)]
    pub shift_voxels: (usize, usize),
    /// Test-time mirror augmentation in validation and `infer`: average the class probabilities of
    /// each frame and its mirror image (`crate::infer::predict_sample`). Default off.
    #[serde(default)]
    pub test_mirror: bool,
}

fn resize_lim() -> (f64, f64) {
    (-0.06, 0.11)
}
fn flip() -> f64 {
    0.5
}
fn rot() -> (f64, f64) {
    (-5.4, 5.4)
}

impl DataConfig {
    /// The image pipeline these settings describe.
    pub fn pipeline(&self) -> ImagePipelineConfig {
        ImagePipelineConfig {
            out_width: self.image_width,
            out_height: self.image_height,
            resize_lim: self.resize_lim,
            flip_prob: self.flip_prob,
            rot_lim_deg: self.rot_lim_deg,
        }
    }
}

impl DataConfig {
    /// Checks the augmentation settings and the sequence lists.
    pub fn validate(&self) -> Result<(), String> {
        for (key, v) in [
            ("flip_prob", self.flip_prob),
            ("mirror_prob", self.mirror_prob),
        ] {
            if !(0.0..=1.0).contains(&v) {
                return Err(format!("data.{key} = {v}: must be a probability in [0, 1]"));
            }
        }
        for (key, (lo, hi)) in [
            ("resize_lim", self.resize_lim),
            ("rot_lim_deg", self.rot_lim_deg),
        ] {
            if !(lo.is_finite() && hi.is_finite() && lo <= hi) {
                return Err(format!(
                    "data.{key} = [{lo}, {hi}]: must be two finite numbers, the first not above the second"
                ));
            }
        }
        if self.resize_lim.0 <= -1.0 {
            return Err(format!(
                "data.resize_lim = [{}, {}]: the lower end must be above -1 (a positive scale)",
                self.resize_lim.0, self.resize_lim.1
            ));
        }
        for (key, list) in [
            ("train_sequences", &self.train_sequences),
            ("val_sequences", &self.val_sequences),
        ] {
            for (i, a) in list.iter().enumerate() {
                if a.trim().is_empty() {
                    return Err(format!("data.{key}: entry {} is empty", i + 1));
                }
                if list[..i].contains(a) {
                    return Err(format!("data.{key}: `{a}` is listed twice"));
                }
            }
        }
        Ok(())
    }
}

/// Every float in `v` finite; the error names the key (`train.lr`, `model.dense.dbound[1]`).
fn check_finite(v: &toml::Value, path: &str) -> Result<(), String> {
    match v {
        toml::Value::Float(f) if !f.is_finite() => {
            Err(format!("{path} = {f}: must be a finite number"))
        }
        toml::Value::Table(t) => {
            for (k, x) in t {
                let p = if path.is_empty() {
                    k.clone()
                } else {
                    format!("{path}.{k}")
                };
                check_finite(x, &p)?;
            }
            Ok(())
        }
        toml::Value::Array(a) => {
            for (i, x) in a.iter().enumerate() {
                check_finite(x, &format!("{path}[{i}]"))?;
            }
            Ok(())
        }
        _ => Ok(()),
    }
}

/// Every key of `user` (recursively) is also in `known`, the parsed config written back.
fn check_known_keys(user: &toml::Table, known: &toml::Table, path: &str) -> Result<(), String> {
    for (k, v) in user {
        let p = if path.is_empty() {
            k.clone()
        } else {
            format!("{path}.{k}")
        };
        let Some(kv) = known.get(k) else {
            let section = if path.is_empty() {
                "the top level".to_string()
            } else {
                format!("[{path}]")
            };
            let mut keys: Vec<&str> = known.keys().map(String::as_str).collect();
            keys.sort_unstable();
            return Err(format!(
                "unknown key `{p}` (in {section}: expected one of {})",
                keys.join(", ")
            ));
        };
        if let (toml::Value::Table(u), toml::Value::Table(kt)) = (v, kv) {
            check_known_keys(u, kt, &p)?;
        }
    }
    Ok(())
}

/// Merges `user` over `defaults` (tables recursively; any other value replaces).
fn merge(defaults: &mut toml::Table, user: &toml::Table) {
    for (k, v) in user {
        match (defaults.get_mut(k), v) {
            (Some(toml::Value::Table(d)), toml::Value::Table(u)) => merge(d, u),
            _ => {
                defaults.insert(k.clone(), v.clone());
            }
        }
    }
}

fn to_table<T: Serialize>(v: &T) -> Result<toml::Table, String> {
    toml::Table::try_from(v).map_err(|e| e.to_string())
}

/// Fills the model sub-sections of a parsed config with their defaults (see [`RunConfig::from_toml`]).
fn fill_model_defaults(root: &mut toml::Table) -> Result<(), String> {
    use occ_model::dense::DenseBaselineConfig;
    use occ_model::encoder::backbone::ResNetConfig;
    use occ_model::encoder::fpn::FpnConfig;
    use occ_model::sparseocc::SparseOccConfig;
    use occ_model::sparseocc_pp::SparseOccPPConfig;
    let Some(toml::Value::Table(model)) = root.get_mut("model") else {
        return Err("missing [model] section".into());
    };
    let num_classes = model
        .get("num_classes")
        .and_then(|v| v.as_integer())
        .ok_or("model.num_classes is missing")? as usize;
    let dims: Vec<usize> = model
        .get("full_dims")
        .and_then(|v| v.as_array())
        .map(|a| {
            a.iter()
                .filter_map(|x| x.as_integer())
                .map(|x| x as usize)
                .collect()
        })
        .unwrap_or_default();
    let full_dims: [usize; 3] = dims
        .try_into()
        .map_err(|_| "model.full_dims must be three integers".to_string())?;
    let mut encoder = toml::Table::new();
    encoder.insert(
        "resnet".into(),
        toml::Value::Table(to_table(&ResNetConfig::new())?),
    );
    encoder.insert(
        "fpn".into(),
        toml::Value::Table(to_table(&FpnConfig::new())?),
    );
    if let Some(toml::Value::Table(u)) = model.get("encoder") {
        merge(&mut encoder, u);
    }
    let feat = encoder
        .get("fpn")
        .and_then(|f| f.get("out_channels"))
        .and_then(|v| v.as_integer())
        .unwrap_or(256) as usize;
    model.insert("encoder".into(), toml::Value::Table(encoder));
    let sections = [
        (
            "sparseocc_pp",
            to_table(&SparseOccPPConfig::new(num_classes, 128, feat, full_dims))?,
        ),
        (
            "sparseocc",
            to_table(&SparseOccConfig::new(num_classes, feat, full_dims))?,
        ),
        (
            "dense",
            to_table(&DenseBaselineConfig::new(num_classes, feat, full_dims))?,
        ),
    ];
    for (name, mut defaults) in sections {
        if let Some(toml::Value::Table(u)) = model.get(name) {
            merge(&mut defaults, u);
            model.insert(name.into(), toml::Value::Table(defaults));
        }
    }
    Ok(())
}

/// A whole run configuration.
#[derive(Clone, Debug, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct RunConfig {
    /// The network.
    pub model: OccNetConfig,
    /// Optimisation.
    pub train: TrainConfig,
    /// Inputs.
    pub data: DataConfig,
}

impl RunConfig {
    /// Parses TOML text; `origin` names the source in errors.
    ///
    /// The model sub-sections (`[model.encoder.resnet]`, `[model.encoder.fpn]`,
    /// `[model.sparseocc_pp]`, `[model.sparseocc]`, `[model.dense]`) need only the fields that differ
    /// from the paper defaults: they are merged over the defaults, and the shared sizes
    /// (`num_classes`, `full_dims`, feature channels) come from `[model]`.
    ///
    /// Every key is checked, at every level: an unknown key (also inside the model sub-sections), a
    /// value of the wrong type, a number that is not finite (`nan`, `inf`) or out of its range is an
    /// error naming the key and `origin`.
    pub fn from_toml(text: &str, origin: &str) -> Result<Self, TrainError> {
        let err = |e: String| TrainError::Config(format!("{origin}: {e}"));
        let user: toml::Table = toml::from_str(text).map_err(|e| err(e.to_string()))?;
        check_finite(&toml::Value::Table(user.clone()), "").map_err(err)?;
        let mut value = user.clone();
        fill_model_defaults(&mut value).map_err(err)?;
        let cfg: RunConfig =
            serde_path_to_error::deserialize(toml::Value::Table(value)).map_err(|e| {
                let path = e.path().to_string();
                let inner = e.into_inner().to_string();
                // toml repeats the key on a line `in \`train.lr\``: the path above says it.
                let inner = inner
                    .lines()
                    .map(str::trim)
                    .filter(|l| !l.is_empty() && !l.starts_with("in `"))
                    .collect::<Vec<_>>()
                    .join("; ");
                err(if path == "." || path.is_empty() {
                    inner.to_string()
                } else {
                    format!("{path}: {inner}")
                })
            })?;
        // Keys the types above do not have are dropped by deserialization where a section has no
        // `deny_unknown_fields` (the model sub-sections): every key given must survive a round trip.
        let back = to_table(&cfg).map_err(err)?;
        check_known_keys(&user, &back, "").map_err(err)?;
        cfg.validate().map_err(err)?;
        Ok(cfg)
    }

    /// Reads and validates a config file.
    pub fn load(path: &Path) -> Result<Self, TrainError> {
        let text = std::fs::read_to_string(path).map_err(|source| TrainError::Io {
            path: path.to_path_buf(),
            source,
        })?;
        Self::from_toml(&text, &path.display().to_string())
    }

    /// The config as TOML (saved into every run folder, read back by `infer`).
    pub fn to_toml(&self) -> Result<String, TrainError> {
        toml::to_string_pretty(self).map_err(|e| TrainError::Config(e.to_string()))
    }

    /// Checks sizes (model, and the image size against the encoder strides), the training settings
    /// ([`TrainConfig::validate`]) and the data settings (probabilities in [0, 1], ranges ordered,
    /// no sequence listed twice).
    pub fn validate(&self) -> Result<(), String> {
        check_finite(&toml::Value::Table(to_table(self)?), "")?;
        self.train.validate()?;
        self.data.validate()?;
        self.model.validate().map_err(|e| e.to_string())?;
        let classes = self.data.format.num_classes();
        if self.model.num_classes != classes {
            return Err(format!(
                "model.num_classes is {} but data.format `{}` has {classes} training classes (0 = empty)",
                self.model.num_classes,
                self.data.format.name()
            ));
        }
        if self.data.image_width < 32 || self.data.image_height < 32 {
            return Err(format!(
                "data: image {}x{} is too small (at least 32x32)",
                self.data.image_width, self.data.image_height
            ));
        }
        Ok(())
    }
}
