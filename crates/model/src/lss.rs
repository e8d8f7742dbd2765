//! Lift-Splat-Shoot view transform (paper Sec. 3.1; docs/reference_models.md §1 "view transform", docs/losses.md §6).
//!
//! Image features `[B*V, C_in, h, w]` at `stride` input pixels go through a depth net that predicts,
//! per feature pixel, a distribution over `D` depth bins and `C` context channels. Every
//! (pixel, depth bin) pair is a frustum point; it is lifted to the LiDAR frame through the inverse of
//! [`CameraInput::img_from_lidar`](crate::CameraInput) and its depth-weighted context feature is
//! sum-pooled into the voxel that contains it ("splat").
//!
//! Choices where the reference is heavier or silent (all documented, simplified on purpose):
//! - **Depth net.** The official BEVDepth `DepthNet` is 3x3 reduce conv + camera-aware MLP/SE + (3
//!   BasicBlocks + ASPP + DCN) depth branch. Here: 3x3 reduce conv + BN + ReLU, then a camera-aware
//!   SE gate per branch (an MLP on the flattened camera parameters producing a sigmoid channel scale),
//!   then depth = 3x3 conv + BN + ReLU + 1x1 conv to `D` logits, context = 1x1 conv to `C` channels.
//! - **Camera parameters** (21 values): the intrinsic part of `img_from_cam = img_from_lidar ·
//!   cam_from_lidar⁻¹` (3x3, row 0 divided by the input width, row 1 by the input height, so they are
//!   O(1)), and the top 3x4 of `cam_from_lidar` (rotation, translation in metres). BEVDepth also
//!   batch-normalises this vector; that is skipped (batch statistics over one or two cameras are
//!   degenerate).
//! - **Frustum pixels.** Feature pixel `(i, j)` at stride `s` is placed at the centre of the `s x s`
//!   input patch it summarises: `u = j·s + (s-1)/2`, `v = i·s + (s-1)/2` (pixel centres at integer
//!   coordinates, as the projection `u = round(...)` of docs/formats.md §2.7 assumes). BEVDepth uses
//!   `linspace(0, W-1, w)`, which differs by a fraction of a stride.
//! - **Depth bins** from `dbound = [min, max, step]`: `d_k = min + k·step`, `k < D = ceil((max-min)/step)`
//!   (`torch.arange`, D = 112 for `[2, 58, 0.5]`).
//! - **Depth targets**: LiDAR points projected with `img_from_lidar`, pixel `round(u), round(v)` inside
//!   the input image, the minimum depth per `s x s` patch; target bin
//!   `k = floor((d - (min - step/2)) / step)` (the bin whose centre `d_k` is nearest), no target when
//!   `k ∉ [0, D)`. The official code (docs/losses.md §6) uses `floor((d - (2.0 - 0.25))/0.5)` followed by dropping one-hot
//!   column 0, which is one bin lower; here the target bin is the bin where the frustum point sits.
//! - **Non-empty voxels**: the sites hit by at least one frustum point (a host-side count, so a
//!   feature that is exactly zero by chance still counts), as the paper's "gathering non-empty voxels".

use crate::batch::Batch;
use crate::error::ModelError;
use crate::kernels::conv2d_host::conv_bn;
use crate::kernels::ModelBackend;
use burn::nn::conv::{Conv2d, Conv2dConfig};
use burn::nn::{BatchNorm, BatchNormConfig, Linear, LinearConfig, PaddingConfig2d};
use burn::prelude::*;
use burn::tensor::activation::{relu, sigmoid, softmax};
use burn::tensor::TensorData;
use occ_geometry::{mat4_inverse, mat4_mul, Mat4, VoxelGrid};
use occ_sparse::{gather_rows, scatter_add_rows, RowPlan, SparseConvBackend, SparseTensor};
use std::sync::Arc;

/// Number of camera-parameter values fed to the camera-aware gates.
pub const CAM_PARAM_CHANNELS: usize = 21;

