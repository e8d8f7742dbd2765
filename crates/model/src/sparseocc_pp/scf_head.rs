//! Scene completion field (SCF) heads and their targets (SparseOcc++, paper Sec. 4.2 "Compact Scene
//! Completion").
//!
//! - **Orthogonal decomposition** (default): two heads, planar `s^{X-Y}` and vertical `s^Z`.
//!   Ablation `Scalar`: one isotropic distance `s`, whose ground truth is Algorithm 2 with the cubic
//!   kernel `[2s+1]^3` ([`scf_isotropic`]) and whose propagation dilates by the same cube
//!   (see [`crate::sparseocc_pp::propagation`]); it uses `s_max_planar` as its range.
//! - **Discretized learning** (default): each head is an MLP `D → D → 2·s_max + 1` giving logits over
//!   the bins `d_k = k - s_max`, `k = 0..2·s_max` (so bin index = `s + s_max`); the predicted distance is
//!   the arg-max bin. Ablation `Regression`: the MLP outputs one value `[N, 1]` (in voxels), the
//!   prediction is `round(clamp(value, -s_max, s_max))`, and the target value is `bin - s_max`.
//! - **Targets** ([`scf_targets`]) come from `occ_geometry::scf` (Algorithm 2, zero padding counted) on
//!   the `1/2`-resolution occupancy, where "occupied" means a label other than 0 (empty) and 255
//!   (ignore). Unknown voxels count as empty for the field: Algorithm 2 binarises `occ > 0`, which
//!   would make the 255 (unobserved) region solid and teach the heads to grow into it. An anchor whose
//!   own `1/2`-resolution label is 255 gets the ignore index 255.

use crate::error::ModelError;
use burn::nn::{Linear, LinearConfig};
use burn::prelude::*;
use burn::tensor::activation::relu;
use occ_geometry::scf::{scf_planar, scf_vertical};
use occ_labels::{is_occupied, IGNORE};
use occ_sparse::Coord;

/// Planar + vertical components, or one isotropic scalar (ablation).
#[derive(Config, Debug, Copy, PartialEq, Eq)]
pub enum ScfDecomposition {
    /// `s = (s^{X-Y}, s^Z)` (paper default).
    Decomposed,
    /// One isotropic `s` (cubic kernel).
    Scalar,
}

/// Classification over bins or direct regression.
#[derive(Config, Debug, Copy, PartialEq, Eq)]
pub enum ScfLearning {
    /// `2·s_max + 1` bins, cross-entropy (paper default).
    Bins,
    /// One value per component (ablation).
    Regression,
}

/// Configuration of [`ScfHead`].
#[derive(Config, Debug)]
pub struct ScfHeadConfig {
    /// Anchor feature width `D`.
    pub embed_dim: usize,
    /// `s_max^{X-Y}` (also the range of the scalar ablation).
    #[config(default = 10)]
    pub s_max_planar: u32,
    /// `s_max^{Z}`. Paper Sec. 5.4 says 5; its chosen ablation row is (10, 3) (docs/paper_notes.md §2).
    #[config(default = 3)]
    pub s_max_vertical: u32,
    /// Decomposed or scalar.
    #[config(default = "ScfDecomposition::Decomposed")]
    pub decomposition: ScfDecomposition,
    /// Bins or regression.
    #[config(default = "ScfLearning::Bins")]
    pub learning: ScfLearning,
}

impl ScfHeadConfig {
    /// Checks the ranges (`s_max` in `1..=127`, bins fit the `u8` targets).
    pub fn validate(&self) -> Result<(), ModelError> {
        for (name, s) in [
            ("s_max_planar", self.s_max_planar),
            ("s_max_vertical", self.s_max_vertical),
        ] {
            if s == 0 || s > 127 {
                return Err(ModelError::Config(format!(
                    "SCF: {name} = {s} must be in 1..=127"
                )));
            }
        }
        if self.embed_dim == 0 {
            return Err(ModelError::Config("SCF: embed_dim must be positive".into()));
        }
        Ok(())
    }

    fn outputs(&self, s_max: u32) -> usize {
        match self.learning {
            ScfLearning::Bins => 2 * s_max as usize + 1,
            ScfLearning::Regression => 1,
        }
    }

