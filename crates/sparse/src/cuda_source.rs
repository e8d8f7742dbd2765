//! The CUDA C++ of the `#[cube]` kernels, generated and compiled without a GPU: a pre-flight check
//! for the CUDA build, whose kernels are otherwise only run (and compiled) on the rare GPU machine.
//!
//! cubecl-cuda turns a kernel into CUDA C++ with its compiler (`cubecl::cuda::CudaCompiler`) and
//! compiles that with NVRTC when the kernel is first launched. Neither step needs a device, but the
//! CUDA runtime does (its client opens the driver). So this module has an offline runtime
//! ([`OfflineCuda`]): a client with an H100's (sm_90) device properties whose server refuses to
//! run anything, enough to build a kernel's definition; [`cuda_source`] compiles that definition
//! with the compilation options cubecl-cuda sets for sm_90 (cubecl-cuda 0.10 `runtime.rs`) and
//! checks the cube against the device limits as its launch does; [`Nvrtc`] compiles the source as
//! cubecl-cuda's `compute/context.rs` does (`--gpu-architecture=sm_90a`, the CUDA include folders,
//! `-lineinfo`), to PTX and on to an sm_90a binary (the step the driver takes when it loads the
//! PTX), when an NVRTC library and CUDA headers are at hand (`CUDA_PATH`; docs/gpu.md says where
//! to get them without a CUDA install).
//!
//! What this does not cover: burn's and cubek's own kernels (matmul, reductions, fusion), which
//! the earlier GPU runs compiled; errors that only a launch raises (cube counts); and NVRTC
//! versions other than the one used here. `sparseocc check-cuda-source` runs it over every kernel
//! of this crate and of `occ-model`.

use cubecl::cuda::{CudaCompiler, CudaRuntime};
use cubecl::ir::{DeviceProperties, HardwareProperties, MemoryDeviceProperties, VectorSize};
use cubecl::prelude::*;
use cubecl::server::{
    Binding, ComputeServer, CopyDescriptor, KernelArguments, ProfileError, ProfilingToken,
    ServerCommunication, ServerError, ServerUtilities,
};
use cubecl::{Compiler, CubeDim, CubeTask};
use cubecl_common::backtrace::BackTrace;
use cubecl_common::bytes::Bytes;
use cubecl_common::device::{Device, DeviceId, DeviceService, ServerUtilitiesHandle};
use cubecl_common::future::DynFut;
use cubecl_common::profile::{ProfileDuration, TimingMethod};
use cubecl_common::stream_id::StreamId;
use cubecl_runtime::allocator::ContiguousMemoryLayoutPolicy;
use cubecl_runtime::logging::ServerLogger;
use cubecl_runtime::memory_management::{ManagedMemoryHandle, MemoryAllocationMode, MemoryUsage};
use cubecl_runtime::storage::{BytesResource, BytesStorage, ManagedResource};
use std::ffi::{CStr, CString};
use std::path::{Path, PathBuf};
use std::sync::Arc;

/// The compute capability the sources are made for: an H100 / H200 (PTX for sm_90a serves both).
pub const ARCH: u32 = 90;
/// Shared memory one cube may use on an sm_90 device (bytes; the opt-in limit cubecl-cuda checks).
pub const MAX_SHARED_BYTES: usize = 232_448;

/// The one device of [`OfflineCuda`].
#[derive(Clone, Debug, Default, PartialEq, Eq, Hash)]
pub struct OfflineDevice;

impl Device for OfflineDevice {
    fn from_id(_: DeviceId) -> Self {
        Self
    }
    fn to_id(&self) -> DeviceId {
        DeviceId {
            type_id: 0,
            index_id: 0,
        }
    }
}

/// The server of [`OfflineCuda`]: holds the device properties; allocating, moving data,
/// profiling and launching are refused (a kernel is only ever defined and compiled here, never
/// run): with an error where the trait has one, with a panic naming the request where it has none.
#[derive(Debug)]
pub struct OfflineServer {
    utilities: Arc<ServerUtilities<Self>>,
}