/// Configuration of [`Lss`].
#[derive(Config, Debug)]
pub struct LssConfig {
    /// Image feature channels in (640 for the official KITTI SECONDFPN).
    pub in_channels: usize,
    /// Context channels out, i.e. voxel feature channels (numC_Trans, 128 officially).
    pub out_channels: usize,
    /// Hidden channels of the depth net.
    #[config(default = 256)]
    pub mid_channels: usize,
    /// Depth bins `[min, max, step]` in metres.
    #[config(default = "[2.0, 58.0, 0.5]")]
    pub dbound: [f64; 3],
    /// LSS voxel size in full-resolution voxels (2: a 1/2-resolution volume, 0.4 m on SemanticKITTI).
    #[config(default = 2)]
    pub downsample: usize,
    /// Condition the depth and context branches on the camera parameters (SE-style gates).
    #[config(default = true)]
    pub camera_aware: bool,
}

impl LssConfig {
    /// Number of depth bins `D`.
    pub fn num_bins(&self) -> usize {
        num_bins(self.dbound)
    }

    /// Initialises the module; errors on an invalid `dbound`, zero channels or zero downsample.
    pub fn init<B: Backend>(&self, device: &B::Device) -> Result<Lss<B>, ModelError> {
        check_dbound(self.dbound)?;
        if self.in_channels == 0 || self.out_channels == 0 || self.mid_channels == 0 {
            return Err(ModelError::Config(format!(
                "lss.rs: channels must be positive (in {}, mid {}, out {})",
                self.in_channels, self.mid_channels, self.out_channels
            )));
        }
        if self.downsample == 0 {
            return Err(ModelError::Config("lss.rs: downsample must be >= 1".into()));
        }
        let d = self.num_bins();
        let m = self.mid_channels;
        let conv = |cin: usize, cout: usize, k: usize, bias: bool| {
            Conv2dConfig::new([cin, cout], [k, k])
                .with_padding(PaddingConfig2d::Explicit(k / 2, k / 2, k / 2, k / 2))
                .with_bias(bias)
                .init(device)
        };
        let gates = self.camera_aware.then(|| CameraGates {
            fc1: LinearConfig::new(CAM_PARAM_CHANNELS, m).init(device),
            fc_depth: LinearConfig::new(m, m).init(device),
            fc_context: LinearConfig::new(m, m).init(device),
        });
        Ok(Lss {
            reduce: conv(self.in_channels, m, 3, false),
            reduce_bn: BatchNormConfig::new(m).init(device),
            gates,
            depth_conv: conv(m, m, 3, false),
            depth_bn: BatchNormConfig::new(m).init(device),
            depth_out: conv(m, d, 1, true),
            context_out: conv(m, self.out_channels, 1, true),
            dbound: self.dbound,
            num_bins: d,
            downsample: self.downsample,
            out_channels: self.out_channels,
        })
    }
}

fn num_bins(dbound: [f64; 3]) -> usize {
    let n = (dbound[1] - dbound[0]) / dbound[2];
    if n.is_finite() && n > 0.0 {
        (n - 1e-9).ceil() as usize
    } else {
        0
    }
}

fn check_dbound(dbound: [f64; 3]) -> Result<(), ModelError> {
    let [lo, hi, step] = dbound;
    if !(lo.is_finite() && hi.is_finite() && step.is_finite() && lo > 0.0 && hi > lo && step > 0.0)
    {
        return Err(ModelError::Config(format!(
            "lss.rs: dbound {dbound:?} must be [min > 0, max > min, step > 0]"
        )));
    }
    if num_bins(dbound) > 100_000 {
        return Err(ModelError::Config(format!(
            "lss.rs: dbound {dbound:?} gives too many depth bins"
        )));
    }
    Ok(())
}

/// Camera-aware SE gates: `gate = sigmoid(W_b · relu(W_1 · cam))`, one per branch.
#[derive(Module, Debug)]
pub struct CameraGates<B: Backend> {
    fc1: Linear<B>,
    fc_depth: Linear<B>,
    fc_context: Linear<B>,
}

/// The LSS depth net and splatting (see the module documentation).
#[derive(Module, Debug)]
pub struct Lss<B: Backend> {
    reduce: Conv2d<B>,
    reduce_bn: BatchNorm<B>,
    gates: Option<CameraGates<B>>,
    depth_conv: Conv2d<B>,
    depth_bn: BatchNorm<B>,
    depth_out: Conv2d<B>,
    context_out: Conv2d<B>,
    dbound: [f64; 3],
    num_bins: usize,
    downsample: usize,
    out_channels: usize,
}