    /// Initialises the heads.
    pub fn init<B: Backend>(&self, device: &B::Device) -> ScfHead<B> {
        let d = self.embed_dim;
        let mlp = |out: usize| ScfMlp {
            fc1: LinearConfig::new(d, d).init(device),
            fc2: LinearConfig::new(d, out).init(device),
        };
        ScfHead {
            planar: mlp(self.outputs(self.s_max_planar)),
            vertical: match self.decomposition {
                ScfDecomposition::Decomposed => Some(mlp(self.outputs(self.s_max_vertical))),
                ScfDecomposition::Scalar => None,
            },
            s_max_planar: self.s_max_planar,
            s_max_vertical: self.s_max_vertical,
            decomposition: self.decomposition,
            learning: self.learning,
        }
    }
}

/// `D → D → out` MLP.
#[derive(Module, Debug)]
pub struct ScfMlp<B: Backend> {
    /// Hidden layer.
    pub fc1: Linear<B>,
    /// Output layer.
    pub fc2: Linear<B>,
}

impl<B: occ_sparse::SparseConvBackend> ScfMlp<B> {
    /// `[N, D]` → `[N, out]`.
    pub fn forward(&self, x: Tensor<B, 2>) -> Tensor<B, 2> {
        crate::profile::linear(&self.fc2, relu(crate::profile::linear(&self.fc1, x)))
    }
}

/// The SCF heads (see the module docs).
#[derive(Module, Debug)]
pub struct ScfHead<B: Backend> {
    /// Planar head (the only head in the scalar ablation).
    pub planar: ScfMlp<B>,
    /// Vertical head (decomposed only).
    pub vertical: Option<ScfMlp<B>>,
    s_max_planar: u32,
    s_max_vertical: u32,
    decomposition: ScfDecomposition,
    learning: ScfLearning,
}

/// SCF predictions on the anchors, for `L_scf` and the propagation.
#[derive(Clone, Debug)]
pub struct ScfPrediction<B: Backend> {
    /// Anchors `(b, x, y, z)` on the `1/2`-resolution grid.
    pub coords: Vec<Coord>,
    /// The `1/2`-resolution grid.
    pub dims: [usize; 3],
    /// Planar (or scalar) output: bin logits `[N, 2·s_max_planar + 1]`, or values `[N, 1]`.
    pub planar: Tensor<B, 2>,
    /// Vertical output `[N, 2·s_max_vertical + 1]` or `[N, 1]`; `None` in the scalar ablation.
    pub vertical: Option<Tensor<B, 2>>,
    /// Decoded planar (or scalar) distances in `[-s_max, s_max]` used by the propagation.
    pub s_planar: Vec<i32>,
    /// Decoded vertical distances (empty in the scalar ablation).
    pub s_vertical: Vec<i32>,
    /// Decomposition used.
    pub decomposition: ScfDecomposition,
    /// Learning used (bins: CE on bin indices; regression: regress `bin - s_max`).
    pub learning: ScfLearning,
    /// Range of the planar (scalar) component.
    pub s_max_planar: u32,
    /// Range of the vertical component.
    pub s_max_vertical: u32,
}

impl<B: occ_sparse::SparseConvBackend> ScfHead<B> {
    /// Decomposition of this head.
    pub fn decomposition(&self) -> ScfDecomposition {
        self.decomposition
    }

    /// Raw outputs: planar (or scalar) and vertical.
    pub fn forward(&self, feats: Tensor<B, 2>) -> (Tensor<B, 2>, Option<Tensor<B, 2>>) {
        let v = self.vertical.as_ref().map(|h| h.forward(feats.clone()));
        (self.planar.forward(feats), v)
    }

    /// Decodes outputs `[N, K]` to distances: arg-max bin minus `s_max`, or rounded clamped value.
    pub fn decode(&self, out: &Tensor<B, 2>, s_max: u32) -> Vec<i32> {
        let n = out.dims()[0];
        if n == 0 {
            return Vec::new();
        }
        let s_max = s_max as i32;
        match self.learning {
            // The arg-max over each row's bins, the rows padded (see `kernels::rows_bucketed`).
            ScfLearning::Bins => B::ROW_BUCKET
                .pad(out.clone().detach())
                .argmax(1)
                .narrow(0, 0, n)
                .reshape([n])
                .into_data()
                .convert::<i64>()
                .to_vec::<i64>()
                .unwrap_or_else(|_| vec![s_max as i64; n])
                .into_iter()
                .map(|k| k as i32 - s_max)
                .collect(),
            ScfLearning::Regression => out
                .clone()
                .detach()
                .reshape([n])
                .into_data()
                .convert::<f32>()
                .to_vec::<f32>()
                .unwrap_or_else(|_| vec![0.0; n])
                .into_iter()
                .map(|v| {
                    if v.is_nan() {
                        0
                    } else {
                        (v.round() as i32).clamp(-s_max, s_max)
                    }
                })
                .collect(),
        }
    }

