//! Helpers shared by the occ-eval integration tests.

use occ_eval::FolderOptions;
use occ_testdata::TempDir;
use std::sync::atomic::{AtomicUsize, Ordering};

/// Runs `score` with default options whose `on_frame` counts the frames it is called for: what
/// `score` returned, and the count.
pub fn counting_frames<R>(score: impl FnOnce(&FolderOptions) -> R) -> (R, usize) {
    let frames = AtomicUsize::new(0);
    let on_frame = || {
        frames.fetch_add(1, Ordering::Relaxed);
    };
    let opts = FolderOptions {
        on_frame: Some(&on_frame),
        ..Default::default()
    };
    let out = score(&opts);
    (out, frames.load(Ordering::Relaxed))
}

/// Runs `score` with options that select the sequences (scenes) `names`.
pub fn with_sequences<R>(names: &[&str], score: impl FnOnce(&FolderOptions) -> R) -> R {
    let names: Vec<String> = names.iter().map(|n| n.to_string()).collect();
    score(&FolderOptions {
        sequences: Some(&names),
        ..Default::default()
    })
}

/// A fresh ground-truth folder and a fresh prediction folder, `<prefix>-<tag>-gt-…` and
/// `<prefix>-<tag>-pred-…`.
pub fn gt_and_pred(prefix: &str, tag: &str) -> (TempDir, TempDir) {
    (
        TempDir::new(prefix, &format!("{tag}-gt")),
        TempDir::new(prefix, &format!("{tag}-pred")),
    )
}