/// What [`Lss::forward`] returns: the depth distribution, the context features and the frustum
/// geometry; [`LssOutput::splat_sparse`] / [`LssOutput::splat_dense`] pool them into voxels.
#[derive(Clone, Debug)]
pub struct LssOutput<B: Backend> {
    /// Depth logits `[B*V, D, h, w]`.
    pub depth_logits: Tensor<B, 4>,
    /// Context features `[B*V, C, h, w]`.
    pub context: Tensor<B, 4>,
    /// Voxel of every frustum point.
    pub frustum: Frustum,
}

impl<B: ModelBackend> Lss<B> {
    /// Number of depth bins `D`.
    pub fn num_bins(&self) -> usize {
        self.num_bins
    }
    /// Depth bins `[min, max, step]` (m).
    pub fn dbound(&self) -> [f64; 3] {
        self.dbound
    }
    /// Output (context) channels.
    pub fn out_channels(&self) -> usize {
        self.out_channels
    }
    /// The LSS voxel grid for a full-resolution grid (`downsample` times coarser, same origin).
    pub fn lss_grid(&self, full: &VoxelGrid) -> VoxelGrid {
        full.downsampled(self.downsample)
    }

    /// Depth net and frustum geometry.
    ///
    /// # Shapes
    /// - feats: `[B*V, C_in, h, w]` (row `b*V + v`), at `stride` input pixels per feature pixel
    /// - returns depth logits `[B*V, D, h, w]`, context `[B*V, C, h, w]`
    pub fn forward(
        &self,
        feats: Tensor<B, 4>,
        stride: usize,
        batch: &Batch<B>,
    ) -> Result<LssOutput<B>, ModelError> {
        let [bv, _, h, w] = feats.dims();
        let (b, v) = (batch.batch_size(), batch.num_views());
        if bv != b * v {
            return Err(ModelError::Input(format!(
                "lss.rs: feature map has {bv} rows, the batch has {b} items x {v} views"
            )));
        }
        if stride == 0 || h == 0 || w == 0 {
            return Err(ModelError::Input(format!(
                "lss.rs: empty feature map {h}x{w} or zero stride {stride}"
            )));
        }
        let device = feats.device();
        let grid = self.lss_grid(&batch.grid);
        let frustum = Frustum::new(batch, h, w, stride, self.dbound, grid)?;

        let x = conv_bn(&self.reduce, Some(&self.reduce_bn), feats, true);
        let (xd, xc) = match &self.gates {
            Some(g) => {
                let cam = camera_params::<B>(batch, &device)?;
                let hidden = relu(crate::profile::linear(&g.fc1, cam));
                let gd = sigmoid(crate::profile::linear(&g.fc_depth, hidden.clone()));
                let gc = sigmoid(crate::profile::linear(&g.fc_context, hidden));
                let m = gd.dims()[1];
                (
                    x.clone() * gd.reshape([bv, m, 1, 1]),
                    x * gc.reshape([bv, m, 1, 1]),
                )
            }
            None => (x.clone(), x),
        };
        let depth_hidden = conv_bn(&self.depth_conv, Some(&self.depth_bn), xd, true);
        let depth_logits = conv_bn(&self.depth_out, None, depth_hidden, false);
        let context = conv_bn(&self.context_out, None, xc, false);
        Ok(LssOutput {
            depth_logits,
            context,
            frustum,
        })
    }
}

