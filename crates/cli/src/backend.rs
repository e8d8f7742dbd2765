//! The burn backend the binary runs on: ndarray on the CPU by default, CUDA with `--features cuda`.

use burn::backend::Autodiff;

/// Inference backend.
#[cfg(not(feature = "cuda"))]
pub type Infer = burn::backend::NdArray<f32>;
/// Inference backend.
#[cfg(feature = "cuda")]
pub type Infer = burn_cuda::Cuda;

/// Training backend.
pub type Train = Autodiff<Infer>;

/// The device to run on (CPU, or CUDA device 0).
pub fn device() -> burn::tensor::Device<Infer> {
    Default::default()
}

/// Human-readable device and precision, for logs and benchmark tables.
pub fn describe() -> String {
    if cfg!(feature = "cuda") {
        format!(
            "CUDA device 0 (burn-cuda), fp32, cubecl autotune {}",
            if cfg!(feature = "cuda-autotune") {
                "on"
            } else {
                "off"
            }
        )
    } else {
        format!(
            "CPU, burn-ndarray, {} rayon threads, fp32",
            std::thread::available_parallelism()
                .map(|n| n.get())
                .unwrap_or(1)
        )
    }
}