/// The properties cubecl-cuda reads from an H100 (SXM, 132 multiprocessors) at start-up.
fn sm90_properties() -> DeviceProperties {
    let hardware = HardwareProperties {
        load_width: 128,
        plane_size_min: 32,
        plane_size_max: 32,
        max_bindings: 1024,
        max_shared_memory_size: MAX_SHARED_BYTES,
        max_cube_count: (i32::MAX as u32, 65_535, 65_535),
        max_units_per_cube: 1024,
        max_cube_dim: (1024, 1024, 64),
        num_streaming_multiprocessors: Some(132),
        num_tensor_cores: Some(4),
        min_tensor_cores_dim: Some(8),
        num_cpu_cores: None,
        max_vector_size: VectorSize::MAX,
    };
    let memory = MemoryDeviceProperties {
        max_page_size: 20 << 30,
        alignment: 512,
    };
    DeviceProperties::new(Default::default(), memory, hardware, TimingMethod::System)
}

impl ServerCommunication for OfflineServer {
    const SERVER_COMM_ENABLED: bool = false;
}

impl DeviceService for OfflineServer {
    fn init(_: DeviceId) -> Self {
        let utilities = ServerUtilities::new(
            sm90_properties(),
            Arc::new(ServerLogger::default()),
            (),
            ContiguousMemoryLayoutPolicy::new(512),
        );
        Self {
            utilities: Arc::new(utilities),
        }
    }
    fn utilities(&self) -> ServerUtilitiesHandle {
        self.utilities.clone()
    }
}

/// Why the offline server turns a request down: it has no device memory and runs nothing.
fn refusal(what: &str) -> String {
    format!("the offline CUDA runtime only defines and compiles kernels; it cannot {what}")
}

/// The error of a refused request that can return one.
fn refused(what: &str) -> ServerError {
    ServerError::Generic {
        reason: refusal(what),
        backtrace: BackTrace::capture(),
    }
}

impl ComputeServer for OfflineServer {
    type Kernel = Box<dyn CubeTask<CudaCompiler>>;
    type Info = ();
    type MemoryLayoutPolicy = ContiguousMemoryLayoutPolicy;
    type Storage = BytesStorage;

    /// Refused with a panic (the trait gives no error path): a tensor on this runtime would hold
    /// no data, and `cuda_source` never makes one.
    fn initialize_memory(&mut self, _: ManagedMemoryHandle, _: u64, _: StreamId) {
        panic!("{}", refusal("allocate memory"))
    }
    fn logger(&self) -> Arc<ServerLogger> {
        self.utilities.logger.clone()
    }
    fn utilities(&self) -> Arc<ServerUtilities<Self>> {
        self.utilities.clone()
    }
    fn read(
        &mut self,
        _: Vec<CopyDescriptor>,
        _: StreamId,
    ) -> DynFut<Result<Vec<Bytes>, ServerError>> {
        let error = refused("read device memory");
        Box::pin(async move { Err(error) })
    }
    /// Refused with a panic (no error path; dropping the data silently would be worse).
    fn write(&mut self, _: Vec<(CopyDescriptor, Bytes)>, _: StreamId) {
        panic!("{}", refusal("write device memory"))
    }
    fn sync(&mut self, _: StreamId) -> DynFut<Result<(), ServerError>> {
        Box::pin(async { Ok(()) })
    }
    fn get_resource(
        &mut self,
        _: Binding,
        _: StreamId,
    ) -> Result<ManagedResource<BytesResource>, ServerError> {
        Err(refused("hand out device memory"))
    }
    unsafe fn launch(
        &mut self,
        _: Self::Kernel,
        _: CubeCount,
        _: KernelArguments,
        _: ExecutionMode,
        _: StreamId,
    ) {
        // No error path, and a launch that silently did nothing would pass for one that ran.
        panic!("{}", refusal("run a kernel (use `cuda_source`)"))
    }
    fn flush(&mut self, _: StreamId) -> Result<(), ServerError> {
        Ok(())
    }
    /// Nothing is ever allocated here.
    fn memory_usage(&mut self, _: StreamId) -> Result<MemoryUsage, ServerError> {
        Ok(MemoryUsage {
            number_allocs: 0,
            bytes_in_use: 0,
            bytes_padding: 0,
            bytes_reserved: 0,
        })
    }
    fn memory_cleanup(&mut self, _: StreamId) {}
    fn start_profile(&mut self, _: StreamId) -> Result<ProfilingToken, ServerError> {
        Err(refused("profile"))
    }
    fn end_profile(
        &mut self,
        _: StreamId,
        _: ProfilingToken,
    ) -> Result<ProfileDuration, ProfileError> {
        Err(ProfileError::Unknown {
            reason: refusal("profile"),
            backtrace: BackTrace::capture(),
        })
    }
    fn allocation_mode(&mut self, _: MemoryAllocationMode, _: StreamId) {}
}