/// Camera parameter vectors `[B*V, 21]` (see the module documentation).
pub fn camera_params<B: Backend>(
    batch: &Batch<B>,
    device: &B::Device,
) -> Result<Tensor<B, 2>, ModelError> {
    let (b, v) = (batch.batch_size(), batch.num_views());
    let (hh, ww) = batch.image_hw();
    let mut out = Vec::with_capacity(b * v * CAM_PARAM_CHANNELS);
    for bi in 0..b {
        for vi in 0..v {
            let cam = camera(batch, bi, vi)?;
            let lidar_from_cam = mat4_inverse(&cam.cam_from_lidar).ok_or_else(|| {
                ModelError::Input(format!(
                    "lss.rs: cam_from_lidar of item {bi} view {vi} is not invertible"
                ))
            })?;
            let img_from_cam = mat4_mul(&cam.img_from_lidar, &lidar_from_cam);
            for (r, row) in img_from_cam.iter().take(3).enumerate() {
                let scale = match r {
                    0 => ww.max(1) as f64,
                    1 => hh.max(1) as f64,
                    _ => 1.0,
                };
                out.extend(row.iter().take(3).map(|x| (x / scale) as f32));
            }
            for row in cam.cam_from_lidar.iter().take(3) {
                out.extend(row.iter().map(|&x| x as f32));
            }
        }
    }
    if out.iter().any(|x| !x.is_finite()) {
        return Err(ModelError::Input(
            "lss.rs: camera matrices contain non-finite values".into(),
        ));
    }
    Ok(Tensor::from_data(
        TensorData::new(out, [b * v, CAM_PARAM_CHANNELS]),
        device,
    ))
}

fn camera<B: Backend>(
    batch: &Batch<B>,
    bi: usize,
    vi: usize,
) -> Result<&crate::CameraInput, ModelError> {
    batch
        .cameras
        .get(bi)
        .and_then(|c| c.get(vi))
        .ok_or_else(|| {
            ModelError::Input(format!(
                "lss.rs: batch.cameras has no camera for item {bi} view {vi}"
            ))
        })
}

/// Input-image pixel coordinate of the centre of feature pixel index `i` at `stride`.
pub fn feature_pixel_center(i: usize, stride: usize) -> f64 {
    (i * stride) as f64 + (stride as f64 - 1.0) / 2.0
}

/// The frustum points of one forward pass and the voxel each falls in.
///
/// Point order is `[b*V + v][k][i][j]` (row-major over `[B*V, D, h, w]`), the same order as the
/// depth logits.
#[derive(Clone, Debug)]
pub struct Frustum {
    /// Batch size `B`.
    pub batch_size: usize,
    /// Views per item `V`.
    pub views: usize,
    /// Depth bins `D`.
    pub bins: usize,
    /// Feature map height.
    pub h: usize,
    /// Feature map width.
    pub w: usize,
    /// Input pixels per feature pixel.
    pub stride: usize,
    /// The LSS voxel grid the points are binned into.
    pub grid: VoxelGrid,
    /// Per point: the voxel `(b, x, y, z)` containing it, or `None` outside the grid / behind the
    /// camera.
    pub voxel: Vec<Option<[i32; 4]>>,
}

impl Frustum {
    /// Lifts every (feature pixel, depth bin) pair through `img_from_lidar⁻¹` and bins it.
    pub fn new<B: Backend>(
        batch: &Batch<B>,
        h: usize,
        w: usize,
        stride: usize,
        dbound: [f64; 3],
        grid: VoxelGrid,
    ) -> Result<Self, ModelError> {
        check_dbound(dbound)?;
        let (b, v) = (batch.batch_size(), batch.num_views());
        let d = num_bins(dbound);
        let mut voxel = Vec::with_capacity(b * v * d * h * w);
        for bi in 0..b {
            for vi in 0..v {
                let cam = camera(batch, bi, vi)?;
                let lidar_from_img = mat4_inverse(&cam.img_from_lidar).ok_or_else(|| {
                    ModelError::Input(format!(
                        "lss.rs: img_from_lidar of item {bi} view {vi} is not invertible"
                    ))
                })?;
                for k in 0..d {
                    let depth = dbound[0] + k as f64 * dbound[2];
                    for i in 0..h {
                        let pv = feature_pixel_center(i, stride);
                        for j in 0..w {
                            let pu = feature_pixel_center(j, stride);
                            let p = unproject(&lidar_from_img, pu, pv, depth);
                            voxel.push(p.and_then(|p| grid.voxel_of_point_m(p)).map(|ijk| {
                                [bi as i32, ijk[0] as i32, ijk[1] as i32, ijk[2] as i32]
                            }));
                        }
                    }
                }
            }
        }
        Ok(Self {
            batch_size: b,
            views: v,
            bins: d,
            h,
            w,
            stride,
            grid,
            voxel,
        })
    }

