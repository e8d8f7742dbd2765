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

use burn::prelude::*;
use std::cell::RefCell;
use std::time::Instant;

/// Start of the current stage and the `(stage, ms)` records.
type Records = Option<(Instant, Vec<(String, f64)>)>;

/// Whether `SPARSEOCC_TRACE` is set (read once).
fn trace() -> bool {
    static TRACE: std::sync::OnceLock<bool> = std::sync::OnceLock::new();
    *TRACE.get_or_init(|| std::env::var_os("SPARSEOCC_TRACE").is_some())
}

thread_local! {
    static TRACE_CLOCK: std::cell::Cell<Option<Instant>> = const { std::cell::Cell::new(None) };
    static PROFILE: RefCell<Records> = const { RefCell::new(None) };
}

/// Turns stage timing on (clearing earlier records) or off for this thread.
pub fn enable(on: bool) {
    PROFILE.with(|p| *p.borrow_mut() = on.then(|| (Instant::now(), Vec::new())));
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

/// Ends stage `name`: synchronises on `done` and records the milliseconds since the last mark.
pub fn mark<B: Backend, const D: usize>(name: &str, done: &Tensor<B, D>) {
    let on = PROFILE.with(|p| p.borrow().is_some());
    if !on && !trace() {
        return;
    }
    if done.shape().num_elements() > 0 {
        let s: f32 = done.clone().sum().into_scalar().elem();
        std::hint::black_box(s);
    }
    if trace() {
        let now = Instant::now();
        let since = TRACE_CLOCK.with(|c| c.replace(Some(now)));
        let ms = since.map_or(0.0, |t| (now - t).as_secs_f64() * 1e3);
        eprintln!("[trace] {name}: {ms:.1} ms, {:?}", done.dims());
    }
    PROFILE.with(|p| {
        if let Some((t, v)) = p.borrow_mut().as_mut() {
            v.push((name.to_string(), t.elapsed().as_secs_f64() * 1e3));
            *t = Instant::now();
        }
    });
}

/// The recorded `(stage, ms)` pairs since [`enable`], cleared.
pub fn take() -> Vec<(String, f64)> {
    PROFILE.with(|p| {
        p.borrow_mut()
            .as_mut()
            .map(|(_, v)| std::mem::take(v))
            .unwrap_or_default()
    })
}

/// A finer mark for `SPARSEOCC_TRACE` only (a layer inside a stage): synchronises and prints when
/// tracing, does nothing otherwise, and never enters the stage records.
pub fn trace_mark<B: Backend, const D: usize>(name: &str, done: &Tensor<B, D>) {
    if !trace() {
        return;
    }
    if done.shape().num_elements() > 0 {
        let s: f32 = done.clone().sum().into_scalar().elem();
        std::hint::black_box(s);
    }
    let now = Instant::now();
    let since = TRACE_CLOCK.with(|c| c.replace(Some(now)));
    let ms = since.map_or(0.0, |t| (now - t).as_secs_f64() * 1e3);
    eprintln!("[trace]   {name}: {ms:.1} ms, {:?}", done.dims());
}
