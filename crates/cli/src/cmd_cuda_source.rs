//! `sparseocc check-cuda-source`: the CUDA build's own kernels compiled for an H100 (sm_90a)
//! without a GPU, so that a kernel CUDA cannot compile is found before the rare GPU session, not
//! in it (`occ_sparse::cuda_source`, docs/gpu.md "Before a GPU session").
//!
//! Every configuration of every `#[cube]` kernel of `occ-sparse` (sparse convolution forward and
//! weight gradient, device kernel maps, row ops) and `occ-model` (DCA sampling forward and
//! backward, im2col / col2im) that a launch can compile: the CUDA C++ that cubecl-cuda generates
//! for it (always), then NVRTC's PTX and sm_90a binary of that source when NVRTC and the CUDA
//! headers are at hand (`CUDA_PATH` holding `include/`, `libnvrtc.so*` on the library path;
//! `scripts/cuda_source_check.sh` fetches both from PyPI). Without them only the generation is
//! checked, and the JSON says why NVRTC was skipped; `--require-nvrtc` makes that a failure.

use anyhow::Result;
use std::path::PathBuf;

/// Arguments of `sparseocc check-cuda-source`.
#[derive(clap::Args, Debug)]
pub struct CudaSourceArgs {
    /// Write every configuration's CUDA C++ (`.cu`) and, when NVRTC ran, its PTX (`.ptx`) here.
    #[arg(long)]
    pub out: Option<PathBuf>,
    /// Write the results as JSON here.
    #[arg(long)]
    pub json: Option<PathBuf>,
    /// Fail when NVRTC cannot run (no CUDA_PATH headers or no libnvrtc) instead of checking the
    /// generated sources only.
    #[arg(long)]
    pub require_nvrtc: bool,
}

/// Without the `cuda` feature there is no CUDA compiler in the binary.
#[cfg(not(feature = "cuda-source"))]
pub fn run(_: &CudaSourceArgs) -> Result<()> {
    anyhow::bail!(
        "this binary was built without CUDA; build it with `CUDARC_CUDA_VERSION=13000 cargo build \
         --release -p sparseocc --features cuda` (no GPU or CUDA install needed)"
    )
}

/// Generates (and with NVRTC compiles) every kernel configuration; fails on the first kind of
/// error after checking them all.
#[cfg(feature = "cuda-source")]
pub fn run(a: &CudaSourceArgs) -> Result<()> {
    use crate::backend::{CudaFloat, CudaInt};
    use crate::util::{write_file, write_json};
    use anyhow::bail;
    use cubecl::prelude::CubePrimitive;
    use occ_sparse::cuda_source::{cuda_source, launchable_kernels, offline_client, Nvrtc, ARCH};

    let client = offline_client();
    let float = CudaFloat::as_type_native_unchecked().storage_type();
    let int = CudaInt::as_type_native_unchecked().storage_type();
    let mut kernels = occ_sparse::cube::cuda_source_kernels(&client, float, int);
    kernels.extend(occ_model::kernels::dca_cube::cuda_source_kernels(
        &client, float, int,
    ));
    kernels.extend(occ_model::kernels::conv2d_cube::cuda_source_kernels(
        &client, float,
    ));
    let nvrtc = Nvrtc::from_env();
    match &nvrtc {
        Ok(n) => println!(
            "NVRTC {}.{} for sm_{ARCH}a, headers from CUDA_PATH",
            n.version().0,
            n.version().1
        ),
        Err(why) if a.require_nvrtc => bail!("NVRTC is required (--require-nvrtc): {why}"),
        Err(why) => println!("NVRTC skipped ({why}): checking the generated CUDA C++ only"),
    }
    let mut rows = Vec::with_capacity(kernels.len());
    let mut failed = Vec::new();
    let mut names: Vec<String> = Vec::new();
    for (i, kernel) in kernels.iter().enumerate() {
        let source = match cuda_source(kernel.as_ref()) {
            Ok(s) => s,
            Err(e) => {
                failed.push(e.clone());
                rows.push(serde_json::json!({ "kernel": kernel.name(), "error": e }));
                continue;
            }
        };
        if !names.contains(&source.name) {
            names.push(source.name.clone());
        }
        let stem = format!("{i:03}_{}", source.name);
        if let Some(dir) = &a.out {
            write_file(&dir.join(format!("{stem}.cu")), source.source.as_bytes())?;
        }
        let mut row = serde_json::json!({
            "kernel": source.name,
            "file": format!("{stem}.cu"),
            "cube_dim": [source.cube_dim.x, source.cube_dim.y, source.cube_dim.z],
            "address_type": format!("{:?}", source.address_type),
            "shared_bytes": source.shared_bytes,
            "source_bytes": source.source.len(),
        });
        if let Ok(nvrtc) = &nvrtc {
            match nvrtc.compile(&source) {
                Ok(out) => {
                    if let Some(dir) = &a.out {
                        write_file(&dir.join(format!("{stem}.ptx")), out.ptx.as_bytes())?;
                    }
                    row["ptx_bytes"] = out.ptx.len().into();
                    row["cubin_bytes"] = out.cubin_bytes.into();
                    if !out.log.is_empty() {
                        row["nvrtc_log"] = out.log.into();
                    }
                }
                Err(e) => {
                    failed.push(e.clone());
                    row["error"] = e.into();
                }
            }
        }
        rows.push(row);
    }
    let config_failures = failed.len();
    // A kernel declared in a kernel file but left off its list would go unchecked.
    let declared = [
        occ_sparse::cube::KERNEL_SOURCE,
        occ_model::kernels::dca_cube::KERNEL_SOURCE,
        occ_model::kernels::conv2d_cube::KERNEL_SOURCE,
    ]
    .map(launchable_kernels)
    .concat();
    for kernel in &declared {
        let prefix = format!("{kernel}_");
        if !names.iter().any(|n| n == kernel || n.starts_with(&prefix)) {
            failed.push(format!(
                "{kernel}: declared with #[cube(launch...)] but in no cuda_source_kernels list"
            ));
        }
    }
    let compiled_with = match &nvrtc {
        Ok(n) => serde_json::json!(format!("NVRTC {}.{}", n.version().0, n.version().1)),
        Err(_) => serde_json::Value::Null,
    };
    let summary = serde_json::json!({
        "arch": format!("sm_{ARCH}a"),
        "configurations": kernels.len(),
        "kernels": names,
        "declared_kernels": declared,
        "nvrtc": compiled_with,
        "nvrtc_skipped": nvrtc.as_ref().err(),
        "failed": failed.len(),
        "unlisted_kernels": failed.len() - config_failures,
        "results": rows,
    });
    if let Some(path) = &a.json {
        write_json(path, &summary)?;
    }
    let stage = if nvrtc.is_ok() {
        "CUDA C++ and NVRTC (PTX, sm_90a binary)"
    } else {
        "CUDA C++"
    };
    println!(
        "{} configurations of {} kernels ({} declared): {} passed ({stage}), {} failed",
        kernels.len(),
        names.len(),
        declared.len(),
        kernels.len() - config_failures,
        config_failures
    );
    for e in &failed {
        eprintln!("failed: {e}");
    }
    if config_failures > 0 {
        bail!(
            "{config_failures} of {} kernel configurations do not compile for CUDA",
            kernels.len()
        );
    }
    if !failed.is_empty() {
        bail!(
            "{} launchable kernels are in no cuda_source_kernels list",
            failed.len() - config_failures
        );
    }
    Ok(())
}
