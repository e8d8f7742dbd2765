//! Opt-in per-stage timing of a forward pass (for `sparseocc bench`).
//!
//! With the environment variable `SPARSEOCC_TRACE` set, every mark also synchronises and prints
//! the stage and its milliseconds to stderr as it happens (to see where a slow or stuck pass is,
//! e.g. on a GPU where the first pass compiles kernels).
//!
//! When enabled on the current thread, [`mark`] waits for a tensor of the stage just finished
//! (reading back one scalar, so on a GPU every queued kernel before it has run) and records the
//! wall time since the previous mark. Disabled (the default), it costs nothing and does not
//! synchronise.
//!
//! The same switch counts multiply-adds (MACs): layers call [`add_macs`] (or the helpers [`linear`],
//! [`add_conv2d`], [`add_matmul`]) with the work of what they just ran, computed from shapes and
//! sizes on the host, and the sparse convolutions count `pairs * c_in * c_out` in occ-sparse's own
//! counter ([`occ_sparse::flops`]), drained here. Each [`mark`] attributes the MACs counted since the
//! previous mark to its stage, as it does the time. Disabled, [`add_macs`] reads one thread-local
//! flag and returns (no allocation, no synchronisation, no shape arithmetic in [`linear`]).

use crate::kernels::ModelBackend;
use burn::nn::Linear;
use burn::prelude::*;
use std::cell::{Cell, RefCell};
use std::time::Instant;

/// A stage of a forward pass, as [`mark`] ends it and `sparseocc bench` reports it.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash)]
pub enum Stage {
    /// The image encoder (ResNet + FPN): `encoder`.
    Encoder,
    /// The LSS view transform (SparseOcc, dense baseline): `lss`.
    Lss,
    /// SparseOcc's latent propagator, once per level: `propagator`.
    Propagator,
    /// SparseOcc's sparse feature pyramid: `pyramid`.
    Pyramid,
    /// SparseOcc's mask head: `mask_head`.
    MaskHead,
    /// The dense baseline's 3D convolutions: `dense_encoder`.
    DenseEncoder,
    /// SparseOcc++'s sparse anchor generation: `anchors`.
    Anchors,
    /// SparseOcc++'s SCF heads and geometry-guided propagation: `scf+propagation`.
    ScfPropagation,
    /// SparseOcc++'s DCA on the completed voxels: `dca`.
    Dca,
    /// SparseOcc++'s sparse U-Net: `unet`.
    Unet,
    /// The classifier (SparseOcc++, dense baseline): `head`.
    Head,
}

impl Stage {
    /// The stage's name in traces and benchmark tables.
    pub fn as_str(self) -> &'static str {
        match self {
            Self::Encoder => "encoder",
            Self::Lss => "lss",
            Self::Propagator => "propagator",
            Self::Pyramid => "pyramid",
            Self::MaskHead => "mask_head",
            Self::DenseEncoder => "dense_encoder",
            Self::Anchors => "anchors",
            Self::ScfPropagation => "scf+propagation",
            Self::Dca => "dca",
            Self::Unet => "unet",
            Self::Head => "head",
        }
    }
}

/// One stage of a profiled pass: which, wall milliseconds and multiply-adds.
#[derive(Clone, Debug, PartialEq)]
pub struct StageRecord {
    /// The stage (as given to [`mark`]).
    pub stage: Stage,
    /// Wall time since the previous mark (ms).
    pub ms: f64,
    /// Multiply-adds counted since the previous mark.
    pub macs: u64,
}

/// Start of the current stage and the stage records.
type Records = Option<(Instant, Vec<StageRecord>)>;

/// Op name under which the sparse convolutions' MACs (counted by occ-sparse) are reported.
pub const SPARSE_CONV_OP: &str = "sparse_conv";

/// Whether `SPARSEOCC_TRACE` is set (read once).
fn trace() -> bool {
    static TRACE: std::sync::OnceLock<bool> = std::sync::OnceLock::new();
    *TRACE.get_or_init(|| std::env::var_os("SPARSEOCC_TRACE").is_some())
}

/// With `SPARSEOCC_TRACE=sums`, the trace lines also give each tensor's sum and sum of absolute
/// values: comparing them between two backends finds the first stage where the backends part.
fn trace_sums<B: Backend, const D: usize>(t: &Tensor<B, D>) -> String {
    static SUMS: std::sync::OnceLock<bool> = std::sync::OnceLock::new();
    let on = *SUMS.get_or_init(|| {
        std::env::var("SPARSEOCC_TRACE").is_ok_and(|v| v.eq_ignore_ascii_case("sums"))
    });
    if !on || t.shape().num_elements() == 0 {
        return String::new();
    }
    let s: f64 = t.clone().sum().into_scalar().elem();
    let a: f64 = t.clone().abs().sum().into_scalar().elem();
    format!(", sum {s:.6e}, |sum| {a:.6e}")
}

