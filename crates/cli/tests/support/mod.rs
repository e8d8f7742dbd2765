//! Shared helpers of the `sparseocc` binary's integration tests (`cli.rs`, `bad_input.rs`,
//! `viz_surround.rs`): running the binary, temporary folders, copying datasets, and the tiny
//! SparseOcc++ config every end-to-end test trains.
#![allow(dead_code)] // each test binary uses a different subset

use std::ffi::OsStr;
use std::path::{Path, PathBuf};
use std::process::{Command, Output};

/// The binary under test, with progress bars off (`CI=1`).
pub fn bin() -> Command {
    let mut c = Command::new(env!("CARGO_BIN_EXE_sparseocc"));
    c.env("CI", "1");
    c
}

/// Runs the binary with `args`.
pub fn run<S: AsRef<OsStr>>(args: &[S]) -> Output {
    bin().args(args).output().expect("run sparseocc")
}

/// Stdout followed by stderr.
pub fn text(o: &Output) -> String {
    format!(
        "{}{}",
        String::from_utf8_lossy(&o.stdout),
        String::from_utf8_lossy(&o.stderr)
    )
}

/// Runs and asserts success; returns stdout + stderr.
pub fn ok<S: AsRef<OsStr> + std::fmt::Debug>(args: &[S]) -> String {
    let o = run(args);
    assert!(
        o.status.success(),
        "sparseocc {args:?} failed:\n{}",
        text(&o)
    );
    text(&o)
}

/// Runs and asserts a failure (an exit status, not a signal), an `error:` line and no panic;
/// returns stderr.
pub fn fails<S: AsRef<OsStr> + std::fmt::Debug>(args: &[S]) -> String {
    let o = run(args);
    let err = String::from_utf8_lossy(&o.stderr).into_owned();
    assert!(
        o.status.code().is_some_and(|c| c != 0),
        "sparseocc {args:?} should fail with an exit status, got {:?}: {err}",
        o.status
    );
    assert!(err.contains("error:"), "no error line: {err}");
    assert!(!err.contains("panicked"), "panicked: {err}");
    err
}

/// [`fails`] with exit status 1 (bad input, as opposed to a command-line usage error).
pub fn fails_status_1<S: AsRef<OsStr> + std::fmt::Debug>(args: &[S]) -> String {
    let o = run(args);
    let err = String::from_utf8_lossy(&o.stderr).into_owned();
    assert_eq!(o.status.code(), Some(1), "sparseocc {args:?}: {err}");
    assert!(err.contains("error:"), "no error line: {err}");
    assert!(!err.contains("panicked"), "panicked: {err}");
    err
}

/// A fresh folder `sparseocc-<prefix>-<pid>-<name>` in the system's temporary directory (emptied
/// if it exists; left in place for inspection when a test fails).
pub fn tmp(prefix: &str, name: &str) -> PathBuf {
    let d = std::env::temp_dir().join(format!("sparseocc-{prefix}-{}-{name}", std::process::id()));
    let _ = std::fs::remove_dir_all(&d);
    std::fs::create_dir_all(&d).unwrap();
    d
}

/// The path as UTF-8 (test paths are).
pub fn p(x: &Path) -> &str {
    x.to_str().unwrap()
}

/// Copies the folder `from` to `to`, recursively.
pub fn copy_dir(from: &Path, to: &Path) {
    std::fs::create_dir_all(to).unwrap();
    for e in std::fs::read_dir(from).unwrap() {
        let e = e.unwrap();
        let t = to.join(e.file_name());
        if e.file_type().unwrap().is_dir() {
            copy_dir(&e.path(), &t);
        } else {
            std::fs::copy(e.path(), &t).unwrap();
        }
    }
}

/// Copies the file `from` to `to`, creating `to`'s folder.
pub fn copy_file(from: &Path, to: &Path) {
    std::fs::create_dir_all(to.parent().unwrap()).unwrap();
    std::fs::copy(from, to)
        .unwrap_or_else(|e| panic!("{} -> {}: {e}", from.display(), to.display()));
}

/// A very small SparseOcc++ on the kitti-small grid: `steps` steps, a checkpoint every
/// `checkpoint_every`, training on sequence 00 and validating on `val` (160x64 images).
pub fn tiny_config(steps: usize, checkpoint_every: usize, val: &[&str]) -> String {
    let val: Vec<String> = val.iter().map(|v| format!("\"{v}\"")).collect();
    format!(
        r#"
[model]
kind = "sparseocc++"
num_classes = 20
full_dims = [128, 128, 16]
lss_level = 0

[model.encoder.resnet]
depth = 18
base_width = 8
out_indices = [1]

[model.encoder.fpn]
out_channels = 16

[model.sparseocc_pp]
embed_dim = 16
dca_heads = 2
keep_ratios = [1.0, 0.1, 0.1]

[train]
steps = {steps}
lr = 1e-3
checkpoint_every = {checkpoint_every}

[data]
image_width = 160
image_height = 64
train_sequences = ["00"]
val_sequences = [{}]
"#,
        val.join(", ")
    )
}
