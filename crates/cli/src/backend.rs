//! The burn backend the binary runs on: ndarray on the CPU by default, CUDA with `--features cuda`,
//! WebGPU with `--features wgpu` (any Vulkan/Metal/DX12 device, or lavapipe, Mesa's Vulkan driver on
//! the CPU, which is how the GPU code path is tested on machines without a GPU).
//!
//! On the cubecl backends (CUDA, WebGPU) [`init`] also counts kernel compilations
//! ([`kernel_compilations`]): `bench` and `check-backend` report how many happen after warm-up.
//! With [`COUNT_LAUNCHES_ENV`] set it counts kernel launches too ([`kernel_launches`]), by name:
//! `bench` reports them per frame.

use burn::backend::Autodiff;

/// Inference backend.
#[cfg(not(any(feature = "cuda", feature = "wgpu")))]
pub type Infer = burn::backend::NdArray<f32>;
/// Inference backend.
#[cfg(feature = "cuda")]
pub type Infer = burn_cuda::Cuda;
/// Inference backend.
#[cfg(all(feature = "wgpu", not(feature = "cuda")))]
pub type Infer = burn_wgpu::Wgpu;

/// Training backend.
pub type Train = Autodiff<Infer>;

/// The float element of the CUDA build ([`Infer`] = `burn_cuda::Cuda`'s default).
#[cfg(feature = "cuda-source")]
pub type CudaFloat = f32;
/// The int element of the CUDA build (indices: kernel maps, DCA layouts).
#[cfg(feature = "cuda-source")]
pub type CudaInt = i32;

/// The DCA sampling's `#[cube]` training op (forward and backward kernels) on this build's
/// backend, whatever `SPARSEOCC_CUBE_DCA` chose for training: what `check-backend` tests it with.
#[cfg(feature = "cuda")]
pub fn cube_dca_train(
    s: occ_model::kernels::DcaSample<'_, Train>,
) -> burn::tensor::Tensor<Train, 2> {
    occ_model::kernels::dca_cube::sample_autodiff::<
        cubecl::cuda::CudaRuntime,
        CudaFloat,
        CudaInt,
        u8,
        _,
    >(s)
}

/// The DCA sampling's `#[cube]` training op (forward and backward kernels) on this build's
/// backend, whatever `SPARSEOCC_CUBE_DCA` chose for training: what `check-backend` tests it with.
#[cfg(all(feature = "wgpu", not(feature = "cuda")))]
pub fn cube_dca_train(
    s: occ_model::kernels::DcaSample<'_, Train>,
) -> burn::tensor::Tensor<Train, 2> {
    occ_model::kernels::dca_cube::sample_autodiff::<burn_wgpu::WgpuRuntime, f32, i32, u32, _>(s)
}

/// `bench`'s default warm-up frames. On the cubecl backends two: burn-fusion explores the first
/// pass over a frame's operations and stores execution plans, later passes run the stored plans,
/// which can cut the stream into other fused blocks and so compile a few kernels once more
/// (`check-backend`: 2-20 on the second pass over the same frame, none on the frames after it,
/// whatever their voxel counts; docs/gpu.md). On the CPU one.
pub const DEFAULT_WARMUP: usize = if cfg!(any(feature = "cuda", feature = "wgpu")) {
    2
} else {
    1
};

/// The device to run on (CPU; CUDA device 0; the default WebGPU adapter).
pub fn device() -> burn::tensor::Device<Infer> {
    Default::default()
}

