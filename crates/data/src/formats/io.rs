//! File helpers: whole-file reads with typed errors, and atomic writes (temporary name in the
//! same folder, renamed when complete).

use crate::error::DataError;
use std::io::Write;
use std::path::{Path, PathBuf};

/// Read a whole file; a missing file gives [`DataError::NotFound`].
pub fn read_bytes(path: &Path) -> Result<Vec<u8>, DataError> {
    std::fs::read(path).map_err(|e| DataError::io(path, e))
}

/// Read a UTF-8 text file.
pub fn read_text(path: &Path) -> Result<String, DataError> {
    let bytes = read_bytes(path)?;
    String::from_utf8(bytes).map_err(|_| DataError::format(path, "not valid UTF-8 text"))
}

/// Check that a file has exactly `expected` bytes: shorter is [`DataError::Truncated`], longer
/// is [`DataError::WrongSize`].
pub fn check_len(path: &Path, actual: usize, expected: usize) -> Result<(), DataError> {
    if actual < expected {
        return Err(DataError::Truncated {
            path: path.to_path_buf(),
            expected: expected as u64,
            actual: actual as u64,
        });
    }
    if actual > expected {
        return Err(DataError::WrongSize {
            path: path.to_path_buf(),
            detail: format!("expected {expected} bytes, found {actual}"),
        });
    }
    Ok(())
}

fn temp_path(path: &Path) -> PathBuf {
    let name = path
        .file_name()
        .map(|n| n.to_string_lossy().into_owned())
        .unwrap_or_else(|| "out".into());
    let tmp = format!(".{name}.tmp-{}", std::process::id());
    match path.parent() {
        Some(p) => p.join(tmp),
        None => PathBuf::from(tmp),
    }
}

/// Write `bytes` to `path` atomically: write `.<name>.tmp-<pid>` beside it, flush, rename.
/// The parent folder must exist.
pub fn write_atomic(path: &Path, bytes: &[u8]) -> Result<(), DataError> {
    let tmp = temp_path(path);
    let result = (|| -> std::io::Result<()> {
        let mut f = std::fs::File::create(&tmp)?;
        f.write_all(bytes)?;
        f.sync_all()?;
        Ok(())
    })();
    if let Err(e) = result {
        let _ = std::fs::remove_file(&tmp);
        return Err(DataError::io(path, e));
    }
    std::fs::rename(&tmp, path).map_err(|e| {
        let _ = std::fs::remove_file(&tmp);
        DataError::io(path, e)
    })
}

/// Create a folder and its parents.
pub fn create_dir_all(path: &Path) -> Result<(), DataError> {
    std::fs::create_dir_all(path).map_err(|e| DataError::io(path, e))
}
