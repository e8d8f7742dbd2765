//! Shared setup of the SparseOcc++ tests: a tiny scene with two cameras, fixtures, gradient checks.
#![allow(dead_code)]

use burn::module::{Module, ModuleVisitor, Param};
use burn::prelude::*;
use burn::tensor::backend::AutodiffBackend;
use burn::tensor::{Distribution, TensorData};
use occ_geometry::{Mat4, VoxelGrid};
use occ_model::{Batch, CameraInput};
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;

/// f64 autodiff backend for gradient checks.
pub type AD = burn::backend::Autodiff<burn::backend::NdArray<f64>>;
/// Non-autodiff backend of the tests. Also f64: burn 0.21 fixes the float dtype of a device type
/// process-wide at the first tensor creation, so one test binary must not mix NdArray<f32> and
/// NdArray<f64>.
pub type NB = burn::backend::NdArray<f64>;

/// Network-input image size (H, W).
pub const IMG_HW: (usize, usize) = (32, 64);
/// Image feature strides of the two test levels.
pub const STRIDES: [usize; 2] = [4, 8];
/// Image feature channels.
pub const FEAT_C: usize = 8;
/// Full label grid.
pub const FULL_DIMS: [usize; 3] = [32, 32, 8];

/// The tiny grid: 32x32x8 voxels of 0.2 m, x in [0, 6.4], y in [-3.2, 3.2], z in [-0.8, 0.8].
pub fn grid() -> VoxelGrid {
    VoxelGrid {
        origin_m: [0.0, -3.2, -0.8],
        voxel_size_m: 0.2,
        dims: FULL_DIMS,
    }
}

/// Pinhole camera at `(tx, 0, 0)` looking along `dir · x` (dir = ±1), fx = fy = 20, principal point at
/// the image centre, as `img_from_lidar` and `cam_from_lidar`.
pub fn camera(tx: f64, dir: f64) -> CameraInput {
    // Camera axes in LiDAR coordinates: right, down, forward.
    let fwd = [dir, 0.0, 0.0];
    let right = [0.0, -dir, 0.0];
    let down = [0.0, 0.0, -1.0];
    let t = [tx, 0.0, 0.0];
    let mut cam: Mat4 = [[0.0; 4]; 4];
    for (r, axis) in [right, down, fwd].iter().enumerate() {
        cam[r][..3].copy_from_slice(axis);
        cam[r][3] = -(axis[0] * t[0] + axis[1] * t[1] + axis[2] * t[2]);
    }
    cam[3][3] = 1.0;
    let (f, cu, cv) = (
        20.0,
        IMG_HW.1 as f64 / 2.0 - 0.5,
        IMG_HW.0 as f64 / 2.0 - 0.5,
    );
    let mut img = [[0.0; 4]; 4];
    for j in 0..4 {
        img[0][j] = f * cam[0][j] + cu * cam[2][j];
        img[1][j] = f * cam[1][j] + cv * cam[2][j];
        img[2][j] = cam[2][j];
        img[3][j] = cam[3][j];
    }
    CameraInput {
        img_from_lidar: img,
        cam_from_lidar: cam,
    }
}

/// Two views per item: view 0 at x = 3.2 looking +x (voxels with x < 3.2 are behind it), view 1 at
/// x = -1 looking +x (sees most of the grid).
pub fn cameras(batch: usize) -> Vec<Vec<CameraInput>> {
    (0..batch)
        .map(|_| vec![camera(3.2, 1.0), camera(-1.0, 1.0)])
        .collect()
}

