//! The whole network: image encoder (ResNet + FPN, [`crate::encoder::fpn`]) in front of one of the three
//! occupancy models — SparseOcc++ (paper Sec. 4), SparseOcc (paper Sec. 3) or the dense baseline (the
//! paper's "all modules disabled" row) — with their training losses. This is what training, inference
//! and the benchmark run, through the [`OccNetwork`] interface.
//!
//! The configuration is plain serde (the `[model]` section of a TOML config): the shared sizes
//! (`num_classes`, `full_dims`) are given once and copied into the sub-configurations, whose own
//! fields all have the paper's defaults.

use crate::batch::Batch;
use crate::dense::{DenseBaseline, DenseBaselineConfig};
use crate::encoder::fpn::{ImageEncoder, ImageEncoderConfig};
use crate::error::ModelError;
use crate::kernels::ModelBackend;
use crate::loss::sparseocc_class_weights;
use crate::network::OccNetwork;
use crate::output::ModelOutput;
use crate::profile::Stage;
use crate::sparseocc::{SparseOcc, SparseOccConfig};
use crate::sparseocc_pp::{SparseOccPP, SparseOccPPConfig};
use burn::prelude::*;
use serde::{Deserialize, Serialize};

/// Which occupancy model sits behind the image encoder.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
pub enum ModelKind {
    /// SparseOcc++ (paper Sec. 4).
    #[serde(rename = "sparseocc++")]
    SparseOccPP,
    /// SparseOcc (paper Sec. 3).
    #[serde(rename = "sparseocc")]
    SparseOcc,
    /// LSS + dense 3D conv encoder + linear head.
    #[serde(rename = "dense")]
    Dense,
}

impl ModelKind {
    /// Parses `sparseocc++`, `sparseocc` or `dense`.
    pub fn parse(s: &str) -> Result<Self, ModelError> {
        match s {
            "sparseocc++" | "sparseocc_pp" | "pp" => Ok(Self::SparseOccPP),
            "sparseocc" | "so" => Ok(Self::SparseOcc),
            "dense" => Ok(Self::Dense),
            _ => Err(ModelError::Config(format!(
                "unknown model '{s}' (sparseocc++, sparseocc or dense)"
            ))),
        }
    }

    /// The name used in configs, logs and benchmark tables.
    pub fn name(self) -> &'static str {
        match self {
            Self::SparseOccPP => "sparseocc++",
            Self::SparseOcc => "sparseocc",
            Self::Dense => "dense",
        }
    }
}

/// The chosen model's settings with the shared sizes filled in: what [`OccNetConfig::variant`] resolves
/// the `[model]` section to, and what [`OccNetConfig::init`] builds. One value holds exactly one model's
/// settings, so code that reads a model's settings matches on the model it reads them for.
#[derive(Clone, Debug)]
pub enum NetworkVariant {
    /// SparseOcc++ (paper Sec. 4).
    SparseOccPP(SparseOccPPConfig),
    /// SparseOcc (paper Sec. 3).
    SparseOcc(SparseOccConfig),
    /// The dense baseline.
    Dense(DenseBaselineConfig),
}

impl NetworkVariant {
    /// Which model this is.
    pub fn kind(&self) -> ModelKind {
        match self {
            Self::SparseOccPP(_) => ModelKind::SparseOccPP,
            Self::SparseOcc(_) => ModelKind::SparseOcc,
            Self::Dense(_) => ModelKind::Dense,
        }
    }

    /// Whether training reads the LiDAR scans: the depth supervision of SparseOcc's and the dense
    /// baseline's LSS, and SparseOcc++'s options that read them
    /// ([`SparseOccPPConfig::reads_points_in_training`]).
    pub fn needs_points_for_training(&self) -> bool {
        match self {
            Self::SparseOccPP(pp) => pp.reads_points_in_training(),
            Self::SparseOcc(_) | Self::Dense(_) => true,
        }
    }

    /// Whether inference reads the LiDAR scan: only SparseOcc++'s oracle diagnostics do
    /// ([`SparseOccPPConfig::reads_points_at_test`]); they are no camera-only models.
    pub fn needs_points_at_test(&self) -> bool {
        match self {
            Self::SparseOccPP(pp) => pp.reads_points_at_test(),
            Self::SparseOcc(_) | Self::Dense(_) => false,
        }
    }
}

