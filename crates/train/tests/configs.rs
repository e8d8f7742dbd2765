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