/// Random labels with structure: a ground slab (class 1), boxes of classes 2..5, some 255.
pub fn random_labels(rng: &mut ChaCha8Rng, dims: [usize; 3]) -> Vec<u8> {
    let [nx, ny, nz] = dims;
    let mut t = vec![0u8; nx * ny * nz];
    for x in 0..nx {
        for y in 0..ny {
            for z in 0..nz.min(2) {
                t[(x * ny + y) * nz + z] = 1;
            }
        }
    }
    for _ in 0..6 {
        let c = rng.random_range(2..6u8);
        let (x0, y0, z0) = (
            rng.random_range(0..nx),
            rng.random_range(0..ny),
            rng.random_range(0..nz),
        );
        let (sx, sy, sz) = (
            rng.random_range(1..8),
            rng.random_range(1..8),
            rng.random_range(1..5),
        );
        for x in x0..(x0 + sx).min(nx) {
            for y in y0..(y0 + sy).min(ny) {
                for z in z0..(z0 + sz).min(nz) {
                    t[(x * ny + y) * nz + z] = c;
                }
            }
        }
    }
    for v in t.iter_mut() {
        if rng.random_bool(0.05) {
            *v = 255;
        }
    }
    t
}

/// A batch of `b` items with images, cameras, the tiny grid and random targets.
pub fn batch<B: Backend>(b: usize, seed: u64, device: &B::Device) -> Batch<B> {
    let mut rng = ChaCha8Rng::seed_from_u64(seed);
    let (h, w) = IMG_HW;
    let images = Tensor::<B, 5>::random([b, 2, 3, h, w], Distribution::Normal(0.0, 1.0), device);
    let target = (0..b).map(|_| random_labels(&mut rng, FULL_DIMS)).collect();
    Batch {
        images,
        cameras: cameras(b),
        grid: grid(),
        target: Some(target),
        points: None,
    }
}

/// Seeded random tensor with normal entries.
pub fn randn<B: Backend, const D: usize>(
    shape: [usize; D],
    seed: u64,
    device: &B::Device,
) -> Tensor<B, D> {
    let mut rng = ChaCha8Rng::seed_from_u64(seed);
    let n: usize = shape.iter().product();
    let v: Vec<f32> = (0..n)
        .map(|_| {
            // Box-Muller
            let u1: f64 = rng.random_range(1e-12..1.0);
            let u2: f64 = rng.random_range(0.0..1.0);
            ((-2.0 * u1.ln()).sqrt() * (2.0 * std::f64::consts::PI * u2).cos()) as f32
        })
        .collect();
    Tensor::from_data(TensorData::new(v, shape), device)
}

/// Image features of the two levels `[B·V, C, H/s, W/s]`.
pub fn features<B: Backend>(b: usize, seed: u64, device: &B::Device) -> Vec<Tensor<B, 4>> {
    STRIDES
        .iter()
        .enumerate()
        .map(|(l, &s)| {
            randn(
                [b * 2, FEAT_C, IMG_HW.0 / s, IMG_HW.1 / s],
                seed + l as u64,
                device,
            )
        })
        .collect()
}

/// Tensor values as f64.
pub fn to_f64<B: Backend, const D: usize>(t: &Tensor<B, D>) -> Vec<f64> {
    t.clone()
        .into_data()
        .convert::<f64>()
        .to_vec::<f64>()
        .unwrap()
}

/// Visits every float parameter and records whether it has a finite, present gradient.
pub struct GradCheck<'a, B: AutodiffBackend> {
    pub grads: &'a B::Gradients,
    pub total: usize,
    pub missing: Vec<String>,
    pub non_finite: Vec<String>,
    pub path: Vec<String>,
}

impl<B: AutodiffBackend> ModuleVisitor<B> for GradCheck<'_, B> {
    fn enter_module(&mut self, name: &str, _container_type: &str) {
        self.path.push(name.to_string());
    }
    fn exit_module(&mut self, _name: &str, _container_type: &str) {
        self.path.pop();
    }
    fn visit_float<const D: usize>(&mut self, param: &Param<Tensor<B, D>>) {
        // Batch-norm running statistics are state, not trainable parameters.
        if !param.val().is_require_grad() {
            return;
        }
        self.total += 1;
        let name = format!("{} ({:?})", self.path.join("."), param.id);
        match param.val().grad(self.grads) {
            None => self.missing.push(name),
            Some(g) => {
                let v = g.into_data().convert::<f64>().to_vec::<f64>().unwrap();
                if v.iter().any(|x| !x.is_finite()) {
                    self.non_finite.push(name);
                }
            }
        }
    }
}