    /// Number of frustum points `B*V*D*h*w`.
    pub fn num_points(&self) -> usize {
        self.voxel.len()
    }

    /// Distinct voxels hit by at least one point, sorted by `(b, x, y, z)`, and for every point
    /// its row in that list (`u32::MAX` when it hits no voxel).
    pub fn hit_voxels(&self) -> (Vec<[i32; 4]>, Vec<u32>) {
        let [sx, sy, sz] = self.grid.dims;
        let lin = |c: &[i32; 4]| {
            ((c[0] as usize * sx + c[1] as usize) * sy + c[2] as usize) * sz + c[3] as usize
        };
        let mut keys: Vec<usize> = self.voxel.iter().flatten().map(lin).collect();
        keys.sort_unstable();
        keys.dedup();
        let rows = self
            .voxel
            .iter()
            .map(|c| match c {
                Some(c) => keys
                    .binary_search(&lin(c))
                    .map(|r| r as u32)
                    .unwrap_or(u32::MAX),
                None => u32::MAX,
            })
            .collect();
        let coords = keys
            .into_iter()
            .map(|l| {
                let z = l % sz;
                let y = (l / sz) % sy;
                let x = (l / (sz * sy)) % sx;
                let bb = l / (sz * sy * sx);
                [bb as i32, x as i32, y as i32, z as i32]
            })
            .collect();
        (coords, rows)
    }

    /// Per point: the linear index in a dense `[B, X, Y, Z]` grid (`u32::MAX` when outside).
    pub fn dense_rows(&self) -> Vec<u32> {
        let [sx, sy, sz] = self.grid.dims;
        self.voxel
            .iter()
            .map(|c| match c {
                Some(c) => {
                    (((c[0] as usize * sx + c[1] as usize) * sy + c[2] as usize) * sz
                        + c[3] as usize) as u32
                }
                None => u32::MAX,
            })
            .collect()
    }
}

/// LiDAR-frame point of pixel `(u, v)` at depth `d`: `lidar_from_img · [u·d, v·d, d, 1]`, divided by
/// the homogeneous coordinate; `None` when that is not finite or zero.
fn unproject(lidar_from_img: &Mat4, u: f64, v: f64, d: f64) -> Option<[f64; 3]> {
    let q = [u * d, v * d, d, 1.0];
    let mut p = [0.0f64; 4];
    for (r, out) in p.iter_mut().enumerate() {
        *out = (0..4).map(|c| lidar_from_img[r][c] * q[c]).sum();
    }
    if !p[3].is_finite() || p[3].abs() < 1e-12 {
        return None;
    }
    let out = [p[0] / p[3], p[1] / p[3], p[2] / p[3]];
    out.iter().all(|x| x.is_finite()).then_some(out)
}

/// Sum-pools depth-weighted context features: `out[rows[p]] += softmax(depth)[p] · context[pixel(p)]`
/// for every frustum point `p` with `rows[p] < n_rows` (other points are dropped). Differentiable
/// with respect to both inputs (row gathers and a row scatter-add: `occ_sparse::rows`).
///
/// # Shapes
/// - depth_prob: `[B*V, D, h, w]`, context: `[B*V, C, h, w]`, rows: `B*V*D*h*w` -> `[n_rows, C]`
pub fn splat<B: SparseConvBackend>(
    depth_prob: Tensor<B, 4>,
    context: Tensor<B, 4>,
    rows: &[u32],
    n_rows: usize,
) -> Result<Tensor<B, 2>, ModelError> {
    let [bv, d, h, w] = depth_prob.dims();
    let [bv2, c, h2, w2] = context.dims();
    if (bv, h, w) != (bv2, h2, w2) || rows.len() != bv * d * h * w {
        return Err(ModelError::Input(format!(
            "lss.rs splat: depth {:?}, context {:?}, {} rows",
            depth_prob.dims(),
            context.dims(),
            rows.len()
        )));
    }
    let device = depth_prob.device();
    let mut point_idx = Vec::new();
    let mut pixel_idx = Vec::new();
    let mut target = Vec::new();
    let hw = h * w;
    for (p, &r) in rows.iter().enumerate() {
        if (r as usize) < n_rows {
            let pix = (p / (d * hw)) * hw + p % hw;
            point_idx.push(p as u32);
            pixel_idx.push(pix as u32);
            target.push(r);
        }
    }
    let out = Tensor::<B, 2>::zeros([n_rows, c], &device);
    if target.is_empty() {
        return Ok(out);
    }
    let n = target.len();
    // One multiply-add per (point, channel): the depth-weighted context added into its voxel.
    crate::profile::add_matmul("lss_splat", 1, n, 1, c);
    // Gathers and the scatter-add as row plans (occ_sparse::rows): a segment sum per voxel on the
    // cubecl backends instead of burn's per-column `select_assign` loop.
    let plan = |dest: Vec<u32>, n_out: usize| -> Result<Arc<RowPlan>, ModelError> {
        Ok(Arc::new(RowPlan::new(dest, n_out)?))
    };
    let prob = gather_rows(
        depth_prob.reshape([bv * d * hw, 1]),
        &plan(point_idx, bv * d * hw)?,
    );
    let ctx = gather_rows(
        context.permute([0, 2, 3, 1]).reshape([bv * hw, c]),
        &plan(pixel_idx, bv * hw)?,
    );
    debug_assert_eq!(prob.dims()[0], n);
    Ok(out + scatter_add_rows(ctx * prob, &plan(target, n_rows)?))
}