/// A cubecl runtime with CUDA's compiler and target properties and an sm_90 device that runs
/// nothing: its client builds kernel definitions exactly as a `CudaRuntime` client would.
#[derive(Clone, Debug)]
pub struct OfflineCuda;

impl Runtime for OfflineCuda {
    type Compiler = CudaCompiler;
    type Server = OfflineServer;
    type Device = OfflineDevice;

    fn client(device: &Self::Device) -> ComputeClient<Self> {
        ComputeClient::load(device)
    }
    fn name(_: &ComputeClient<Self>) -> &'static str {
        "cuda-offline"
    }
    fn require_array_lengths() -> bool {
        true
    }
    fn max_cube_count() -> (u32, u32, u32) {
        CudaRuntime::max_cube_count()
    }
    fn can_read_tensor(shape: &cubecl::zspace::Shape, strides: &cubecl::zspace::Strides) -> bool {
        CudaRuntime::can_read_tensor(shape, strides)
    }
    fn target_properties() -> cubecl::ir::TargetProperties {
        CudaRuntime::target_properties()
    }
    fn enumerate_devices(_: u16, _: &()) -> Vec<DeviceId> {
        vec![OfflineDevice.to_id()]
    }
}

/// The client of the offline sm_90 device.
pub fn offline_client() -> ComputeClient<OfflineCuda> {
    OfflineCuda::client(&OfflineDevice)
}

/// The options of cubecl-cuda's compiler.
pub type CudaOptions = <CudaCompiler as Compiler>::CompilationOptions;

/// The compilation options cubecl-cuda 0.10 sets for an sm_90 device (`runtime.rs`: fast math,
/// a 32-wide plane, grid constants from sm_70, fast tanh from sm_75 with CUDA 12.8+, clusters
/// and `elect.sync` from sm_90).
pub fn sm90_options() -> CudaOptions {
    let mut features = CudaOptions::default().supports_features;
    features.fast_math = true;
    features.grid_constants = true;
    features.fast_tanh = cudarc::driver::sys::CUDA_VERSION >= 12080;
    features.clusters = true;
    features.elect_sync = true;
    CudaOptions {
        warp_size: 32,
        supports_features: features,
    }
}

/// One kernel configuration's CUDA C++, as cubecl-cuda would hand it to NVRTC.
#[derive(Clone, Debug)]
pub struct KernelSource {
    /// The kernel's entry-point name (with its element types).
    pub name: String,
    /// Units of one cube.
    pub cube_dim: CubeDim,
    /// The index type: 32- or 64-bit addressing.
    pub address_type: StorageType,
    /// Shared memory of one cube, bytes (cubecl-cuda declares it as dynamic shared memory).
    pub shared_bytes: usize,
    /// The CUDA C++ source.
    pub source: String,
}

/// Compiles one kernel configuration to CUDA C++ with cubecl-cuda's compiler and sm_90 options
/// (unchecked mode, as the launches of this project use), after the checks cubecl-cuda makes
/// before compiling: the cube's shape and unit count against the device, then the shared memory.
/// Errors name the kernel.
pub fn cuda_source(kernel: &dyn CubeKernel) -> Result<KernelSource, String> {
    let id = kernel.id();
    let props = sm90_properties();
    cubecl_runtime::validation::validate_cube_dim(&props, &id)
        .and_then(|()| cubecl_runtime::validation::validate_units(&props, &id))
        .map_err(|e| format!("{}: {e:?}", kernel.name()))?;
    let definition = kernel.define();
    let name = definition.options.kernel_name.clone();
    let compiled = CudaCompiler::default()
        .compile(
            definition,
            &sm90_options(),
            ExecutionMode::Unchecked,
            kernel.address_type(),
        )
        .map_err(|e| format!("{name}: cubecl's CUDA compiler: {e:?}"))?;
    let shared_bytes = compiled.shared_memory_size();
    if shared_bytes > MAX_SHARED_BYTES {
        return Err(format!(
            "{name}: {shared_bytes} bytes of shared memory, above the {MAX_SHARED_BYTES} of an sm_90 cube"
        ));
    }
    Ok(KernelSource {
        name,
        cube_dim: id.cube_dim,
        address_type: kernel.address_type(),
        shared_bytes,
        source: compiled.to_string(),
    })
}

