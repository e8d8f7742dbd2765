//! `sparseocc`: camera images in, a semantic voxel grid out.
//!
//! Commands: `demo` (the whole pipeline on built-in synthetic data), `synth`, `prepare`, `train`,
//! `eval`, `infer`, `bench`, `viz`, and the backend checks `check-backend` and `check-cuda-source`.
//! Every long command shows progress and writes a JSON summary.

mod backend;
mod cmd_bench;
mod cmd_check;
mod cmd_cuda_source;
mod cmd_demo;
mod cmd_eval;
mod cmd_infer;
mod cmd_prepare;
mod cmd_synth;
mod cmd_train;
mod cmd_viz;
mod curves;
mod labels_io;
mod panels;
mod progress;
mod runs;
mod util;

use clap::{Parser, Subcommand};

/// mimalloc instead of glibc malloc: the models allocate and free multi-megabyte tensors every
/// layer, which glibc serves with fresh `mmap`s (page faults and zeroing each time) above its mmap
/// threshold; mimalloc keeps and reuses those pages (BENCHMARKS.md, "allocator"), once
/// [`keep_freed_memory`] has turned its purging off.
#[global_allocator]
static GLOBAL: mimalloc::MiMalloc = mimalloc::MiMalloc;

/// `mi_option_purge_delay`: its position in `mi_option_e` of the mimalloc v3 sources that
/// libmimalloc-sys 0.1.49 builds (pinned in Cargo.toml; `purge_delay_option_is_the_one_set`
/// checks it against the option's documented default).
const MI_OPTION_PURGE_DELAY: libmimalloc_sys::mi_option_t = 15;

/// Tells mimalloc never to give freed pages back to the OS (its `purge_delay` = -1), unless the
/// user set `MIMALLOC_PURGE_DELAY`. By default it purges pages unused for a moment, and every
/// frame then faults them in again, zeroed by the kernel: measured on SparseOcc++ at the
/// nuScenes-Occupancy setting, 195k page faults per run and 15 % of the CPU time in the kernel's
/// page clearing; with purging off 1.6k faults and 7.5 -> 6.7 s per frame, for a peak resident
/// size 18 % higher (freed pages stay mapped for the next frame). BENCHMARKS.md, "allocator".
fn keep_freed_memory() {
    if std::env::var_os("MIMALLOC_PURGE_DELAY").is_none() {
        // SAFETY: plain option setter of the linked mimalloc; valid option index (see above).
        unsafe { libmimalloc_sys::mi_option_set(MI_OPTION_PURGE_DELAY, -1) }
    }
}

#[derive(Parser, Debug)]
#[command(
    name = "sparseocc",
    version,
    about = "Vision-based 3D semantic occupancy prediction (SparseOcc, SparseOcc++)"
)]
struct Cli {
    #[command(subcommand)]
    cmd: Cmd,
}

#[derive(Subcommand, Debug)]
enum Cmd {
    /// The whole pipeline on built-in synthetic data (generate, fit, predict, score, render).
    Demo(cmd_demo::DemoArgs),
    /// Generate synthetic driving scenes in the SemanticKITTI / Occ3D layouts.
    Synth(cmd_synth::SynthArgs),
    /// Check a dataset's layout and write preprocessed labels.
    Prepare(cmd_prepare::PrepareArgs),
    /// Score predictions with the official protocol (SemanticKITTI, Occ3D).
    Eval(cmd_eval::EvalArgs),
    /// Train SparseOcc++, SparseOcc or the dense baseline from a TOML config.
    Train(cmd_train::TrainArgs),
    /// Predict with a trained model: dataset sequences (submission layout) or one camera image.
    Infer(cmd_infer::InferArgs),
    /// Latency, FPS, peak memory and active voxels of the models side by side; memory scan.
    Bench(cmd_bench::BenchArgs),
    /// Check this build's backend (CUDA or WebGPU) against the CPU reference: sparse convs, the encoder, a SparseOcc++ forward pass and training step.
    CheckBackend(cmd_check::CheckArgs),
    /// Compile this build's CUDA kernels for an H100 (sm_90a) without a GPU: the CUDA C++ cubecl
    /// generates, then NVRTC when `CUDA_PATH` and libnvrtc are at hand (`--features cuda` builds).
    CheckCudaSource(cmd_cuda_source::CudaSourceArgs),
    /// Render voxel grids (and camera overlays) to PNG, export PLY; `--nuscenes`: a surround-camera
    /// frame with the LiDAR points and voxels projected into every camera.
    Viz(cmd_viz::VizArgs),
}

fn main() {
    keep_freed_memory();
    let cli = Cli::parse();
    backend::init();
    let r = match &cli.cmd {
        Cmd::Demo(a) => cmd_demo::run(a),
        Cmd::Synth(a) => cmd_synth::run(a),
        Cmd::Prepare(a) => cmd_prepare::run(a),
        Cmd::Viz(a) => cmd_viz::run(a),
        Cmd::Train(a) => cmd_train::run(a),
        Cmd::Infer(a) => cmd_infer::run(a),
        Cmd::Bench(a) => cmd_bench::run(a),
        Cmd::CheckBackend(a) => cmd_check::run(a),
        Cmd::CheckCudaSource(a) => cmd_cuda_source::run(a),
        Cmd::Eval(a) => cmd_eval::run(a).map(|_| ()),
    };
    if let Err(e) = r {
        eprintln!("error: {}", error_text(&e));
        std::process::exit(1);
    }
}

/// The error and its causes on one line, `outer: cause: cause`, each cause once: many errors
/// already print their source (`path: No such file or directory`), which `{:#}` would repeat.
fn error_text(e: &anyhow::Error) -> String {
    let mut text = String::new();
    for cause in e.chain() {
        let c = cause.to_string();
        let c = c.trim();
        if c.is_empty() || text.contains(c) {
            continue;
        }
        if !text.is_empty() {
            text.push_str(": ");
        }
        text.push_str(c);
    }
    text
}

#[cfg(test)]
mod alloc_tests {
    use super::*;

    /// The option index names the purge delay: its documented default (1000 ms in mimalloc v3)
    /// reads back unless the environment set it, and a value set through it reads back.
    #[test]
    fn purge_delay_option_is_the_one_set() {
        // SAFETY: plain option getters and setters of the linked mimalloc.
        unsafe {
            if std::env::var_os("MIMALLOC_PURGE_DELAY").is_none() {
                assert_eq!(libmimalloc_sys::mi_option_get(MI_OPTION_PURGE_DELAY), 1000);
            }
            let before = libmimalloc_sys::mi_option_get(MI_OPTION_PURGE_DELAY);
            libmimalloc_sys::mi_option_set(MI_OPTION_PURGE_DELAY, -1);
            assert_eq!(libmimalloc_sys::mi_option_get(MI_OPTION_PURGE_DELAY), -1);
            libmimalloc_sys::mi_option_set(MI_OPTION_PURGE_DELAY, before);
        }
    }
}