impl<B: Backend> LssOutput<B> {
    /// Depth probabilities `softmax(depth_logits, dim = 1)`.
    pub fn depth_prob(&self) -> Tensor<B, 4> {
        softmax(self.depth_logits.clone(), 1)
    }

    /// The non-empty voxels as a sparse tensor on the LSS grid: the sites hit by at least one
    /// frustum point, with their pooled features. Errors when no point hits the grid.
    pub fn splat_sparse(&self) -> Result<SparseTensor<B>, ModelError>
    where
        B: SparseConvBackend,
    {
        let (coords, rows) = self.frustum.hit_voxels();
        if coords.is_empty() {
            return Err(ModelError::Input(
                "lss.rs: no frustum point falls inside the voxel grid (check img_from_lidar, dbound and grid)"
                    .into(),
            ));
        }
        let feats = splat(self.depth_prob(), self.context.clone(), &rows, coords.len())?;
        Ok(SparseTensor::new(
            coords,
            feats,
            self.frustum.grid.dims,
            self.frustum.batch_size,
        )?)
    }

    /// The pooled volume as a dense grid `[B, C, X, Y, Z]` (the dense baseline's input).
    pub fn splat_dense(&self) -> Result<Tensor<B, 5>, ModelError>
    where
        B: SparseConvBackend,
    {
        let [sx, sy, sz] = self.frustum.grid.dims;
        let b = self.frustum.batch_size;
        let c = self.context.dims()[1];
        let rows = self.frustum.dense_rows();
        let flat = splat(
            self.depth_prob(),
            self.context.clone(),
            &rows,
            b * sx * sy * sz,
        )?;
        Ok(flat.reshape([b, sx, sy, sz, c]).permute([0, 4, 1, 2, 3]))
    }
}

/// The feature pixel (row-major index `i * w + j` of an `h x w` map with `stride` input pixels per
/// feature pixel) that the point `p` (metres) projects onto through `img_from_lidar`, with its depth
/// along the optical axis; the pixel is the rounded projection (pixel centres at integer
/// coordinates). `None` behind the camera or outside the `img_hw` image or the map.
pub fn feature_pixel_of_point(
    img_from_lidar: &Mat4,
    p: [f64; 3],
    img_hw: (usize, usize),
    hw: (usize, usize),
    stride: usize,
) -> Option<(usize, f64)> {
    let m = img_from_lidar;
    let q: [f64; 3] =
        std::array::from_fn(|r| m[r][0] * p[0] + m[r][1] * p[1] + m[r][2] * p[2] + m[r][3]);
    let depth = q[2];
    if !(depth.is_finite() && depth > 1e-6) {
        return None;
    }
    let (u, v) = ((q[0] / depth).round(), (q[1] / depth).round());
    if !(u >= 0.0 && v >= 0.0 && u < img_hw.1 as f64 && v < img_hw.0 as f64) {
        return None;
    }
    let (j, i) = (u as usize / stride.max(1), v as usize / stride.max(1));
    (i < hw.0 && j < hw.1).then_some((i * hw.1 + j, depth))
}

