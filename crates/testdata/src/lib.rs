//! Where the tests find the external reference data, in one place for the whole workspace.
//!
//! Two folders live beside the repository, never inside it (they hold third-party sample files and
//! reference outputs of PyTorch / spconv that a clone does not ship):
//!
//! | folder | variable | default |
//! |---|---|---|
//! | reference fixtures (`reference/`, `spconv/`, each with a `manifest.json`) | `SPARSEOCC_FIXTURES` | `<repo>/../shared/fixtures` |
//! | real dataset samples (`semantickitti/`, `occ3d/`) | `SPARSEOCC_REALDATA` | `<repo>/../shared/realdata` |
//!
//! A test that needs one calls [`fixtures`] or [`realdata`] once, at its start:
//!
//! ```no_run
//! let Some(dir) = occ_testdata::fixtures() else { return };
//! ```
//!
//! When the folder exists the test runs on it (and discovers its cases there). When it does not:
//! - with `SPARSEOCC_REQUIRE_DATA` set (to anything but `0` or empty; `.ci/run` sets it), the call
//!   panics, so the test fails and names the folder;
//! - when the variable (`SPARSEOCC_FIXTURES` / `SPARSEOCC_REALDATA`) was set explicitly to a path
//!   that is not a folder, the call panics too (a typo must not turn into a skip);
//! - otherwise (a fresh clone with nothing beside it) it writes one line
//!   `skipped: <test>: SPARSEOCC_FIXTURES folder <path> not found ...` to the process's standard
//!   error, past the test harness's output capture so that it shows in a plain `cargo test`, and
//!   returns `None`: the test returns early and counts as passed.
//!
//! The line is written once per test (several lookups in one test print once).
//!
//! Besides, small helpers the crates' tests share: [`TempDir`] (a temporary folder removed on
//! drop), [`read_npy`] (a fixture array with its shape), [`png_claiming_size`] (a PNG whose header
//! lies about its size).

use std::collections::HashSet;
use std::io::Write;
use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicUsize, Ordering};
use std::sync::Mutex;

/// Variable naming the fixtures folder.
pub const FIXTURES_VAR: &str = "SPARSEOCC_FIXTURES";
/// Variable naming the real-data folder.
pub const REALDATA_VAR: &str = "SPARSEOCC_REALDATA";
/// Variable that turns a missing folder into a test failure.
pub const REQUIRE_VAR: &str = "SPARSEOCC_REQUIRE_DATA";

/// One of the two external test-data folders.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Folder {
    /// Reference outputs (`SPARSEOCC_FIXTURES`, default `<repo>/../shared/fixtures`).
    Fixtures,
    /// Real dataset samples (`SPARSEOCC_REALDATA`, default `<repo>/../shared/realdata`).
    Realdata,
}

impl Folder {
    /// The environment variable that names the folder.
    pub fn var(self) -> &'static str {
        match self {
            Folder::Fixtures => FIXTURES_VAR,
            Folder::Realdata => REALDATA_VAR,
        }
    }

    fn default_name(self) -> &'static str {
        match self {
            Folder::Fixtures => "fixtures",
            Folder::Realdata => "realdata",
        }
    }

    /// Where the folder is looked for (it may not exist): the variable when set, else
    /// `<repo>/../shared/<name>`, and whether the path came from the variable.
    pub fn path(self) -> (PathBuf, bool) {
        match std::env::var_os(self.var()) {
            Some(v) if !v.is_empty() => (PathBuf::from(v), true),
            _ => (
                repo_root()
                    .join("..")
                    .join("shared")
                    .join(self.default_name()),
                false,
            ),
        }
    }

    /// The folder when it exists; otherwise a failure or a visible skip, as the crate docs say.
    pub fn find(self) -> Option<PathBuf> {
        let (dir, explicit) = self.path();
        if dir.is_dir() {
            return Some(dir);
        }
        let var = self.var();
        if explicit {
            panic!(
                "{var} is set to {}, which is not a folder (unset it to skip the tests that need it)",
                dir.display()
            );
        }
        if require_data() {
            panic!(
                "{var} folder {} not found and {REQUIRE_VAR} is set: set {var} to the folder",
                dir.display()
            );
        }
        report_skip(&format!(
            "{var} folder {} not found (set {var} to run it; {REQUIRE_VAR}=1 makes this a failure)",
            dir.display()
        ));
        None
    }
}

