//! Shared helpers of the occ-data integration tests.
#![allow(dead_code)]

use std::path::{Path, PathBuf};

fn repo_root() -> PathBuf {
    // At run time when cargo provides it: a test binary reused from another checkout of the same
    // sources must look beside this checkout.
    std::env::var_os("CARGO_MANIFEST_DIR")
        .map(PathBuf::from)
        .unwrap_or_else(|| Path::new(env!("CARGO_MANIFEST_DIR")).to_path_buf())
        .join("..")
        .join("..")
}

/// `$SPARSEOCC_REALDATA` or `<repo>/../shared/realdata`; panics with a clear message if absent.
pub fn realdata_dir() -> PathBuf {
    let dir = std::env::var_os("SPARSEOCC_REALDATA")
        .map(PathBuf::from)
        .unwrap_or_else(|| repo_root().join("..").join("shared").join("realdata"));
    assert!(
        dir.is_dir(),
        "real sample data folder {} not found: set SPARSEOCC_REALDATA to the shared/realdata folder",
        dir.display()
    );
    dir
}

/// `$SPARSEOCC_FIXTURES` or `<repo>/../shared/fixtures`; panics with a clear message if absent.
pub fn fixtures_dir() -> PathBuf {
    let dir = std::env::var_os("SPARSEOCC_FIXTURES")
        .map(PathBuf::from)
        .unwrap_or_else(|| repo_root().join("..").join("shared").join("fixtures"));
    assert!(
        dir.is_dir(),
        "fixtures folder {} not found: set SPARSEOCC_FIXTURES to the shared/fixtures folder",
        dir.display()
    );
    dir
}

/// The SemanticKITTI root under the real data (the folder containing `sequences/`).
pub fn kitti_root() -> PathBuf {
    let root = realdata_dir().join("semantickitti");
    assert!(
        root.join("sequences").is_dir(),
        "{} has no sequences/ folder",
        root.display()
    );
    root
}

/// A fresh temporary folder removed on drop.
pub struct TempDir(pub PathBuf);

impl TempDir {
    pub fn new(tag: &str) -> Self {
        use std::sync::atomic::{AtomicUsize, Ordering};
        static N: AtomicUsize = AtomicUsize::new(0);
        let p = std::env::temp_dir().join(format!(
            "occ-data-test-{tag}-{}-{}",
            std::process::id(),
            N.fetch_add(1, Ordering::SeqCst)
        ));
        let _ = std::fs::remove_dir_all(&p);
        std::fs::create_dir_all(&p).unwrap();
        TempDir(p)
    }
    pub fn path(&self) -> &Path {
        &self.0
    }
}

impl Drop for TempDir {
    fn drop(&mut self) {
        let _ = std::fs::remove_dir_all(&self.0);
    }
}

/// IoU of two occupancy grids (non-zero = occupied): (intersection, union, iou).
pub fn iou(a: &[u8], b: &[u8]) -> (usize, usize, f64) {
    assert_eq!(a.len(), b.len());
    let mut i = 0;
    let mut u = 0;
    for (&x, &y) in a.iter().zip(b) {
        let (x, y) = (x != 0, y != 0);
        i += (x && y) as usize;
        u += (x || y) as usize;
    }
    (i, u, if u == 0 { 1.0 } else { i as f64 / u as f64 })
}