/// Configuration of [`OccNet`] (the `[model]` section of a config file), in its on-disk form.
///
/// `kind` chooses the model; the per-model sections (`[model.sparseocc_pp]`, `[model.sparseocc]`,
/// `[model.dense]`) may stand side by side, so that one file serves all three (`--model` switches
/// `kind`, the benchmark runs each). Code reads the chosen model's settings through
/// [`Self::variant`] only.
#[derive(Clone, Debug, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct OccNetConfig {
    /// Which model.
    pub kind: ModelKind,
    /// Classes including empty (class 0): 20 for SemanticKITTI.
    pub num_classes: usize,
    /// Full-resolution label grid `[X, Y, Z]` (256x256x32 for SemanticKITTI).
    pub full_dims: [usize; 3],
    /// Backbone and FPN.
    pub encoder: ImageEncoderConfig,
    /// For SparseOcc and the dense baseline, which encoder output level feeds the LSS (index into
    /// the encoder's `out_indices`; the official stride is 16, i.e. level 2 of `[0, 1, 2, 3]`).
    /// SparseOcc++ uses every level.
    #[serde(default = "default_lss_level")]
    pub lss_level: usize,
    /// Per-class loss weights (`num_classes` values). Default: SparseOcc's `(1/ln f)/(1/ln f_0)` for
    /// the 20 SemanticKITTI classes, uniform otherwise.
    #[serde(default)]
    pub class_weights: Option<Vec<f64>>,
    /// SparseOcc++ settings (`num_classes`, `feat_channels`, `full_dims`, `num_feature_levels` are
    /// overwritten from the fields above).
    #[serde(default)]
    pub sparseocc_pp: Option<SparseOccPPConfig>,
    /// SparseOcc settings (shared sizes overwritten likewise).
    #[serde(default)]
    pub sparseocc: Option<SparseOccConfig>,
    /// Dense-baseline settings (shared sizes overwritten likewise).
    #[serde(default)]
    pub dense: Option<DenseBaselineConfig>,
}

fn default_lss_level() -> usize {
    2
}

impl OccNetConfig {
    /// The per-class loss weights.
    pub fn class_weights(&self) -> Result<Vec<f64>, ModelError> {
        let w = match &self.class_weights {
            Some(w) => w.clone(),
            None if self.num_classes == 20 => sparseocc_class_weights().to_vec(),
            None => vec![1.0; self.num_classes],
        };
        if w.len() != self.num_classes || w.iter().any(|v| !v.is_finite() || *v < 0.0) {
            return Err(ModelError::Config(format!(
                "class_weights: need {} finite non-negative values, got {w:?}",
                self.num_classes
            )));
        }
        Ok(w)
    }

    fn feat_channels(&self) -> usize {
        self.encoder.fpn.out_channels
    }

    /// The settings of the model `kind` chooses, from its section (or the paper defaults when the
    /// section is absent), with the shared sizes filled in.
    pub fn variant(&self) -> NetworkVariant {
        let (n, f, dims) = (self.num_classes, self.feat_channels(), self.full_dims);
        // A section (or the default) with the shared sizes: the three configs are distinct types
        // with the same three size fields.
        macro_rules! sized {
            ($section:expr, $default:expr) => {{
                let mut c = $section.clone().unwrap_or_else(|| $default);
                (c.num_classes, c.feat_channels, c.full_dims) = (n, f, dims);
                c
            }};
        }
        match self.kind {
            ModelKind::SparseOccPP => {
                let mut c = sized!(self.sparseocc_pp, SparseOccPPConfig::new(n, 128, f, dims));
                c.num_feature_levels = self.encoder.resnet.out_indices.len();
                NetworkVariant::SparseOccPP(c)
            }
            ModelKind::SparseOcc => {
                NetworkVariant::SparseOcc(sized!(self.sparseocc, SparseOccConfig::new(n, f, dims)))
            }
            ModelKind::Dense => {
                NetworkVariant::Dense(sized!(self.dense, DenseBaselineConfig::new(n, f, dims)))
            }
        }
    }

    /// Whether training needs the LiDAR scans ([`NetworkVariant::needs_points_for_training`]).
    pub fn needs_points_for_training(&self) -> bool {
        self.variant().needs_points_for_training()
    }

    /// Whether inference reads the LiDAR scan ([`NetworkVariant::needs_points_at_test`]).
    pub fn needs_points_at_test(&self) -> bool {
        self.variant().needs_points_at_test()
    }

    /// The same configuration for another model kind (the benchmark runs all three).
    pub fn with_kind(&self, kind: ModelKind) -> Self {
        Self {
            kind,
            ..self.clone()
        }
    }

