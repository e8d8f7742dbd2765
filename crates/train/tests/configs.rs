//! Every shipped run configuration (`configs/*.toml`, discovered by listing the folder) parses,
//! validates, and agrees with its dataset layout.

use occ_train::dataset::DatasetFormat;
use occ_train::RunConfig;
use std::path::Path;

#[test]
fn every_shipped_config_parses_and_validates() {
    let dir = Path::new(env!("CARGO_MANIFEST_DIR")).join("../../configs");
    let mut n = 0;
    for e in std::fs::read_dir(&dir).unwrap() {
        let path = e.unwrap().path();
        if path.extension().and_then(|x| x.to_str()) != Some("toml") {
            continue;
        }
        let cfg = RunConfig::load(&path).unwrap_or_else(|e| panic!("{}: {e}", path.display()));
        let name = path.file_name().unwrap().to_string_lossy().into_owned();
        assert_eq!(
            cfg.model.num_classes,
            cfg.data.format.num_classes(),
            "{name}"
        );
        assert!(!cfg.data.train_sequences.is_empty(), "{name}");
        // The saved form reads back to the same config (run folders store it).
        let again = RunConfig::from_toml(&cfg.to_toml().unwrap(), &name).unwrap();
        assert_eq!(again.to_toml().unwrap(), cfg.to_toml().unwrap(), "{name}");
        if name.starts_with("nuscenes_") {
            assert_eq!(cfg.data.format, DatasetFormat::NuscenesOccupancy, "{name}");
            assert_eq!(cfg.model.full_dims, [512, 512, 40], "{name}");
            assert_eq!((cfg.data.image_width, cfg.data.image_height), (704, 256));
            // The official validation split: 150 distinct scenes; the rest of v1.0-trainval trains.
            let mut v = cfg.data.val_sequences.clone();
            v.sort();
            v.dedup();
            assert_eq!(v.len(), 150, "{name}");
            assert_eq!(cfg.data.train_sequences, vec!["*".to_string()], "{name}");
        }
        n += 1;
    }
    assert!(n >= 6, "only {n} configs in {}", dir.display());
}