/// Every cube shape `CubeDim::new` gives the client for a one-unit-per-value launch, over work
/// sizes from 1 to 2^31: the shapes an elementwise kernel of this project can be launched with.
pub fn elementwise_cube_dims<R: Runtime>(client: &ComputeClient<R>) -> Vec<CubeDim> {
    let mut dims: Vec<CubeDim> = Vec::new();
    for shift in 0..32 {
        let dim = CubeDim::new(client, 1usize << shift);
        if !dims.contains(&dim) {
            dims.push(dim);
        }
    }
    dims
}

/// The launch settings of a kernel with each of `dims`, under 32- and 64-bit addressing (the
/// launchers pick one by buffer length: `cube::address_type_of`).
pub fn launch_settings(dims: &[CubeDim]) -> Vec<KernelSettings> {
    [AddressType::U32, AddressType::U64]
        .into_iter()
        .flat_map(|address| {
            dims.iter().map(move |&dim| {
                KernelSettings::default()
                    .cube_dim(dim)
                    .address_type(address)
            })
        })
        .collect()
}

/// The names of the launchable kernels (`#[cube(launch...)]` functions) declared in a Rust source
/// file: what a `cuda_source_kernels` list beside them must cover. Each kernel file exposes its own
/// text for this (`KERNEL_SOURCE`), so `check-cuda-source` finds a kernel left off its list.
pub fn launchable_kernels(source: &str) -> Vec<&str> {
    let mut names = Vec::new();
    let mut rest = source;
    while let Some(at) = rest.find("#[cube(launch") {
        rest = &rest[at..];
        let Some(f) = rest.find("fn ") else { break };
        let name = rest[f + 3..]
            .split(|c: char| !(c.is_alphanumeric() || c == '_'))
            .next()
            .unwrap_or_default();
        names.push(name);
        rest = &rest[f + 3..];
    }
    names
}

/// What NVRTC made of one source.
#[derive(Clone, Debug)]
pub struct NvrtcOutput {
    /// The PTX text (what cubecl-cuda loads).
    pub ptx: String,
    /// Size of the sm_90a binary NVRTC assembled from it (the driver's step on load), bytes.
    pub cubin_bytes: usize,
    /// NVRTC's log (warnings), if any.
    pub log: String,
}

/// NVRTC, loaded from the system's library path (cudarc's dynamic loading: `libnvrtc.so`,
/// `libnvrtc.so.13`, ...), with the CUDA headers of an include folder.
#[derive(Clone, Debug)]
pub struct Nvrtc {
    include: PathBuf,
    version: (i32, i32),
}

impl Nvrtc {
    /// NVRTC with the headers under `cuda_path/include` (and `include/cccl` when present), or why
    /// it cannot be used: no NVRTC library on the library path, or no `cuda_runtime.h` there.
    pub fn new(cuda_path: &Path) -> Result<Self, String> {
        let include = cuda_path.join("include");
        if !include.join("cuda_runtime.h").is_file() {
            return Err(format!(
                "{}: no cuda_runtime.h (CUDA_PATH must hold the CUDA headers in include/)",
                include.display()
            ));
        }
        // SAFETY: only tries to open the library by its candidate names.
        if !unsafe { cudarc::nvrtc::sys::is_culib_present() } {
            return Err("no NVRTC library (libnvrtc.so*) on the library path".to_string());
        }
        let (mut major, mut minor) = (0, 0);
        // SAFETY: the library is present; both pointers are valid for the call.
        let status = unsafe { cudarc::nvrtc::sys::nvrtcVersion(&mut major, &mut minor) };
        status
            .result()
            .map_err(|e| format!("nvrtcVersion: {e:?}"))?;
        Ok(Self {
            include,
            version: (major, minor),
        })
    }

