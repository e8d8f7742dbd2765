//! Shared helpers of the occ-data integration tests (the external data folders themselves are found
//! by `occ_testdata`).
#![allow(dead_code)]

use std::path::{Path, PathBuf};

/// The SemanticKITTI root under the real data (the folder containing `sequences/`), or `None`
/// (skip reported by `occ_testdata`) when the real-data folder is absent.
pub fn kitti_root() -> Option<PathBuf> {
    let root = occ_testdata::realdata()?.join("semantickitti");
    assert!(
        root.join("sequences").is_dir(),
        "{} has no sequences/ folder",
        root.display()
    );
    Some(root)
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