/// Stage outputs kept by [`capture`]: name and values, in order.
pub type Captures = Vec<(String, Vec<f32>)>;

thread_local! {
    /// Stage outputs read back at every mark while [`capture`] is on (to compare two backends
    /// stage by stage: `sparseocc check-backend`).
    static CAPTURE: RefCell<Option<Captures>> = const { RefCell::new(None) };
    static TRACE_CLOCK: std::cell::Cell<Option<Instant>> = const { std::cell::Cell::new(None) };
    static PROFILE: RefCell<Records> = const { RefCell::new(None) };
    static MACS_ON: Cell<bool> = const { Cell::new(false) };
    /// MACs counted since the last mark (model side; the sparse convs' are in occ-sparse's counter).
    static STAGE_MACS: Cell<u64> = const { Cell::new(0) };
    /// MACs per op since [`enable`] / [`take_ops`].
    static OPS: RefCell<Vec<(&'static str, u64)>> = const { RefCell::new(Vec::new()) };
}

/// Turns stage timing and MAC counting on (clearing earlier records and counts) or off for this
/// thread.
pub fn enable(on: bool) {
    PROFILE.with(|p| *p.borrow_mut() = on.then(|| (Instant::now(), Vec::new())));
    MACS_ON.with(|c| c.set(on));
    STAGE_MACS.with(|c| c.set(0));
    OPS.with(|o| o.borrow_mut().clear());
    occ_sparse::flops::enable(on);
}

/// Whether MAC counting is on for this thread.
#[inline]
pub fn counting() -> bool {
    MACS_ON.with(Cell::get)
}

/// Adds `macs` multiply-adds of kind `op` to the current stage (when profiling is on).
#[inline]
pub fn add_macs(op: &'static str, macs: u64) {
    if counting() {
        record(op, macs);
    }
}

fn record(op: &'static str, macs: u64) {
    STAGE_MACS.with(|c| c.set(c.get().saturating_add(macs)));
    OPS.with(|o| {
        let mut o = o.borrow_mut();
        match o.iter_mut().find(|(k, _)| *k == op) {
            Some(e) => e.1 = e.1.saturating_add(macs),
            None => o.push((op, macs)),
        }
    });
}

/// Moves the sparse convolutions' count (occ-sparse's counter) into this one.
fn drain_sparse() {
    let n = occ_sparse::flops::take();
    if n > 0 {
        record(SPARSE_CONV_OP, n);
    }
}

/// MACs of a matrix product `[batch, m, k] x [batch, k, n]`, counted as op `op`.
#[inline]
pub fn add_matmul(op: &'static str, batch: usize, m: usize, k: usize, n: usize) {
    if counting() {
        record(op, (batch * m * k * n) as u64);
    }
}

/// MACs of a 2D convolution with weight `[C_out, C_in / groups, kh, kw]` that produced an output of
/// `out_elements` values (`N * C_out * H_out * W_out`): each output value takes
/// `C_in / groups * kh * kw` multiply-adds.
#[inline]
pub fn add_conv2d(weight_dims: [usize; 4], out_elements: usize) {
    if counting() {
        let [_, cin_g, kh, kw] = weight_dims;
        record("conv2d", (out_elements * cin_g * kh * kw) as u64);
    }
}

/// `lin.forward(x)`, counting its `rows * d_in * d_out` multiply-adds (the bias is not a MAC).
#[inline]
pub fn linear<B: occ_sparse::SparseConvBackend, const D: usize>(
    lin: &Linear<B>,
    x: Tensor<B, D>,
) -> Tensor<B, D> {
    count_linear(lin, &x);
    crate::kernels::linear_bucketed(lin, x, B::ROW_BUCKET)
}

/// [`linear`] through the backend's [`ModelBackend::row_linear`] (on the CPU a host GEMM with the
/// bias fused into its output), counted the same.
#[inline]
pub fn row_linear<B: ModelBackend, const D: usize>(
    lin: &Linear<B>,
    x: Tensor<B, D>,
) -> Tensor<B, D> {
    count_linear(lin, &x);
    B::row_linear(lin, x, false)
}

/// `relu(lin.forward(x))` through [`ModelBackend::row_linear`] (on the CPU the ReLU is fused too),
/// counted as [`linear`].
#[inline]
pub fn row_linear_relu<B: ModelBackend, const D: usize>(
    lin: &Linear<B>,
    x: Tensor<B, D>,
) -> Tensor<B, D> {
    count_linear(lin, &x);
    B::row_linear(lin, x, true)
}

fn count_linear<B: Backend, const D: usize>(lin: &Linear<B>, x: &Tensor<B, D>) {
    if counting() {
        let [d_in, d_out] = lin.weight.dims();
        let rows = x.shape().num_elements() / d_in.max(1);
        record("linear", (rows * d_in * d_out) as u64);
    }
}

/// Turns the capture of stage outputs on (clearing earlier ones) or off for this thread: every
/// [`mark`] and [`trace_mark`] then reads its tensor back to the host. For diagnosis only (it
/// synchronises and copies every stage output).
pub fn capture(on: bool) {
    CAPTURE.with(|c| *c.borrow_mut() = on.then(Vec::new));
}

/// The stage outputs captured since [`capture`] was turned on, cleared.
pub fn take_captures() -> Captures {
    CAPTURE.with(|c| {
        c.borrow_mut()
            .as_mut()
            .map(std::mem::take)
            .unwrap_or_default()
    })
}

fn capturing() -> bool {
    CAPTURE.with(|c| c.borrow().is_some())
}

fn capture_push<B: Backend, const D: usize>(name: &str, t: &Tensor<B, D>) {
    let values = t
        .to_data()
        .convert::<f32>()
        .to_vec::<f32>()
        .unwrap_or_default();
    CAPTURE.with(|c| {
        if let Some(v) = c.borrow_mut().as_mut() {
            v.push((name.to_string(), values));
        }
    });
}

/// Restarts the clock (call at the start of a forward pass).
pub fn start() {
    if trace() {
        TRACE_CLOCK.with(|c| c.set(Some(Instant::now())));
    }
    PROFILE.with(|p| {
        if let Some((t, _)) = p.borrow_mut().as_mut() {
            *t = Instant::now();
        }
    });
}

/// Waits until `done` (and everything queued before it on its device) is computed: the backend's
/// own sync, which on the cubecl backends drains the fusion stream and waits for the device. Not a
/// reduction of `done`, whose kernel configuration (cubecl's shared sum) follows the element count
/// and would compile anew for every frame's voxel count.
fn sync<B: Backend, const D: usize>(done: &Tensor<B, D>) {
    // An error here is the device's and shows again on the next read of a result.
    let _ = B::sync(&done.device());
}

/// Ends `stage`: synchronises on `done` and records the milliseconds since the last mark.
pub fn mark<B: Backend, const D: usize>(stage: Stage, done: &Tensor<B, D>) {
    if capturing() {
        capture_push(stage.as_str(), done);
    }
    let on = PROFILE.with(|p| p.borrow().is_some());
    if !on && !trace() {
        return;
    }
    sync(done);
    if trace() {
        let now = Instant::now();
        let since = TRACE_CLOCK.with(|c| c.replace(Some(now)));
        let ms = since.map_or(0.0, |t| (now - t).as_secs_f64() * 1e3);
        eprintln!(
            "[trace] {}: {ms:.1} ms, {:?}{}",
            stage.as_str(),
            done.dims(),
            trace_sums(done)
        );
    }
    if !on {
        return;
    }
    // The stage's time ends at the sync; reading its counts (device pair counts of deferred maps)
    // is outside it and outside the next one.
    let ms = PROFILE.with(|p| {
        p.borrow()
            .as_ref()
            .map(|(t, _)| t.elapsed().as_secs_f64() * 1e3)
    });
    drain_sparse();
    let macs = STAGE_MACS.with(|c| c.replace(0));
    PROFILE.with(|p| {
        if let (Some((t, v)), Some(ms)) = (p.borrow_mut().as_mut(), ms) {
            v.push(StageRecord { stage, ms, macs });
            *t = Instant::now();
        }
    });
}

/// The recorded stages since [`enable`], cleared.
pub fn take() -> Vec<StageRecord> {
    PROFILE.with(|p| {
        p.borrow_mut()
            .as_mut()
            .map(|(_, v)| std::mem::take(v))
            .unwrap_or_default()
    })
}

/// The MACs counted since the last [`mark`] (work outside any marked stage, or a pass without
/// marks), cleared.
pub fn take_unmarked_macs() -> u64 {
    drain_sparse();
    STAGE_MACS.with(|c| c.replace(0))
}

/// The MACs per op (`"linear"`, `"conv2d"`, `"sparse_conv"`, `"dca_sampling"`, ...) since
/// [`enable`] or the last call, cleared.
pub fn take_ops() -> Vec<(&'static str, u64)> {
    drain_sparse();
    OPS.with(|o| std::mem::take(&mut *o.borrow_mut()))
}

/// A finer mark for `SPARSEOCC_TRACE` and [`capture`] only (a layer inside a stage): synchronises
/// and prints when tracing, does nothing otherwise, and never enters the stage records.
pub fn trace_mark<B: Backend, const D: usize>(name: &str, done: &Tensor<B, D>) {
    if capturing() {
        capture_push(name, done);
    }
    if !trace() {
        return;
    }
    sync(done);
    let now = Instant::now();
    let since = TRACE_CLOCK.with(|c| c.replace(Some(now)));
    let ms = since.map_or(0.0, |t| (now - t).as_secs_f64() * 1e3);
    eprintln!(
        "[trace]   {name}: {ms:.1} ms, {:?}{}",
        done.dims(),
        trace_sums(done)
    );
}

#[cfg(test)]
mod tests {
    use super::*;
    use burn::nn::conv::Conv2dConfig;
    use burn::nn::{LinearConfig, PaddingConfig2d};

    type B = burn::backend::NdArray<f32>;

    #[test]
    fn linear_counts_rows_times_in_times_out() {
        let device = Default::default();
        let lin = LinearConfig::new(6, 5).init::<B>(&device);
        enable(false);
        linear(&lin, Tensor::<B, 2>::ones([7, 6], &device));
        assert_eq!(take_unmarked_macs(), 0, "nothing is counted when off");
        enable(true);
        // A rank-3 input: 2 x 3 = 6 rows of 6 inputs.
        let y = linear(&lin, Tensor::<B, 3>::ones([2, 3, 6], &device));
        assert_eq!(y.dims(), [2, 3, 5]);
        assert_eq!(take_unmarked_macs(), 6 * 6 * 5);
        enable(false);
    }

    #[test]
    fn conv2d_counts_output_values_times_kernel_and_input_channels() {
        let device = Default::default();
        // 3 -> 4 channels, 3x3, stride 2, padding 1, on 1 x 3 x 9 x 7: output 4 x 5 x 4.
        let conv = Conv2dConfig::new([3, 4], [3, 3])
            .with_stride([2, 2])
            .with_padding(PaddingConfig2d::Explicit(1, 1, 1, 1))
            .init::<B>(&device);
        enable(true);
        let y = crate::kernels::conv2d_host::conv_bn(
            &conv,
            None,
            Tensor::<B, 4>::ones([1, 3, 9, 7], &device),
            true,
        );
        assert_eq!(y.dims(), [1, 4, 5, 4]);
        assert_eq!(take_unmarked_macs(), (4 * 5 * 4) * 3 * 3 * 3);
        // Grouped: 4 -> 4 channels in 2 groups, 1x1, on 2 x 4 x 2 x 3: each output value takes 2 MACs.
        let grouped = Conv2dConfig::new([4, 4], [1, 1])
            .with_groups(2)
            .init::<B>(&device);
        crate::kernels::conv2d_host::conv_bn(
            &grouped,
            None,
            Tensor::<B, 4>::ones([2, 4, 2, 3], &device),
            false,
        );
        assert_eq!(take_unmarked_macs(), (2 * 4 * 2 * 3) * 2);
        enable(false);
    }

    #[test]
    fn marks_attribute_macs_and_ops_to_stages() {
        let device = Default::default();
        let lin = LinearConfig::new(4, 2).init::<B>(&device);
        enable(true);
        let y = linear(&lin, Tensor::<B, 2>::ones([3, 4], &device));
        add_matmul("attention", 2, 3, 4, 5);
        mark(Stage::Encoder, &y);
        add_macs("dca_sampling", 11);
        mark(Stage::Head, &y);
        add_conv2d([8, 2, 3, 3], 10);
        let stages = take();
        assert_eq!(stages.len(), 2);
        assert_eq!(
            (stages[0].stage, stages[0].macs),
            (Stage::Encoder, 3 * 4 * 2 + 2 * 3 * 4 * 5)
        );
        assert_eq!((stages[1].stage, stages[1].macs), (Stage::Head, 11));
        assert!(stages.iter().all(|s| s.ms >= 0.0));
        assert_eq!(take_unmarked_macs(), 10 * 2 * 3 * 3);
        let mut ops = take_ops();
        ops.sort();
        assert_eq!(
            ops,
            vec![
                ("attention", 120),
                ("conv2d", 180),
                ("dca_sampling", 11),
                ("linear", 24)
            ]
        );
        enable(false);
        add_macs("linear", 5);
        mark(Stage::Dca, &y);
        assert!(take().is_empty());
        assert_eq!(take_unmarked_macs(), 0);
    }
}