/// Depth targets per feature pixel, row-major `[B*V, h, w]`: the bin of the minimum LiDAR depth over
/// the points whose rounded pixel lies in the pixel's `stride x stride` patch, or `-1` (no target).
/// `None` when the batch carries no points.
pub fn depth_targets<B: Backend>(
    batch: &Batch<B>,
    h: usize,
    w: usize,
    stride: usize,
    dbound: [f64; 3],
) -> Result<Option<Vec<i64>>, ModelError> {
    check_dbound(dbound)?;
    let Some(points) = &batch.points else {
        return Ok(None);
    };
    let (b, v) = (batch.batch_size(), batch.num_views());
    if points.len() != b {
        return Err(ModelError::Input(format!(
            "lss.rs: batch.points has {} items, the batch has {b}",
            points.len()
        )));
    }
    let img_hw = batch.image_hw();
    let d = num_bins(dbound) as i64;
    let mut min_depth = vec![f64::INFINITY; b * v * h * w];
    for (bi, pts) in points.iter().enumerate() {
        for vi in 0..v {
            let m = camera(batch, bi, vi)?.img_from_lidar;
            let base = (bi * v + vi) * h * w;
            for p in pts {
                let p = [p[0] as f64, p[1] as f64, p[2] as f64];
                if let Some((cell, depth)) = feature_pixel_of_point(&m, p, img_hw, (h, w), stride) {
                    let c = &mut min_depth[base + cell];
                    *c = c.min(depth);
                }
            }
        }
    }
    let [lo, _, step] = dbound;
    Ok(Some(
        min_depth
            .into_iter()
            .map(|dep| {
                if !dep.is_finite() {
                    return -1;
                }
                let k = ((dep - (lo - step / 2.0)) / step).floor();
                if k >= 0.0 && (k as i64) < d {
                    k as i64
                } else {
                    -1
                }
            })
            .collect(),
    ))
}

/// Depth loss (docs/losses.md §6): binary cross-entropy between `softmax(depth_logits)` and the one-hot
/// target bin, summed over the bins of the foreground pixels (target >= 0) and divided by
/// `max(1, #foreground)`. Probabilities are clamped to `[1e-6, 1 - 1e-6]` before the logarithms.
///
/// # Shapes
/// - depth_logits: `[B*V, D, h, w]`, targets: `B*V*h*w` bins or -1 -> `[1]`
pub fn depth_loss<B: Backend>(
    depth_logits: Tensor<B, 4>,
    targets: &[i64],
) -> Result<Tensor<B, 1>, ModelError> {
    let [bv, d, h, w] = depth_logits.dims();
    let device = depth_logits.device();
    if targets.len() != bv * h * w {
        return Err(ModelError::Input(format!(
            "lss.rs depth_loss: {} targets for a [{bv}, {d}, {h}, {w}] depth map",
            targets.len()
        )));
    }
    let fg: Vec<i64> = (0..targets.len())
        .filter(|&p| targets[p] >= 0 && (targets[p] as usize) < d)
        .map(|p| p as i64)
        .collect();
    if fg.is_empty() {
        return Ok(depth_logits.sum().mul_scalar(0.0).reshape([1]));
    }
    let n = fg.len();
    let mut onehot = vec![0.0f32; n * d];
    for (r, &p) in fg.iter().enumerate() {
        onehot[r * d + targets[p as usize] as usize] = 1.0;
    }
    let t = Tensor::<B, 2>::from_data(TensorData::new(onehot, [n, d]), &device);
    let prob = softmax(depth_logits, 1)
        .permute([0, 2, 3, 1])
        .reshape([bv * h * w, d])
        .select(
            0,
            Tensor::<B, 1, Int>::from_data(TensorData::new(fg, [n]), &device),
        )
        .clamp(1e-6, 1.0 - 1e-6);
    let bce = -(t.clone() * prob.clone().log() + (t.neg() + 1.0) * (prob.neg() + 1.0).log());
    Ok(bce.sum().div_scalar(n as f64).reshape([1]))
}
