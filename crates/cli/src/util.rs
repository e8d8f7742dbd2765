//! Small helpers shared by the commands.

use anyhow::{Context, Result};
use std::path::Path;

/// Writes `value` as pretty JSON to `path` atomically (a fresh temporary file beside it, renamed
/// into place: [`occ_data::formats::io::write_atomic`]), so that concurrent writers of one path
/// always leave one complete document.
pub fn write_json<T: serde::Serialize>(path: &Path, value: &T) -> Result<()> {
    let text = serde_json::to_string_pretty(value)?;
    write_file(path, text.as_bytes())
}

/// Writes `bytes` to `path` atomically, creating its folder.
pub fn write_file(path: &Path, bytes: &[u8]) -> Result<()> {
    if let Some(dir) = path.parent() {
        if !dir.as_os_str().is_empty() {
            std::fs::create_dir_all(dir).with_context(|| format!("creating {}", dir.display()))?;
        }
    }
    occ_data::formats::io::write_atomic(path, bytes)?;
    Ok(())
}

/// The `--model` / `--models` values: the three networks, named as in configs and tables
/// ([`occ_model::ModelKind::name`]); `--help` lists them.
#[derive(Clone, Copy, Debug, PartialEq, Eq, clap::ValueEnum)]
pub enum ModelArg {
    /// SparseOcc++.
    #[value(name = "sparseocc++", alias = "sparseocc_pp", alias = "pp")]
    SparseOccPP,
    /// SparseOcc.
    #[value(name = "sparseocc", alias = "so")]
    SparseOcc,
    /// The dense baseline.
    #[value(name = "dense")]
    Dense,
}

impl From<ModelArg> for occ_model::ModelKind {
    fn from(m: ModelArg) -> Self {
        match m {
            ModelArg::SparseOccPP => Self::SparseOccPP,
            ModelArg::SparseOcc => Self::SparseOcc,
            ModelArg::Dense => Self::Dense,
        }
    }
}

impl ModelArg {
    /// The model's name in configs, logs and tables.
    pub fn name(self) -> &'static str {
        occ_model::ModelKind::from(self).name()
    }
}

/// A clap parser of a count that must be at least `min`: `bench --frames 0` timed one frame
/// anyway, `check-backend --frames 1` tested no frame after the warm-up and passed.
pub fn at_least(min: u64) -> clap::builder::RangedU64ValueParser<usize> {
    clap::builder::RangedU64ValueParser::<usize>::new().range(min..)
}

/// A clap parser of a finite number above 0 (a NaN tolerance passes every comparison).
pub fn positive_finite(s: &str) -> Result<f64, String> {
    let v: f64 = s
        .parse()
        .map_err(|e| format!("`{s}` is not a number: {e}"))?;
    if v.is_finite() && v > 0.0 {
        Ok(v)
    } else {
        Err(format!("{v} is not a finite number above 0"))
    }
}

#[cfg(test)]
mod tests {
    use super::ModelArg;
    use clap::ValueEnum;

    #[test]
    fn model_values_parse_and_name_the_model_kinds() {
        for m in ModelArg::value_variants() {
            let name = m.to_possible_value().unwrap().get_name().to_string();
            assert_eq!(name, m.name());
            assert_eq!(ModelArg::from_str(&name, false).unwrap(), *m);
        }
        assert_eq!(
            ModelArg::from_str("pp", false).unwrap(),
            ModelArg::SparseOccPP
        );
        assert!(ModelArg::from_str("resnet", false).is_err());
    }
}
