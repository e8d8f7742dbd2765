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
