//! occ-model integration tests on the f32 NdArray backend (PyTorch reference outputs, overfitting),
//! one binary (see `model_f64/main.rs` for why the dtypes are split).

#[path = "../common/kernel_checks/mod.rs"]
mod kernel_checks;
#[path = "../common/so_common/mod.rs"]
mod so_common;

/// `tests/data/<name>` of this crate, which must hold a `manifest.json` (made by
/// `scripts/<script>`). The manifest dir is read at run time (cargo sets it), so a test binary
/// reused from another checkout of the same sources still reads this checkout's data.
fn fixture_dir(name: &str, script: &str) -> std::path::PathBuf {
    let manifest = std::env::var_os("CARGO_MANIFEST_DIR")
        .map(std::path::PathBuf::from)
        .unwrap_or_else(|| env!("CARGO_MANIFEST_DIR").into());
    let dir = manifest.join("tests/data").join(name);
    assert!(
        dir.join("manifest.json").is_file(),
        "fixture folder {} (manifest.json) is missing: regenerate it with scripts/{script}",
        dir.display()
    );
    dir
}

mod conv_host;
mod host_kernels;
mod image_encoder;
mod pp_overfit;
mod pth_cases;
mod so_overfit;