/// The fixtures folder, or `None` after a visible skip line (see the crate docs).
pub fn fixtures() -> Option<PathBuf> {
    Folder::Fixtures.find()
}

/// The real-data folder, or `None` after a visible skip line (see the crate docs).
pub fn realdata() -> Option<PathBuf> {
    Folder::Realdata.find()
}

/// Whether `SPARSEOCC_REQUIRE_DATA` asks for a missing folder to fail the test.
pub fn require_data() -> bool {
    match std::env::var_os(REQUIRE_VAR) {
        Some(v) => !(v.is_empty() || v == "0"),
        None => false,
    }
}

/// The repository root: two levels above the manifest folder of the crate under test (read at run
/// time when cargo provides it, so a test binary reused from another checkout looks beside the
/// checkout it runs in), else above this crate's own folder.
pub fn repo_root() -> PathBuf {
    std::env::var_os("CARGO_MANIFEST_DIR")
        .map(PathBuf::from)
        .unwrap_or_else(|| Path::new(env!("CARGO_MANIFEST_DIR")).to_path_buf())
        .join("..")
        .join("..")
}

/// Writes `skipped: <test>: <why>` to the process's standard error once per test. The test
/// harness names each test's thread after the test; `std::io::stderr()` is not captured by it
/// (only `print!`/`eprint!` are), so the line shows without `--nocapture`.
pub fn report_skip(why: &str) {
    static SEEN: Mutex<Option<HashSet<String>>> = Mutex::new(None);
    let test = std::thread::current()
        .name()
        .unwrap_or("<unnamed test>")
        .to_string();
    {
        let mut seen = SEEN.lock().unwrap_or_else(|e| e.into_inner());
        if !seen.get_or_insert_with(HashSet::new).insert(test.clone()) {
            return;
        }
    }
    let _ = writeln!(std::io::stderr(), "skipped: {test}: {why}");
}

/// A fresh folder under the system temp dir, named `<prefix>-<tag>-<process id>-<counter>` (unique
/// within the process too), created empty and removed with everything in it on drop.
pub struct TempDir(pub PathBuf);

impl TempDir {
    /// Creates the folder (removing a leftover of the same name first).
    pub fn new(prefix: &str, tag: &str) -> Self {
        static N: AtomicUsize = AtomicUsize::new(0);
        let p = std::env::temp_dir().join(format!(
            "{prefix}-{tag}-{}-{}",
            std::process::id(),
            N.fetch_add(1, Ordering::Relaxed)
        ));
        let _ = std::fs::remove_dir_all(&p);
        std::fs::create_dir_all(&p).unwrap_or_else(|e| panic!("{}: {e}", p.display()));
        TempDir(p)
    }

    /// The folder.
    pub fn path(&self) -> &Path {
        &self.0
    }
}

impl Drop for TempDir {
    fn drop(&mut self) {
        let _ = std::fs::remove_dir_all(&self.0);
    }
}

/// Reads a little-endian C-order `.npy` file as (values, shape); panics naming the file on any
/// error.
pub fn read_npy<T: npyz::Deserialize>(path: &Path) -> (Vec<T>, Vec<usize>) {
    let bytes = std::fs::read(path).unwrap_or_else(|e| panic!("{}: {e}", path.display()));
    let npy = npyz::NpyFile::new(&bytes[..]).unwrap_or_else(|e| panic!("{}: {e}", path.display()));
    let shape: Vec<usize> = npy.shape().iter().map(|&s| s as usize).collect();
    let v = npy
        .into_vec::<T>()
        .unwrap_or_else(|e| panic!("{}: {e}", path.display()));
    (v, shape)
}