/// Human-readable device and precision, for logs and benchmark tables.
pub fn describe() -> String {
    #[cfg(any(feature = "cuda", feature = "wgpu"))]
    let conv = format!(
        "{}, maps {}, conv2d {}, dca {}",
        occ_sparse::cube::CubeConv::current().as_str(),
        occ_sparse::cube::CubeMaps::current().as_str(),
        occ_model::kernels::conv2d_cube::CubeConv2d::current().as_str(),
        occ_model::kernels::dca_cube::CubeDca::current().as_str()
    );
    #[cfg(not(any(feature = "cuda", feature = "wgpu")))]
    let conv = "";
    if cfg!(feature = "cuda") {
        format!(
            "CUDA device 0 (burn-cuda), fp32, cubecl autotune {}, sparse conv {conv}",
            if cfg!(feature = "cuda-autotune") {
                "on"
            } else {
                "off"
            }
        )
    } else if cfg!(feature = "wgpu") {
        format!(
            "WebGPU default adapter (burn-wgpu, WGSL), fp32, cubecl autotune off, sparse conv {conv}"
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

/// The environment variable naming a folder for cubecl's on-disk caches (compiled kernels under
/// `compilation/`, autotune results under `autotune/`) on the cubecl backends; unset, cubecl's own
/// configuration decides (off by default for compiled kernels).
#[cfg(any(feature = "cuda", feature = "wgpu"))]
pub const KERNEL_CACHE_ENV: &str = "SPARSEOCC_KERNEL_CACHE";

/// The environment variable that turns kernel-launch counting on (any value; cubecl backends):
/// cubecl's profiling log at its `minimal` level (one line per executed kernel, no timing) is routed
/// to the counter of [`kernel_launches`]; `log` also prints each launch's kernel to stderr. It costs a formatted name and a channel message per
/// launch, so `bench` times taken with it on are not the device's speed.
#[cfg(any(feature = "cuda", feature = "wgpu"))]
pub const COUNT_LAUNCHES_ENV: &str = "SPARSEOCC_COUNT_LAUNCHES";

/// Sets the process up for the backend; call first thing in `main`. On the cubecl backends this
/// turns cubecl's compilation log on at its basic level (one line per compiled kernel), routed to
/// the `log` crate, where a small logger counts the lines; warnings and errors of cubecl and wgpu are
/// printed to stderr. The cubecl configuration files (`cubecl.toml`) and `CUBECL_DEBUG_*` variables
/// are read first and kept, with the compilation logger added, and the caches put in the folder
/// [`KERNEL_CACHE_ENV`] names, if any.
pub fn init() {
    #[cfg(any(feature = "cuda", feature = "wgpu"))]
    kernel_counts::install();
}

/// Kernels compiled so far by this process (None on the CPU backend, which compiles nothing).
/// Compilations are logged asynchronously: call [`settled_kernel_compilations`] after a device sync
/// to read a count that includes everything launched so far.
pub fn kernel_compilations() -> Option<u64> {
    #[cfg(any(feature = "cuda", feature = "wgpu"))]
    {
        Some(kernel_counts::COMPILES.load(std::sync::atomic::Ordering::SeqCst))
    }
    #[cfg(not(any(feature = "cuda", feature = "wgpu")))]
    {
        None
    }
}

/// [`kernel_compilations`] once it has stopped changing for 200 ms (at most 5 s): cubecl hands each
/// compilation's log line to a background task, so the count trails the launches by a moment.
pub fn settled_kernel_compilations() -> Option<u64> {
    settled(kernel_compilations)
}

/// Kernel launches so far by this process, by kernel name (cubecl's short form of its type name),
/// when [`COUNT_LAUNCHES_ENV`] is set on a cubecl backend; `None` otherwise. Read once the count
/// has settled (it trails the launches as [`settled_kernel_compilations`] does).
pub fn kernel_launches() -> Option<Vec<(String, u64)>> {
    #[cfg(any(feature = "cuda", feature = "wgpu"))]
    {
        kernel_counts::counting_launches().then(|| {
            settled(|| Some(kernel_counts::LAUNCHES.load(std::sync::atomic::Ordering::SeqCst)));
            kernel_counts::launches_by_name()
        })
    }
    #[cfg(not(any(feature = "cuda", feature = "wgpu")))]
    {
        None
    }
}

/// `count()` once it has stopped changing for 200 ms (at most 5 s).
fn settled(count: impl Fn() -> Option<u64>) -> Option<u64> {
    let mut last = count()?;
    let start = std::time::Instant::now();
    let mut stable_since = std::time::Instant::now();
    while start.elapsed() < std::time::Duration::from_secs(5) {
        std::thread::sleep(std::time::Duration::from_millis(20));
        let now = count()?;
        if now != last {
            last = now;
            stable_since = std::time::Instant::now();
        } else if stable_since.elapsed() >= std::time::Duration::from_millis(200) {
            break;
        }
    }
    Some(last)
}

#[cfg(any(feature = "cuda", feature = "wgpu"))]
mod kernel_counts {
    use super::{COUNT_LAUNCHES_ENV, KERNEL_CACHE_ENV};
    use cubecl::config::cache::CacheConfig;
    use cubecl::config::compilation::CompilationLogLevel;
    use cubecl::config::profiling::ProfilingLogLevel;
    use cubecl::config::{CubeClRuntimeConfig, RuntimeConfig};
    use cubecl_common::config::logger::LogCrateLevel;
    use std::collections::HashMap;
    use std::sync::atomic::{AtomicBool, AtomicU64, Ordering};
    use std::sync::Mutex;

    /// Kernels compiled so far.
    pub static COMPILES: AtomicU64 = AtomicU64::new(0);
    /// Kernels launched so far (counted only when [`COUNTING_LAUNCHES`]).
    pub static LAUNCHES: AtomicU64 = AtomicU64::new(0);
    /// Whether cubecl's execution log is on and counted.
    static COUNTING_LAUNCHES: AtomicBool = AtomicBool::new(false);
    /// Whether every counted launch is also printed (`SPARSEOCC_COUNT_LAUNCHES=log`; with
    /// `SPARSEOCC_TRACE=1` the stage lines fall between them).
    static PRINTING_LAUNCHES: AtomicBool = AtomicBool::new(false);
    /// Launches by kernel name.
    static BY_NAME: Mutex<Option<HashMap<String, u64>>> = Mutex::new(None);

    /// How cubecl's profiling log at its `minimal` level starts the line of each executed kernel.
    const EXECUTING: &str = "Executing ";

    pub fn counting_launches() -> bool {
        COUNTING_LAUNCHES.load(Ordering::SeqCst)
    }

    /// The launch counts by name, most launched first (ties by name).
    pub fn launches_by_name() -> Vec<(String, u64)> {
        let by_name = BY_NAME.lock().unwrap_or_else(|p| p.into_inner());
        let mut v: Vec<(String, u64)> = by_name
            .iter()
            .flatten()
            .map(|(k, &n)| (k.clone(), n))
            .collect();
        v.sort_by(|a, b| b.1.cmp(&a.1).then_with(|| a.0.cmp(&b.0)));
        v
    }

    /// How cubecl's compilation log starts the entry of each compiled kernel (basic level; full
    /// level, which `CUBECL_DEBUG_LOG` selects).
    const MARKS: [&str; 2] = ["[Compiling kernel]", "[START_KERNEL_COMPILATION]"];

    struct Counter;

    impl log::Log for Counter {
        fn enabled(&self, _: &log::Metadata) -> bool {
            true
        }

        fn log(&self, record: &log::Record) {
            let cubecl = record.target().starts_with("cubecl");
            if cubecl && record.level() >= log::Level::Info {
                let msg = record.args().to_string();
                if let Some(name) = msg.strip_prefix(EXECUTING) {
                    LAUNCHES.fetch_add(1, Ordering::SeqCst);
                    if PRINTING_LAUNCHES.load(Ordering::Relaxed) {
                        eprintln!("launch {name}");
                    }
                    let mut by_name = BY_NAME.lock().unwrap_or_else(|p| p.into_inner());
                    *by_name
                        .get_or_insert_with(HashMap::new)
                        .entry(name.to_string())
                        .or_default() += 1;
                    return;
                }
                if MARKS.iter().any(|m| msg.starts_with(m)) {
                    COMPILES.fetch_add(1, Ordering::SeqCst);
                    match std::env::var("SPARSEOCC_LOG_COMPILES").as_deref() {
                        // The kernel's name and id (its configuration), not its source.
                        Ok("full") => eprintln!(
                            "{}",
                            msg.lines()
                                .take_while(|l| !l.starts_with("source:"))
                                .collect::<Vec<_>>()
                                .join("\n")
                        ),
                        Ok(_) => {
                            eprintln!("{}", msg.lines().take(2).collect::<Vec<_>>().join(" "))
                        }
                        Err(_) => {}
                    }
                    return;
                }
            }
            if record.level() <= log::Level::Warn {
                eprintln!("{} {}: {}", record.level(), record.target(), record.args());
            }
        }

        fn flush(&self) {}
    }

    static COUNTER: Counter = Counter;

    pub fn install() {
        let mut config = CubeClRuntimeConfig::from_current_dir().override_from_env();
        if let Some(dir) = std::env::var_os(KERNEL_CACHE_ENV).filter(|d| !d.is_empty()) {
            // cubecl's caches of compiled kernels and of autotune results in one folder.
            let dir = std::path::PathBuf::from(dir);
            config.compilation.cache = Some(CacheConfig::File(dir.join("compilation")));
            config.autotune.cache = CacheConfig::File(dir.join("autotune"));
        }
        let logger = &mut config.compilation.logger;
        if std::env::var("SPARSEOCC_LOG_COMPILES").as_deref() == Ok("full") {
            // Each kernel's id (its whole configuration) in the log, to tell why one recompiles.
            logger.level = CompilationLogLevel::Full;
        } else if matches!(logger.level, CompilationLogLevel::Disabled) {
            logger.level = CompilationLogLevel::Basic;
        }
        logger.log = Some(LogCrateLevel::Info);
        let count_launches = std::env::var_os(COUNT_LAUNCHES_ENV).is_some();
        let print_launches = std::env::var(COUNT_LAUNCHES_ENV).as_deref() == Ok("log");
        PRINTING_LAUNCHES.store(print_launches, Ordering::SeqCst);
        if count_launches {
            // One line per executed kernel, without timing (no sync per launch).
            let logger = &mut config.profiling.logger;
            logger.level = ProfilingLogLevel::Minimal;
            logger.log = Some(LogCrateLevel::Info);
        }
        CubeClRuntimeConfig::set(config);
        COUNTING_LAUNCHES.store(count_launches, Ordering::SeqCst);
        // Another logger may already be installed (a test harness); then nothing is counted.
        if log::set_logger(&COUNTER).is_ok() {
            log::set_max_level(log::LevelFilter::Info);
        }
    }
}