    /// NVRTC from `CUDA_PATH` (as cubecl-cuda reads it), or why not.
    pub fn from_env() -> Result<Self, String> {
        let path =
            std::env::var_os("CUDA_PATH").ok_or_else(|| "CUDA_PATH is not set".to_string())?;
        Self::new(Path::new(&path))
    }

    /// NVRTC's version, `(major, minor)`.
    pub fn version(&self) -> (i32, i32) {
        self.version
    }

    /// The options cubecl-cuda 0.10 passes to NVRTC for an sm_90 device.
    fn options(&self) -> Vec<String> {
        let mut options = vec![
            format!("--gpu-architecture=sm_{ARCH}a"),
            format!("--include-path={}", self.include.display()),
            "-lineinfo".to_string(),
        ];
        let cccl = self.include.join("cccl");
        if cccl.is_dir() {
            options.push(format!("--include-path={}", cccl.display()));
        }
        options
    }

    /// Compiles one source to PTX and an sm_90a binary; the error is NVRTC's log.
    pub fn compile(&self, source: &KernelSource) -> Result<NvrtcOutput, String> {
        use cudarc::nvrtc::{result, sys};
        let name = &source.name;
        let text = CString::new(source.source.as_str())
            .map_err(|_| format!("{name}: the source holds a NUL byte"))?;
        let file = CString::new(format!("{name}.cu")).unwrap_or_default();
        let program = result::create_program(&text, Some(&file))
            .map_err(|e| format!("{name}: nvrtcCreateProgram: {e:?}"))?;
        let log = |program| {
            // SAFETY: `program` is a live program.
            unsafe { result::get_program_log(program) }
                .map(|raw| {
                    // SAFETY: NVRTC's log is NUL-terminated.
                    unsafe { CStr::from_ptr(raw.as_ptr()) }
                        .to_string_lossy()
                        .trim()
                        .to_string()
                })
                .unwrap_or_default()
        };
        // SAFETY: `program` is a live program; the options are plain strings.
        let compiled = unsafe { result::compile_program(program, &self.options()) };
        let outcome = match compiled {
            Err(e) => Err(format!("{name}: NVRTC: {e:?}\n{}", log(program))),
            Ok(()) => {
                // SAFETY: the program compiled; the buffer is sized by NVRTC.
                let ptx = unsafe { result::get_ptx(program) }
                    .map(|raw| {
                        // SAFETY: PTX is NUL-terminated text.
                        unsafe { CStr::from_ptr(raw.as_ptr()) }
                            .to_string_lossy()
                            .into_owned()
                    })
                    .map_err(|e| format!("{name}: nvrtcGetPTX: {e:?}"));
                let mut cubin_bytes = 0usize;
                // SAFETY: the program compiled for a real architecture (sm_90a), so it holds a
                // binary; the pointer is valid for the call.
                let cubin = unsafe { sys::nvrtcGetCUBINSize(program, &mut cubin_bytes) }
                    .result()
                    .map_err(|e| format!("{name}: nvrtcGetCUBINSize: {e:?}"));
                ptx.and_then(|ptx| {
                    cubin.map(|()| NvrtcOutput {
                        ptx,
                        cubin_bytes,
                        log: log(program),
                    })
                })
            }
        };
        // SAFETY: the program is not used after this.
        let _ = unsafe { result::destroy_program(program) };
        outcome
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_offline_server_answers_what_it_cannot_do_with_an_error() {
        let client = offline_client();
        let usage = client
            .memory_usage()
            .expect("memory usage of the offline server");
        assert_eq!(
            (
                usage.number_allocs,
                usage.bytes_in_use,
                usage.bytes_reserved
            ),
            (0, 0, 0)
        );
        let Err(error) = client.profile(|| (), "nothing") else {
            panic!("profiling on the offline server must fail");
        };
        assert!(
            format!("{error:?}").contains("cannot profile"),
            "the error names the refused request: {error:?}"
        );
    }

    #[test]
    fn the_offline_device_is_an_sm90_with_32_wide_planes() {
        let client = offline_client();
        let dims: Vec<(u32, u32, u32)> = elementwise_cube_dims(&client)
            .into_iter()
            .map(|d| (d.x, d.y, d.z))
            .collect();
        assert_eq!(dims, [(32, 1, 1), (32, 2, 1), (32, 4, 1), (32, 8, 1)]);
        assert_eq!(
            client.properties().hardware.max_shared_memory_size,
            MAX_SHARED_BYTES
        );
    }

    #[test]
    fn every_kernel_of_the_crate_has_cuda_source() {
        let client = offline_client();
        let float = f32::as_type_native_unchecked().storage_type();
        let int = i32::as_type_native_unchecked().storage_type();
        let kernels = crate::cube::cuda_source_kernels(&client, float, int);
        assert!(!kernels.is_empty());
        let mut conv_shared = None;
        for k in &kernels {
            let s = cuda_source(k.as_ref()).unwrap();
            assert!(s.source.contains("__global__"), "{}", s.name);
            assert!(s.source.contains(&s.name), "{}", s.name);
            if s.name.starts_with("sparse_conv_kernel") {
                conv_shared = Some(s.shared_bytes);
            }
        }
        // The forward convolution stages a 64 x 16 block of inputs, a 16 x 32 block of weights
        // (f32) and 64 neighbour rows (u32) per cube.
        assert_eq!(conv_shared, Some((64 * 16 + 16 * 32) * 4 + 64 * 4));
    }

    /// Runs where NVRTC is at hand (`CUDA_PATH` and libnvrtc, as `scripts/cuda_source_check.sh`
    /// sets them up); says it skipped otherwise.
    #[test]
    fn nvrtc_compiles_the_convolution_and_reports_errors() {
        let nvrtc = match Nvrtc::from_env() {
            Ok(n) => n,
            Err(why) => {
                eprintln!("skipped: nvrtc_compiles_the_convolution_and_reports_errors: {why}");
                return;
            }
        };
        let client = offline_client();
        let float = f32::as_type_native_unchecked().storage_type();
        let int = i32::as_type_native_unchecked().storage_type();
        let kernels = crate::cube::cuda_source_kernels(&client, float, int);
        let conv = kernels
            .iter()
            .map(|k| cuda_source(k.as_ref()).unwrap())
            .find(|s| s.name.starts_with("sparse_conv_kernel"))
            .unwrap();
        let out = nvrtc.compile(&conv).unwrap();
        assert!(out.ptx.contains(".target sm_90a"), "{}", &out.ptx[..300]);
        assert!(out.ptx.contains(&conv.name));
        assert!(out.cubin_bytes > 0);
        let mut bad = conv.clone();
        bad.source.push_str("\nnot_a_type x;\n");
        let e = nvrtc.compile(&bad).unwrap_err();
        assert!(e.contains(&conv.name) && e.contains("not_a_type"), "{e}");
    }

    #[test]
    fn every_launchable_kernel_of_the_crate_is_listed() {
        let declared = launchable_kernels(crate::cube::KERNEL_SOURCE);
        assert_eq!(declared.len(), 7, "{declared:?}");
        assert!(declared.contains(&"sparse_conv_kernel"), "{declared:?}");
        let client = offline_client();
        let float = f32::as_type_native_unchecked().storage_type();
        let int = i32::as_type_native_unchecked().storage_type();
        let listed: Vec<String> = crate::cube::cuda_source_kernels(&client, float, int)
            .iter()
            .map(|k| k.define().options.kernel_name)
            .collect();
        for name in declared {
            assert!(
                listed.iter().any(|l| l.starts_with(&format!("{name}_"))),
                "{name}"
            );
        }
    }

    #[test]
    fn nvrtc_without_headers_says_where_it_looked() {
        let dir = std::env::temp_dir().join(format!("occ-sparse-no-cuda-{}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        let e = Nvrtc::new(&dir).unwrap_err();
        assert!(e.contains("cuda_runtime.h"), "{e}");
        assert!(
            e.contains(&dir.join("include").display().to_string()),
            "{e}"
        );
        let _ = std::fs::remove_dir_all(&dir);
    }
}