/// A copy of the encoded PNG `png` whose header chunk (IHDR, its CRC rewritten so that it stays
/// valid) claims `w` x `h` pixels: input for the image readers' size checks.
pub fn png_claiming_size(png: &[u8], w: u32, h: u32) -> Vec<u8> {
    let mut b = png.to_vec();
    // Signature (8), IHDR length (4), "IHDR" (4), width, height at 16..24, CRC at 29..33.
    assert!(b.len() >= 33 && &b[12..16] == b"IHDR", "not a PNG");
    b[16..20].copy_from_slice(&w.to_be_bytes());
    b[20..24].copy_from_slice(&h.to_be_bytes());
    let crc = crc32(&b[12..29]);
    b[29..33].copy_from_slice(&crc.to_be_bytes());
    b
}

/// CRC-32 (ISO-HDLC, as PNG chunks use it).
fn crc32(bytes: &[u8]) -> u32 {
    let mut c = 0xFFFF_FFFFu32;
    for &b in bytes {
        c ^= b as u32;
        for _ in 0..8 {
            c = if c & 1 != 0 {
                0xEDB8_8320 ^ (c >> 1)
            } else {
                c >> 1
            };
        }
    }
    !c
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn crc32_of_the_check_string() {
        // The standard check value of CRC-32/ISO-HDLC.
        assert_eq!(crc32(b"123456789"), 0xCBF4_3926);
    }

    // The environment is shared by the tests of this binary: only this one test touches it.
    #[test]
    fn missing_folder_skips_fails_or_is_found() {
        let tmp = std::env::temp_dir().join(format!("occ-testdata-{}", std::process::id()));
        let _ = std::fs::remove_dir_all(&tmp);
        std::fs::create_dir_all(tmp.join("repo/crates/x")).unwrap();
        let saved: Vec<_> = [FIXTURES_VAR, REQUIRE_VAR, "CARGO_MANIFEST_DIR"]
            .iter()
            .map(|v| (*v, std::env::var_os(v)))
            .collect();
        // SAFETY (edition 2021: set_var is safe): no other test of this crate reads these.
        std::env::remove_var(FIXTURES_VAR);
        std::env::remove_var(REQUIRE_VAR);
        std::env::set_var("CARGO_MANIFEST_DIR", tmp.join("repo/crates/x"));

        // Default path beside the repository, absent: skipped.
        let (p, explicit) = Folder::Fixtures.path();
        assert!(!explicit);
        assert_eq!(p, tmp.join("repo/crates/x/../../../shared/fixtures"));
        assert_eq!(fixtures(), None);

        // Absent with SPARSEOCC_REQUIRE_DATA: a failure naming the variable.
        std::env::set_var(REQUIRE_VAR, "1");
        let e = std::panic::catch_unwind(fixtures).unwrap_err();
        let msg = e.downcast_ref::<String>().unwrap();
        assert!(
            msg.contains(FIXTURES_VAR) && msg.contains(REQUIRE_VAR),
            "{msg}"
        );
        std::env::set_var(REQUIRE_VAR, "0");
        assert!(!require_data());
        assert_eq!(fixtures(), None);

        // Present beside the repository: found.
        std::fs::create_dir_all(tmp.join("shared/fixtures")).unwrap();
        assert_eq!(fixtures(), Some(p));

        // Set explicitly to a path that is not a folder: a failure even without REQUIRE.
        std::env::set_var(FIXTURES_VAR, tmp.join("nowhere"));
        assert!(std::panic::catch_unwind(fixtures).is_err());
        std::env::set_var(FIXTURES_VAR, tmp.join("shared/fixtures"));
        assert_eq!(fixtures(), Some(tmp.join("shared/fixtures")));

        for (v, old) in saved {
            match old {
                Some(o) => std::env::set_var(v, o),
                None => std::env::remove_var(v),
            }
        }
        let _ = std::fs::remove_dir_all(&tmp);
    }
}