/// Bad settings are refused at load time, each with an error naming the file and the key: numbers
/// out of range or not finite, values of the wrong type, and unknown keys at every nesting level.
#[test]
fn bad_settings_are_errors_naming_the_file_and_the_key() {
    let path = Path::new(env!("CARGO_MANIFEST_DIR")).join("../../configs/synthetic_tiny.toml");
    let base = std::fs::read_to_string(&path).unwrap();
    // (what to replace, replacement, substrings the error must contain)
    let cases: &[(&str, &str, &[&str])] = &[
        (
            "clip_norm = 35.0",
            "clip_norm = -1.0",
            &["train.clip_norm", "-1"],
        ),
        (
            "clip_norm = 35.0",
            "clip_norm = nan",
            &["train.clip_norm", "NaN"],
        ),
        ("clip_norm = 35.0", "clip_norm = 0.0", &["train.clip_norm"]),
        (
            "min_lr_ratio = 0.05",
            "min_lr_ratio = nan",
            &["train.min_lr_ratio"],
        ),
        (
            "min_lr_ratio = 0.05",
            "min_lr_ratio = 1.5",
            &["train.min_lr_ratio", "[0, 1]"],
        ),
        ("lr = 3e-3", "lr = inf", &["train.lr", "finite"]),
        ("lr = 3e-3", "lr = -1e-3", &["train.lr"]),
        ("lr = 3e-3", "lr = \"fast\"", &["train.lr", "fast"]),
        (
            "weight_decay = 0.01",
            "weight_decay = nan",
            &["train.weight_decay"],
        ),
        (
            "weight_decay = 0.01",
            "weight_decay = -0.5",
            &["train.weight_decay"],
        ),
        ("steps = 750", "steps = 0", &["train.steps"]),
        ("steps = 750", "steps = -3", &["train.steps"]),
        ("log_every = 5", "log_every = 0", &["train.log_every"]),
        (
            "checkpoint_every = 50",
            "checkpoint_every = 0",
            &["train.checkpoint_every"],
        ),
        ("flip_prob = 0.0", "flip_prob = 1.5", &["data.flip_prob"]),
        (
            "mirror_prob = 0.5",
            "mirror_prob = nan",
            &["data.mirror_prob"],
        ),
        (
            "rot_lim_deg = [0.0, 0.0]",
            "rot_lim_deg = [5.0, -5.0]",
            &["data.rot_lim_deg"],
        ),
        (
            "resize_lim = [0.0, 0.0]",
            "resize_lim = [-1.5, 0.0]",
            &["data.resize_lim"],
        ),
        (
            "val_sequences = [\"08\"]",
            "val_sequences = [\"08\", \"08\"]",
            &["data.val_sequences", "08", "twice"],
        ),
        (
            "dbound = [2.0, 58.0, 1.0]\npropagator",
            "dbound = [2.0, nan, 1.0]\npropagator",
            &["model.sparseocc.dbound[1]", "finite"],
        ),
        (
            "dca_offset_init_scale = 0.25",
            "dca_offset_init_scale = inf",
            &["model.sparseocc_pp.dca_offset_init_scale"],
        ),
        // Unknown keys at every level.
        (
            "embed_dim = 32",
            "embed_dim = 32\nembed_dims = 32",
            &["model.sparseocc_pp.embed_dims", "unknown"],
        ),
        (
            "depth = 18",
            "depth = 18\nwidth = 3",
            &["model.encoder.resnet.width", "unknown"],
        ),
        (
            "out_channels = 32",
            "out_channels = 32\nnorm = 1",
            &["model.encoder.fpn.norm", "unknown"],
        ),
        (
            "num_queries = 20",
            "num_queries = 20\nqueries = 1",
            &["model.sparseocc.queries", "unknown"],
        ),
        (
            "encoder_channels = [32, 32, 32]",
            "encoder_channels = [32, 32, 32]\nlayers = 2",
            &["model.dense.layers", "unknown"],
        ),
        (
            "lss_level = 2",
            "lss_level = 2\nlss_levels = 2",
            &["lss_levels"],
        ),
        ("[train]", "[train]\nlearning_rate = 1", &["learning_rate"]),
        ("[data]", "[data]\nformat2 = 1", &["format2"]),
        ("[data]", "[extra]\nx = 1\n[data]", &["extra"]),
    ];
    for (from, to, want) in cases {
        assert!(base.contains(from), "the base config has no `{from}`");
        let text = base.replacen(from, to, 1);
        let e = match RunConfig::from_toml(&text, "bad-config.toml") {
            Ok(_) => panic!("`{to}` was accepted"),
            Err(e) => e.to_string(),
        };
        assert!(
            e.contains("bad-config.toml"),
            "`{to}`: error without the file: {e}"
        );
        for w in *want {
            assert!(e.contains(w), "`{to}`: error without `{w}`: {e}");
        }
    }
    // The base itself is fine, and a value equal to the default is not mistaken for an unknown key.
    RunConfig::from_toml(&base, "base").unwrap();
    RunConfig::from_toml(
        &base.replace("embed_dim = 32", "embed_dim = 32\nnum_classes = 20"),
        "base",
    )
    .unwrap();
}

/// Which runs read the LiDAR scans is the model config's decision: LSS depth supervision and the
/// SparseOcc++ options that read them in training, only the depth oracle at test time.
#[test]
fn lidar_needs_follow_the_model_config() {
    let base = std::fs::read_to_string(
        Path::new(env!("CARGO_MANIFEST_DIR")).join("../../configs/synthetic_tiny.toml"),
    )
    .unwrap();
    let with = |from: &str, to: &str| {
        assert!(base.contains(from), "{from}");
        RunConfig::from_toml(&base.replacen(from, to, 1), "test").unwrap()
    };
    let pp_opt = |line: &str| {
        with(
            "output = \"SubVoxel\"",
            &format!("output = \"SubVoxel\"\n{line}"),
        )
    };
    let cases = [
        (with("", ""), false, false),
        (
            with("kind = \"sparseocc++\"", "kind = \"sparseocc\""),
            true,
            false,
        ),
        (
            with("kind = \"sparseocc++\"", "kind = \"dense\""),
            true,
            false,
        ),
        (pp_opt("depth_gate = true"), true, false),
        (pp_opt("sem2d_aux = true"), true, false),
        (pp_opt("depth_oracle = true"), true, true),
    ];
    for (i, (cfg, train, test)) in cases.iter().enumerate() {
        assert_eq!(cfg.model.needs_points_for_training(), *train, "case {i}");
        assert_eq!(cfg.model.needs_points_at_test(), *test, "case {i}");
    }
}

