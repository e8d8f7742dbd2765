//! `sparseocc`: camera images in, a semantic voxel grid out.
//!
//! Commands: `demo` (the whole pipeline on built-in synthetic data), `synth`, `prepare`, `train`,
//! `eval`, `infer`, `bench`, `viz`. Every long command shows progress and writes a JSON summary.

mod backend;
mod cmd_bench;
mod cmd_check;
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
/// threshold; mimalloc keeps and reuses those pages (BENCHMARKS.md, "allocator").
#[global_allocator]
static GLOBAL: mimalloc::MiMalloc = mimalloc::MiMalloc;

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
    /// Render voxel grids (and camera overlays) to PNG, export PLY; `--nuscenes`: a surround-camera
    /// frame with the LiDAR points and voxels projected into every camera.
    Viz(cmd_viz::VizArgs),
}

fn main() {
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