    /// Heads + decoding on the anchors `coords` (grid `dims`) with features `feats [N, D]`.
    pub fn predict(
        &self,
        coords: Vec<Coord>,
        dims: [usize; 3],
        feats: Tensor<B, 2>,
    ) -> ScfPrediction<B> {
        let (planar, vertical) = self.forward(feats);
        let s_planar = self.decode(&planar, self.s_max_planar);
        let s_vertical = vertical
            .as_ref()
            .map(|v| self.decode(v, self.s_max_vertical))
            .unwrap_or_default();
        ScfPrediction {
            coords,
            dims,
            planar,
            vertical,
            s_planar,
            s_vertical,
            decomposition: self.decomposition,
            learning: self.learning,
            s_max_planar: self.s_max_planar,
            s_max_vertical: self.s_max_vertical,
        }
    }
}

/// Isotropic Algorithm 2 (ablation `Scalar`): kernel `[2s+1, 2s+1, 2s+1]`, padding `s`, zero padding
/// counted in the average (so occupied voxels within `s` of the border are never homogeneous at `s`).
/// `occ` is flat `[X][Y][Z]` (non-zero = occupied). Uses a summed-volume table; cost `O(X·Y·Z·s_max)`.
pub fn scf_isotropic(occ: &[u8], dims: [usize; 3], s_max: u32) -> Result<Vec<i8>, ModelError> {
    let [nx, ny, nz] = dims;
    let volume = nx
        .checked_mul(ny)
        .and_then(|v| v.checked_mul(nz))
        .ok_or_else(|| ModelError::Input(format!("SCF isotropic: dims {dims:?} overflow")))?;
    if occ.len() != volume {
        return Err(ModelError::Input(format!(
            "SCF isotropic: occupancy has {} voxels, dims {dims:?} need {volume}",
            occ.len()
        )));
    }
    let s_max = i8::try_from(s_max)
        .map_err(|_| ModelError::Config(format!("SCF isotropic: s_max {s_max} > 127")))?;
    let mut out = vec![0i8; volume];
    if volume == 0 || s_max == 0 {
        return Ok(out);
    }
    let (sy, sz) = (ny + 1, nz + 1);
    let idx = |x: usize, y: usize, z: usize| (x * sy + y) * sz + z;
    let mut sat = vec![0u32; (nx + 1) * sy * sz];
    for x in 0..nx {
        for y in 0..ny {
            for z in 0..nz {
                let v = u32::from(occ[(x * ny + y) * nz + z] != 0);
                sat[idx(x + 1, y + 1, z + 1)] = v
                    .wrapping_add(sat[idx(x, y + 1, z + 1)])
                    .wrapping_add(sat[idx(x + 1, y, z + 1)])
                    .wrapping_add(sat[idx(x + 1, y + 1, z)])
                    .wrapping_sub(sat[idx(x, y, z + 1)])
                    .wrapping_sub(sat[idx(x, y + 1, z)])
                    .wrapping_sub(sat[idx(x + 1, y, z)])
                    .wrapping_add(sat[idx(x, y, z)]);
            }
        }
    }
    for x in 0..nx {
        for y in 0..ny {
            for z in 0..nz {
                let occupied = occ[(x * ny + y) * nz + z] != 0;
                for s in 1..=s_max {
                    let r = s as usize;
                    let (x1, x2) = (x.saturating_sub(r), (x + r + 1).min(nx));
                    let (y1, y2) = (y.saturating_sub(r), (y + r + 1).min(ny));
                    let (z1, z2) = (z.saturating_sub(r), (z + r + 1).min(nz));
                    let count = sat[idx(x2, y2, z2)]
                        .wrapping_sub(sat[idx(x1, y2, z2)])
                        .wrapping_sub(sat[idx(x2, y1, z2)])
                        .wrapping_sub(sat[idx(x2, y2, z1)])
                        .wrapping_add(sat[idx(x1, y1, z2)])
                        .wrapping_add(sat[idx(x1, y2, z1)])
                        .wrapping_add(sat[idx(x2, y1, z1)])
                        .wrapping_sub(sat[idx(x1, y1, z1)]);
                    let full = ((2 * r + 1) as u64).pow(3);
                    let homogeneous = if occupied {
                        count as u64 == full
                    } else {
                        count == 0
                    };
                    if !homogeneous {
                        break;
                    }
                    out[(x * ny + y) * nz + z] = if occupied { -s } else { s };
                }
            }
        }
    }
    Ok(out)
}