/// The `[model]` section resolves to the settings of one model: for every shipped config and each of
/// the three kinds (as `--model` switches them), [`OccNetConfig::variant`] is that kind's section of
/// the file (defaults filled in; the paper defaults without one) with the shared sizes of `[model]`,
/// whatever the other sections hold.
///
/// [`OccNetConfig::variant`]: occ_model::OccNetConfig::variant
#[test]
fn every_shipped_config_resolves_each_kind_to_its_own_section() {
    use occ_model::dense::DenseBaselineConfig;
    use occ_model::sparseocc::SparseOccConfig;
    use occ_model::sparseocc_pp::SparseOccPPConfig;
    use occ_model::{ModelKind, NetworkVariant};
    fn json<T: serde::Serialize>(v: &T) -> serde_json::Value {
        serde_json::to_value(v).unwrap()
    }
    let dir = Path::new(env!("CARGO_MANIFEST_DIR")).join("../../configs");
    for e in std::fs::read_dir(&dir).unwrap() {
        let path = e.unwrap().path();
        if path.extension().and_then(|x| x.to_str()) != Some("toml") {
            continue;
        }
        let cfg = RunConfig::load(&path).unwrap().model;
        let (n, f, dims) = (cfg.num_classes, cfg.encoder.fpn.out_channels, cfg.full_dims);
        for kind in [
            ModelKind::SparseOccPP,
            ModelKind::SparseOcc,
            ModelKind::Dense,
        ] {
            let variant = cfg.with_kind(kind).variant();
            assert_eq!(variant.kind(), kind, "{}", path.display());
            let (got, want) = match variant {
                NetworkVariant::SparseOccPP(c) => {
                    let mut s = (cfg.sparseocc_pp.clone())
                        .unwrap_or_else(|| SparseOccPPConfig::new(n, 128, f, dims));
                    (s.num_classes, s.feat_channels, s.full_dims) = (n, f, dims);
                    s.num_feature_levels = cfg.encoder.resnet.out_indices.len();
                    (json(&c), json(&s))
                }
                NetworkVariant::SparseOcc(c) => {
                    let mut s =
                        (cfg.sparseocc.clone()).unwrap_or_else(|| SparseOccConfig::new(n, f, dims));
                    (s.num_classes, s.feat_channels, s.full_dims) = (n, f, dims);
                    (json(&c), json(&s))
                }
                NetworkVariant::Dense(c) => {
                    let mut s =
                        (cfg.dense.clone()).unwrap_or_else(|| DenseBaselineConfig::new(n, f, dims));
                    (s.num_classes, s.feat_channels, s.full_dims) = (n, f, dims);
                    (json(&c), json(&s))
                }
            };
            assert_eq!(got, want, "{} as {}", path.display(), kind.name());
        }
    }
}

/// `init` builds the model the config names, and its parameters keep the checkpoint paths
/// (`encoder.*` and `pp.*` / `so.*` / `dense.*`) that the run folders' `model.bin` files hold.
#[test]
fn each_kind_builds_its_own_network_under_the_checkpoint_paths() {
    use occ_model::occnet::param_shapes;
    use occ_model::{ModelKind, Network, OccNet};
    type B = burn::backend::NdArray<f32>;
    let path = Path::new(env!("CARGO_MANIFEST_DIR")).join("../../configs/synthetic_tiny.toml");
    let cfg = RunConfig::load(&path).unwrap().model;
    let device = Default::default();
    for (kind, prefix) in [
        (ModelKind::SparseOccPP, "pp."),
        (ModelKind::SparseOcc, "so."),
        (ModelKind::Dense, "dense."),
    ] {
        let net: OccNet<B> = cfg.with_kind(kind).init(&device).unwrap();
        assert_eq!(net.kind(), kind);
        let built = match net.network().unwrap() {
            Network::SparseOccPP(_) => ModelKind::SparseOccPP,
            Network::SparseOcc(_) => ModelKind::SparseOcc,
            Network::Dense(_) => ModelKind::Dense,
        };
        assert_eq!(built, kind);
        let shapes = param_shapes::<B, _>(&net);
        assert!(
            shapes.iter().any(|(p, _)| p.starts_with(prefix)),
            "{prefix}"
        );
        assert!(
            shapes
                .iter()
                .all(|(p, _)| p.starts_with("encoder.") || p.starts_with(prefix)),
            "{:?}",
            shapes.iter().map(|(p, _)| p).collect::<Vec<_>>()
        );
    }
}