    /// Checks sizes and switches without building anything.
    pub fn validate(&self) -> Result<(), ModelError> {
        if self.num_classes < 2 || self.full_dims.iter().any(|&d| d == 0 || d % 8 != 0) {
            return Err(ModelError::Config(format!(
                "model: num_classes {} (need >= 2), full_dims {:?} (each a positive multiple of 8)",
                self.num_classes, self.full_dims
            )));
        }
        self.encoder.resnet.validate()?;
        self.class_weights()?;
        let variant = self.variant();
        if !matches!(variant, NetworkVariant::SparseOccPP(_))
            && self.lss_level >= self.encoder.resnet.out_indices.len()
        {
            return Err(ModelError::Config(format!(
                "model: lss_level {} but the encoder has {} output levels",
                self.lss_level,
                self.encoder.resnet.out_indices.len()
            )));
        }
        match variant {
            NetworkVariant::SparseOccPP(c) => c.validate(),
            NetworkVariant::SparseOcc(_) | NetworkVariant::Dense(_) => Ok(()),
        }
    }

    /// Builds the network.
    pub fn init<B: ModelBackend>(&self, device: &B::Device) -> Result<OccNet<B>, ModelError> {
        self.validate()?;
        let encoder = self.encoder.init(device)?;
        let variant = self.variant();
        let (mut pp, mut so, mut dense) = (None, None, None);
        match &variant {
            NetworkVariant::SparseOccPP(c) => pp = Some(c.try_init(device)?),
            NetworkVariant::SparseOcc(c) => so = Some(c.init(device)?),
            NetworkVariant::Dense(c) => dense = Some(c.init(device)?),
        }
        Ok(OccNet {
            encoder,
            pp,
            so,
            dense,
            kind: self.kind,
            class_weights: self.class_weights()?,
            lss_level: self.lss_level,
            num_classes: self.num_classes,
        })
    }
}

/// The occupancy model behind an [`OccNet`]'s encoder ([`OccNet::network`]).
#[derive(Clone, Copy, Debug)]
pub enum Network<'a, B: Backend> {
    /// SparseOcc++.
    SparseOccPP(&'a SparseOccPP<B>),
    /// SparseOcc.
    SparseOcc(&'a SparseOcc<B>),
    /// The dense baseline.
    Dense(&'a DenseBaseline<B>),
}

/// Image encoder + occupancy model, built by [`OccNetConfig::init`] only; [`Self::network`] gives the
/// model.
///
/// The model is kept in three optional fields, exactly one of them present (the one of `kind`),
/// because they are the checkpoint format: the record is `encoder`, then `pp`, `so` and
/// `dense` as options (burn's `BinFileRecorder` writes them in this order, so an enum here would no
/// longer read the checkpoints of existing run folders). Parameter paths are `encoder.backbone.*`,
/// `encoder.neck.*` and `pp.*` / `so.*` / `dense.*`.
#[derive(Module, Debug)]
pub struct OccNet<B: Backend> {
    /// ResNet + FPN.
    pub encoder: ImageEncoder<B>,
    pp: Option<SparseOccPP<B>>,
    so: Option<SparseOcc<B>>,
    dense: Option<DenseBaseline<B>>,
    kind: ModelKind,
    class_weights: Vec<f64>,
    lss_level: usize,
    num_classes: usize,
}

impl<B: ModelBackend> OccNet<B> {
    /// Which model this is.
    pub fn kind(&self) -> ModelKind {
        self.kind
    }

    /// `sparseocc++`, `sparseocc` or `dense`.
    pub fn kind_name(&self) -> &'static str {
        self.kind().name()
    }

    /// The occupancy model (the one `kind` names; [`OccNetConfig::init`] builds it, loading a
    /// checkpoint keeps it).
    pub fn network(&self) -> Result<Network<'_, B>, ModelError> {
        let missing = || ModelError::Config(format!("OccNet holds no {} model", self.kind_name()));
        Ok(match self.kind {
            ModelKind::SparseOccPP => Network::SparseOccPP(self.pp.as_ref().ok_or_else(missing)?),
            ModelKind::SparseOcc => Network::SparseOcc(self.so.as_ref().ok_or_else(missing)?),
            ModelKind::Dense => Network::Dense(self.dense.as_ref().ok_or_else(missing)?),
        })
    }

    /// Runs encoder and model; with targets in the batch, also the loss terms.
    ///
    /// # Shapes
    /// - `batch.images`: `[B, V, 3, H, W]` → `ModelOutput::logits` `[N, num_classes]` on `N` sites of
    ///   `out_dims` (1/2 resolution, `upsample = 2` with the default settings)
    pub fn forward(&self, batch: &Batch<B>) -> Result<ModelOutput<B>, ModelError> {
        let [b, v, c, h, w] = batch.images.dims();
        if c != 3 || h == 0 || w == 0 {
            return Err(ModelError::Input(format!(
                "images are {:?}, expected [B, V, 3, H, W]",
                batch.images.dims()
            )));
        }
        let network = self.network()?;
        let images = batch.images.clone().reshape([b * v, c, h, w]);
        crate::profile::start();
        let feats = self.encoder.forward(images);
        if let Some(f) = feats.last() {
            crate::profile::mark(Stage::Encoder, f);
        }
        let strides = self.encoder.strides();
        let with_loss = batch.target.is_some();
        let cw = &self.class_weights;
        // SparseOcc and the dense baseline lift one encoder level.
        let lss_input = |feats: Vec<Tensor<B, 4>>| {
            let lvl = self.lss_level.min(feats.len().saturating_sub(1));
            let f = feats.into_iter().nth(lvl).ok_or_else(|| {
                ModelError::Config("the image encoder returned no feature level".into())
            })?;
            Ok::<_, ModelError>((f, strides[lvl]))
        };
        let mut out = match network {
            Network::SparseOccPP(pp) => {
                let o = pp.forward(&feats, &strides, batch)?;
                let losses = if with_loss {
                    o.losses(batch, pp.config(), cw)?
                } else {
                    Vec::new()
                };
                ModelOutput { losses, ..o.out }
            }
            Network::SparseOcc(so) => {
                let (f, stride) = lss_input(feats)?;
                let o = so.forward(f, stride, batch)?;
                let losses = if with_loss {
                    o.losses(batch, cw)?
                } else {
                    Vec::new()
                };
                ModelOutput { losses, ..o.out }
            }
            Network::Dense(dense) => {
                let (f, stride) = lss_input(feats)?;
                let o = dense.forward(f, stride, batch)?;
                let losses = if with_loss {
                    o.losses(batch, cw)?
                } else {
                    Vec::new()
                };
                ModelOutput { losses, ..o.out }
            }
        };
        out.stats
            .insert(0, ("image_pixels".to_string(), b * v * h * w));
        Ok(out)
    }
}