/// Replaces every float parameter by values drawn from a generator seeded with `seed`, so a
/// model's initialisation does not depend on burn's process-wide RNG (which the tests of one
/// binary share across threads). Constant vectors (norm scales and shifts, zero biases) are kept;
/// other vectors get U(-0.1, 0.1), matrices and kernels N(0, 1/fan) with
/// `fan = numel / max(first dim, last dim)` (a rough fan-in: the scale only keeps activations tame).
pub struct SeededInit {
    pub rng: ChaCha8Rng,
}

impl<B: Backend> burn::module::ModuleMapper<B> for SeededInit {
    fn map_float<const D: usize>(&mut self, param: Param<Tensor<B, D>>) -> Param<Tensor<B, D>> {
        let rng = &mut self.rng;
        param.map(|t| {
            let dims = t.dims();
            let device = t.device();
            let require_grad = t.is_require_grad();
            let old = t.into_data().convert::<f64>().to_vec::<f64>().unwrap();
            let n = old.len();
            let values: Vec<f64> = if D == 1 {
                if old.iter().all(|&v| v == old[0]) {
                    old
                } else {
                    (0..n).map(|_| rng.random_range(-0.1..0.1)).collect()
                }
            } else {
                let fan = (n / dims[0]).min(n / dims[D - 1]).max(1) as f64;
                let std = fan.sqrt().recip();
                (0..n)
                    .map(|_| {
                        let u1: f64 = rng.random_range(1e-12..1.0);
                        let u2: f64 = rng.random_range(0.0..1.0);
                        std * (-2.0 * u1.ln()).sqrt() * (2.0 * std::f64::consts::PI * u2).cos()
                    })
                    .collect()
            };
            let t = Tensor::from_data(TensorData::new(values, dims), &device);
            if require_grad {
                t.require_grad()
            } else {
                t
            }
        })
    }
}

/// `module` with every float parameter re-drawn from `seed` (see [`SeededInit`]).
pub fn seeded_init<B: Backend, M: Module<B>>(module: M, seed: u64) -> M {
    module.map(&mut SeededInit {
        rng: ChaCha8Rng::seed_from_u64(seed),
    })
}

/// Asserts that every float parameter of `module` has a finite gradient in `grads`; returns the count.
pub fn assert_all_grads<B: AutodiffBackend, M: Module<B>>(
    module: &M,
    grads: &B::Gradients,
) -> usize {
    let mut v = GradCheck::<B> {
        grads,
        total: 0,
        missing: Vec::new(),
        non_finite: Vec::new(),
        path: Vec::new(),
    };
    module.visit(&mut v);
    assert!(
        v.missing.is_empty(),
        "parameters without gradient: {:?}",
        v.missing
    );
    assert!(
        v.non_finite.is_empty(),
        "non-finite gradients: {:?}",
        v.non_finite
    );
    assert!(v.total > 0);
    v.total
}

/// Reads an .npy file: shape and values.
pub fn read_npy<T: npyz::Deserialize>(path: &std::path::Path) -> (Vec<usize>, Vec<T>) {
    let (values, shape) = occ_testdata::read_npy(path);
    (shape, values)
}

/// `$SPARSEOCC_FIXTURES/reference` and its manifest's file table, or `None` (skip reported by
/// `occ_testdata`) without the external fixtures folder.
pub fn reference_fixtures() -> Option<(
    std::path::PathBuf,
    serde_json::Map<String, serde_json::Value>,
)> {
    let dir = occ_testdata::fixtures()?.join("reference");
    let p = dir.join("manifest.json");
    let text = std::fs::read_to_string(&p).unwrap_or_else(|e| panic!("{}: {e}", p.display()));
    let m: serde_json::Value = serde_json::from_str(&text).unwrap();
    let files = m["files"].as_object().expect("manifest has files").clone();
    Some((dir, files))
}
