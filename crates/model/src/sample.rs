//! Bilinear feature sampling at normalized image coordinates (PyTorch
//! `F.grid_sample(features, grid, mode='bilinear', padding_mode='zeros', align_corners=False)`),
//! used by the deformable cross attention.
//!
//! burn 0.21's `Tensor::grid_sample_2d` with `GridSampleOptions::default()` has exactly these
//! semantics (mode `Bilinear`, padding `Zeros`, `align_corners = false`: x = −1 is the left edge
//! of the left pixel, pixel coordinate `((x + 1)·W − 1) / 2`; corners outside the map contribute 0).
//! On `Autodiff<_>` backends burn composes the op from differentiable tensor ops (gather, mask,
//! arithmetic), which gives the gradients w.r.t. both the features and the grid; the test
//! `tests/grid_sample_fixture.rs` checks output and both gradients against PyTorch.

use burn::prelude::*;
use burn::tensor::ops::{GridSampleOptions, GridSamplePaddingMode, InterpolateMode};

/// Samples `features` `[N, C, H, W]` at `grid` `[N, Hg, Wg, 2]` (last axis `(x, y)` in `[-1, 1]`,
/// `(-1, -1)` = top-left corner of the top-left pixel) with bilinear interpolation and zero padding,
/// `align_corners = false`. Returns `[N, C, Hg, Wg]`. Differentiable w.r.t. both inputs.
pub fn bilinear_sample<B: Backend>(features: Tensor<B, 4>, grid: Tensor<B, 4>) -> Tensor<B, 4> {
    let options = GridSampleOptions::new(InterpolateMode::Bilinear)
        .with_padding_mode(GridSamplePaddingMode::Zeros)
        .with_align_corners(false);
    features.grid_sample_2d(grid, options)
}