impl<B: ModelBackend> OccNetwork<B> for OccNet<B> {
    fn forward_batch(&self, batch: &Batch<B>) -> Result<ModelOutput<B>, ModelError> {
        self.forward(batch)
    }

    fn num_classes(&self) -> usize {
        self.num_classes
    }
}

/// Float parameter shapes of a module, by path (`encoder.backbone.conv1.weight`, ...).
pub fn param_shapes<B: Backend, M: Module<B>>(module: &M) -> Vec<(String, Vec<usize>)> {
    struct Shapes {
        path: Vec<String>,
        out: Vec<(String, Vec<usize>)>,
    }
    impl<B: Backend> burn::module::ModuleVisitor<B> for Shapes {
        fn enter_module(&mut self, name: &str, _container_type: &str) {
            self.path.push(name.to_string());
        }
        fn exit_module(&mut self, _name: &str, _container_type: &str) {
            self.path.pop();
        }
        fn visit_float<const D: usize>(&mut self, param: &burn::module::Param<Tensor<B, D>>) {
            self.out
                .push((self.path.join("."), param.lazy_shape().to_vec()));
        }
    }
    let mut v = Shapes {
        path: Vec::new(),
        out: Vec::new(),
    };
    module.visit(&mut v);
    v.out
}

/// Loads a checkpoint written by `save_file` into `fresh` (a model built from the checkpoint's
/// config) and checks that every parameter kept its shape: burn's recorder itself accepts tensors of
/// any shape, so a config that no longer matches its weights would otherwise fail later, obscurely.
pub fn load_checked<B: Backend, M: Module<B>>(
    fresh: M,
    path: &std::path::Path,
    device: &B::Device,
) -> Result<M, ModelError> {
    use burn::record::{BinFileRecorder, FullPrecisionSettings};
    let expected = param_shapes::<B, M>(&fresh);
    let loaded = fresh
        .load_file(
            path.to_path_buf(),
            &BinFileRecorder::<FullPrecisionSettings>::new(),
            device,
        )
        .map_err(|e| ModelError::Config(format!("{}: {e}", path.display())))?;
    let got = param_shapes::<B, M>(&loaded);
    if got.len() != expected.len() {
        return Err(ModelError::Config(format!(
            "{}: {} parameters, the config builds {}",
            path.display(),
            got.len(),
            expected.len()
        )));
    }
    for ((name, e), (_, g)) in expected.iter().zip(&got) {
        if e != g {
            return Err(ModelError::Config(format!(
                "{}: parameter {name} is {g:?} in the checkpoint but {e:?} in the config",
                path.display()
            )));
        }
    }
    Ok(loaded)
}