/// SCF bin targets of the anchors.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct ScfTargets {
    /// Planar (or scalar) bin index `s + s_max` per anchor, 255 = ignore.
    pub planar: Vec<u8>,
    /// Vertical bin index per anchor (decomposed only).
    pub vertical: Option<Vec<u8>>,
}

/// Targets for anchors `coords` (`(b, x, y, z)` on the grid `dims`) from the dense `1/2`-resolution
/// labels `labels[b]` (flat `[X][Y][Z]`, 0 empty, 255 ignore); see the module docs.
pub fn scf_targets(
    coords: &[Coord],
    labels: &[Vec<u8>],
    dims: [usize; 3],
    decomposition: ScfDecomposition,
    s_max_planar: u32,
    s_max_vertical: u32,
) -> Result<ScfTargets, ModelError> {
    let volume: usize = dims.iter().product();
    let mut needed = vec![false; labels.len()];
    let mut lin = Vec::with_capacity(coords.len());
    for (i, c) in coords.iter().enumerate() {
        let b = usize::try_from(c[0]).ok().filter(|&b| b < labels.len());
        let inside = (0..3).all(|a| c[a + 1] >= 0 && (c[a + 1] as usize) < dims[a]);
        let b = match (b, inside) {
            (Some(b), true) => b,
            _ => {
                return Err(ModelError::Input(format!(
                    "SCF targets: anchor {i} at {c:?} is outside {} items of {dims:?}",
                    labels.len()
                )))
            }
        };
        needed[b] = true;
        lin.push((
            b,
            (c[1] as usize * dims[1] + c[2] as usize) * dims[2] + c[3] as usize,
        ));
    }
    let mut planar_gt: Vec<Vec<i8>> = vec![Vec::new(); labels.len()];
    let mut vertical_gt: Vec<Vec<i8>> = vec![Vec::new(); labels.len()];
    for (b, lab) in labels.iter().enumerate() {
        if !needed[b] {
            continue;
        }
        if lab.len() != volume {
            return Err(ModelError::Input(format!(
                "SCF targets: item {b} has {} labels, dims {dims:?} need {volume}",
                lab.len()
            )));
        }
        let occ: Vec<u8> = lab.iter().map(|&l| u8::from(is_occupied(l))).collect();
        let geo = |e: occ_geometry::scf::ScfError| ModelError::Input(format!("SCF targets: {e}"));
        match decomposition {
            ScfDecomposition::Decomposed => {
                planar_gt[b] = scf_planar(&occ, dims, s_max_planar).map_err(geo)?;
                vertical_gt[b] = scf_vertical(&occ, dims, s_max_vertical).map_err(geo)?;
            }
            ScfDecomposition::Scalar => {
                planar_gt[b] = scf_isotropic(&occ, dims, s_max_planar)?;
            }
        }
    }
    let bin = |s: i8, s_max: u32| (i32::from(s) + s_max as i32) as u8;
    let mut planar = Vec::with_capacity(coords.len());
    let mut vertical = Vec::with_capacity(coords.len());
    for &(b, l) in &lin {
        if labels[b][l] == IGNORE {
            planar.push(IGNORE);
            vertical.push(IGNORE);
        } else {
            planar.push(bin(planar_gt[b][l], s_max_planar));
            if decomposition == ScfDecomposition::Decomposed {
                vertical.push(bin(vertical_gt[b][l], s_max_vertical));
            }
        }
    }
    Ok(ScfTargets {
        planar,
        vertical: (decomposition == ScfDecomposition::Decomposed).then_some(vertical),
    })
}
