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

/// A fresh name beside `path` for a temporary file or folder: `.<name>.tmp-<pid>-<n>-<random>`,
/// unique across processes (pid), threads and calls (a process-wide counter), and across pid reuse
/// (random bits). Writers create it, fill it, and rename it over `path`.
pub fn temp_sibling(path: &Path) -> PathBuf {
    use std::hash::{BuildHasher, Hasher};
    use std::sync::atomic::{AtomicU64, Ordering};
    static COUNTER: AtomicU64 = AtomicU64::new(0);
    let n = COUNTER.fetch_add(1, Ordering::Relaxed);
    // `RandomState` is seeded from the OS once per process; mixing in the time and the counter
    // gives different bits on every call.
    let mut h = std::collections::hash_map::RandomState::new().build_hasher();
    h.write_u64(n);
    h.write_u128(
        std::time::SystemTime::now()
            .duration_since(std::time::UNIX_EPOCH)
            .map(|d| d.as_nanos())
            .unwrap_or(0),
    );
    let name = path
        .file_name()
        .map(|n| n.to_string_lossy().into_owned())
        .unwrap_or_else(|| "out".into());
    let tmp = format!(".{name}.tmp-{}-{n}-{:016x}", std::process::id(), h.finish());
    match path.parent() {
        Some(p) => p.join(tmp),
        None => PathBuf::from(tmp),
    }
}

/// True for a name made by [`temp_sibling`] for `name` (`.<name>.tmp-...`).
pub fn is_temp_sibling_of(candidate: &std::ffi::OsStr, name: &str) -> bool {
    candidate
        .to_str()
        .is_some_and(|c| c.starts_with(&format!(".{name}.tmp-")))
}

/// Create `path` atomically: `write` fills a fresh temporary file beside it ([`temp_sibling`]),
/// which is flushed to disk and renamed over `path` only when `write` succeeded; on any failure the
/// temporary file is removed and `path` is left as it was. Concurrent writers of the same `path`
/// never share a temporary file, so `path` is always one writer's complete output.
/// The parent folder must exist.
pub fn write_atomic_io(
    path: &Path,
    write: impl FnOnce(&mut std::fs::File) -> std::io::Result<()>,
) -> std::io::Result<()> {
    if path.file_name().is_none() {
        return Err(std::io::Error::new(
            std::io::ErrorKind::InvalidInput,
            "path has no file name",
        ));
    }
    let tmp = temp_sibling(path);
    let result = (|| -> std::io::Result<()> {
        let mut f = std::fs::OpenOptions::new()
            .write(true)
            .create_new(true)
            .open(&tmp)?;
        write(&mut f)?;
        f.flush()?;
        f.sync_all()?;
        drop(f);
        std::fs::rename(&tmp, path)
    })();
    if result.is_err() {
        let _ = std::fs::remove_file(&tmp);
    }
    result
}

/// Write `bytes` to `path` atomically ([`write_atomic_io`]). The parent folder must exist.
pub fn write_atomic(path: &Path, bytes: &[u8]) -> Result<(), DataError> {
    write_atomic_io(path, |f| f.write_all(bytes)).map_err(|e| DataError::io(path, e))
}

/// Create a folder and its parents.
pub fn create_dir_all(path: &Path) -> Result<(), DataError> {
    std::fs::create_dir_all(path).map_err(|e| DataError::io(path, e))
}
