//! The sampling step of deformable cross attention ([`crate::sparseocc_pp::dca`]) as an op: its
//! inputs ([`DcaSample`]: the (query, view) hits, the projected value maps, the predicted offsets and
//! attention weights, an optional per-hit gate) and its portable form ([`sample_tensor_ops`], burn
//! tensor ops on any backend, differentiable through burn's autodiff). The CPU backends replace it by
//! the host loops of [`crate::kernels::dca_host`] through [`crate::kernels::ModelBackend::dca_sample`].
//!
//! `out[q] = 1/|V_q| · Σ_{hits h of q} g_h · Σ_{m, l, j} w_{qmlj} · bilinear(values_l[img_h], ref_h/s_l + Δp_{qmlj})[head m]`

use crate::error::ModelError;
use crate::sample::bilinear_sample;
use burn::prelude::*;
use burn::tensor::TensorData;
use occ_sparse::{gather_rows, scatter_add_rows, RowPlan, SparseConvBackend};
use std::sync::Arc;

/// Which views see which query: one entry per (query, view) hit, sorted by image then query.
/// Built by [`crate::sparseocc_pp::dca::project_queries`].
#[derive(Clone, Debug, Default, PartialEq)]
pub struct ViewHits {
    /// Number of queries.
    pub num_queries: usize,
    /// Number of images `B·V`.
    pub num_images: usize,
    /// Query row of each hit.
    pub query: Vec<u32>,
    /// Image index `b·V + v` of each hit.
    pub image: Vec<u32>,
    /// Slot of each hit among the hits of its image (0-based).
    pub slot: Vec<u32>,
    /// Reference point `(u, v)` in network-input pixels.
    pub uv: Vec<[f64; 2]>,
    /// Depth of the voxel centre along the view's optical axis, metres.
    pub depth_m: Vec<f64>,
    /// Number of views that see each query.
    pub views_per_query: Vec<u32>,
    /// Largest number of hits of one image.
    pub max_per_image: usize,
}

impl ViewHits {
    /// Number of (query, view) hits.
    pub fn len(&self) -> usize {
        self.query.len()
    }
    /// True when no view sees any query.
    pub fn is_empty(&self) -> bool {
        self.query.is_empty()
    }
}

/// The per-pixel rows of a set of multi-level image feature maps, channel-last and concatenated over
/// the levels: `rows [Σ_l B·V·h_l·w_l, width]` in level, image, row, column order. The layout the
/// DCA sampling reads its values in ([`DcaSample::values`]). A frame's encoder features are laid out
/// once ([`Self::from_nchw`]) and every DCA block of the frame projects them with one row-wise linear
/// map ([`Self::map_rows`]), since a per-pixel map commutes with the concatenation.
#[derive(Clone, Debug)]
pub struct FeatureRows<B: Backend> {
    /// `[Σ_l B·V·h_l·w_l, width]`.
    pub rows: Tensor<B, 2>,
    /// `[B·V, h_l, w_l]` of each level.
    pub levels: Vec<[usize; 3]>,
}

impl<B: Backend> FeatureRows<B> {
    /// The rows of the feature maps `maps[l] [B·V, C, h_l, w_l]` (one transposing copy per level
    /// and one concatenation). An error when the levels disagree on `B·V` or `C`, or have no pixels.
    pub fn from_nchw(maps: &[Tensor<B, 4>]) -> Result<Self, ModelError> {
        let first = maps
            .first()
            .ok_or_else(|| ModelError::Input("image features: no levels".into()))?
            .dims();
        let mut rows = Vec::with_capacity(maps.len());
        let mut levels = Vec::with_capacity(maps.len());
        for (l, f) in maps.iter().enumerate() {
            let [bv, c, h, w] = f.dims();
            if bv != first[0] || c != first[1] || h == 0 || w == 0 {
                return Err(ModelError::Input(format!(
                    "image features: level {l} is {:?} and level 0 {first:?} (each level needs the same images and channels, and pixels)",
                    f.dims()
                )));
            }
            rows.push(f.clone().permute([0, 2, 3, 1]).reshape([bv * h * w, c]));
            levels.push([bv, h, w]);
        }
        Ok(Self {
            rows: Tensor::cat(rows, 0),
            levels,
        })
    }

    /// The rows of channel-last maps `maps[l] [B·V, h_l, w_l, width]` (one concatenation).
    ///
    /// # Panics
    /// When the levels disagree on `width`.
    pub fn from_channel_last(maps: Vec<Tensor<B, 4>>) -> Self {
        let mut levels = Vec::with_capacity(maps.len());
        let mut rows = Vec::with_capacity(maps.len());
        for m in maps {
            let [bv, h, w, d] = m.dims();
            levels.push([bv, h, w]);
            rows.push(m.reshape([bv * h * w, d]));
        }
        Self {
            rows: Tensor::cat(rows, 0),
            levels,
        }
    }

    /// Width of each row (`C` of the features, `D` of the values).
    pub fn width(&self) -> usize {
        self.rows.dims()[1]
    }

    /// Number of images `B·V` (0 without levels).
    pub fn num_images(&self) -> usize {
        self.levels.first().map_or(0, |l| l[0])
    }

    /// Level `l` as a channel-last map `[B·V, h_l, w_l, width]` (a view of its rows, no copy).
    pub fn level(&self, l: usize) -> Tensor<B, 4> {
        let start: usize = self.levels[..l].iter().map(|&[n, h, w]| n * h * w).sum();
        let [n, h, w] = self.levels[l];
        self.rows
            .clone()
            .narrow(0, start, n * h * w)
            .reshape([n, h, w, self.width()])
    }

    /// The same levels with `rows` replaced by `f(rows)` (a row-wise map keeping the row count).
    pub fn map_rows(&self, f: impl FnOnce(Tensor<B, 2>) -> Tensor<B, 2>) -> Self {
        Self {
            rows: f(self.rows.clone()),
            levels: self.levels.clone(),
        }
    }
}

/// The inputs of the DCA sampling op. Sizes: `N` queries, `M` heads, `L` levels, `P` points per
/// head and level, width `D` (`D / M` per head), `B·V` images.
#[derive(Clone, Debug)]
pub struct DcaSample<'a, B: Backend> {
    /// Which views see which query, and where (the reference points).
    pub hits: &'a ViewHits,
    /// Input pixels per feature pixel of each level (`L`).
    pub strides: &'a [usize],
    /// The projected value maps of all levels as rows `[Σ_l B·V·h_l·w_l, D]` (`D` head-major).
    pub values: FeatureRows<B>,
    /// Sampling offsets `[N, M, L, P, 2]`, `(x, y)` in feature pixels of each level.
    pub offsets: Tensor<B, 5>,
    /// Attention weights `[N, M, L, P]`.
    pub weights: Tensor<B, 4>,
    /// Per-hit gate `[hits.len()]`; `None` = all ones.
    pub gate: Option<Tensor<B, 1>>,
}

impl<B: Backend> DcaSample<'_, B> {
    /// Heads `M` and points per head and level `P`.
    pub fn heads_points(&self) -> (usize, usize) {
        let [_, m, _, p, _] = self.offsets.dims();
        (m, p)
    }

    /// Width `D` of the values (and of the output).
    pub fn width(&self) -> usize {
        self.values.width()
    }
}

/// The sampling composed of burn tensor ops (differentiable; any backend): the hits are laid out per
/// image in a padded sampling grid, one `grid_sample` per level, weighted, summed over the levels,
/// gated, scattered onto their queries and divided by each query's number of views.
///
/// # Shapes
/// see [`DcaSample`]; returns `[N, D]`
pub fn sample_tensor_ops<B: SparseConvBackend>(s: DcaSample<'_, B>) -> Tensor<B, 2> {
    let (m, p) = s.heads_points();
    let d = s.width();
    let DcaSample {
        hits,
        strides,
        values,
        offsets,
        weights,
        gate,
    } = s;
    let device = offsets.device();
    let n = offsets.dims()[0];
    let dh = d / m;
    let nh = hits.len();
    // Hits by query (gathers from the queries, and the final scatter onto them) and by padded
    // slot of their image (the sampling grid), as row plans: a deterministic segment sum on the
    // cubecl backends instead of burn's per-column `select_assign` loop (occ_sparse::rows).
    let by_query = row_plan(hits.query.clone(), n);
    let [_, _, nl, _, _] = offsets.dims();
    let off =
        gather_rows(offsets.reshape([n, m * nl * p * 2]), &by_query).reshape([nh, m, nl, p, 2]);
    let wts = gather_rows(weights.reshape([n, m * nl * p]), &by_query).reshape([nh, m, nl, p]);
    let pmax = hits.max_per_image;
    let slot: Vec<u32> = hits
        .image
        .iter()
        .zip(&hits.slot)
        .map(|(&i, &s)| i * pmax as u32 + s)
        .collect();
    let n_images = hits
        .image
        .iter()
        .map(|&i| i as usize + 1)
        .max()
        .unwrap_or(0);
    let mut acc: Option<Tensor<B, 3>> = None;
    for (lvl, &stride) in strides.iter().enumerate().take(values.levels.len()) {
        let v = values.level(lvl);
        let [bv, fh, fw, _] = v.dims();
        // Reference points, normalised for align_corners = false.
        let sx = 2.0 / (stride as f64 * fw as f64);
        let sy = 2.0 / (stride as f64 * fh as f64);
        let refs: Vec<f64> = hits
            .uv
            .iter()
            .flat_map(|&[u, v]| [(u + 0.5) * sx - 1.0, (v + 0.5) * sy - 1.0])
            .collect();
        let refs = Tensor::<B, 4>::from_data(TensorData::new(refs, [nh, 1, 1, 2]), &device);
        let scale = Tensor::<B, 4>::from_data(
            TensorData::new(vec![2.0 / fw as f64, 2.0 / fh as f64], [1, 1, 1, 2]),
            &device,
        );
        let off_l = off.clone().narrow(2, lvl, 1).reshape([nh, m, p, 2]);
        let loc = off_l * scale + refs; // [nh, M, P, 2]
        let by_slot = row_plan(slot.clone(), bv.max(n_images) * pmax);
        let grid = scatter_add_rows(loc.reshape([nh, m * p * 2]), &by_slot)
            .slice([0..bv * pmax, 0..m * p * 2])
            .reshape([bv, pmax, m, p, 2])
            .permute([0, 2, 1, 3, 4])
            .reshape([bv * m, pmax, p, 2]);
        // [B·V, h, w, D] -> [B·V·M, D/M, h, w] (head-major per image).
        let maps = v
            .reshape([bv, fh, fw, m, dh])
            .permute([0, 3, 4, 1, 2])
            .reshape([bv * m, dh, fh, fw]);
        let sampled = bilinear_sample(maps, grid) // [bv*M, dh, pmax, P]
            .reshape([bv, m, dh, pmax, p])
            .permute([0, 3, 1, 4, 2])
            .reshape([bv * pmax, m * p * dh]);
        let sampled =
            gather_rows(pad_rows(sampled, by_slot.n_out()), &by_slot).reshape([nh, m, p, dh]);
        let w_l = wts.clone().narrow(2, lvl, 1).reshape([nh, m, p, 1]);
        // The sum over the P points as P - 1 additions rather than `sum_dim(2)`: a cubecl reduction
        // over `nh · M · D/M` outputs compiles one kernel when that count is a multiple of its
        // cube and another when not, so a frame's hit count could compile a new kernel (the
        // additions fuse into one element-wise kernel of any size).
        let weighted = sampled * w_l; // [nh, M, P, D/M]
        let mut contrib = weighted.clone().narrow(2, 0, 1);
        for q in 1..p {
            contrib = contrib + weighted.clone().narrow(2, q, 1);
        }
        let contrib = contrib.reshape([nh, m, dh]);
        acc = Some(match acc {
            Some(a) => a + contrib,
            None => contrib,
        });
    }
    let mut per_hit = acc
        .unwrap_or_else(|| Tensor::zeros([nh, m, dh], &device))
        .reshape([nh, d]);
    if let Some(g) = gate {
        per_hit = per_hit * g.reshape([nh, 1]);
    }
    let inv: Vec<f64> = hits
        .views_per_query
        .iter()
        .map(|&c| if c == 0 { 0.0 } else { 1.0 / c as f64 })
        .collect();
    let inv = Tensor::<B, 2>::from_data(TensorData::new(inv, [n, 1]), &device);
    scatter_add_rows(per_hit, &by_query) * inv
}

/// A row plan of host indices known to be in range (built by the hit lists of this module).
fn row_plan(dest: Vec<u32>, n_out: usize) -> Arc<RowPlan> {
    Arc::new(RowPlan::new(dest, n_out).expect("DCA hit indices are in range by construction"))
}

/// `x` with zero rows appended up to `rows` ([`occ_sparse::pad_rows`]: one kernel on the cubecl
/// backends); `x` itself when it has no rows or already `rows` or more.
fn pad_rows<B: SparseConvBackend>(x: Tensor<B, 2>, rows: usize) -> Tensor<B, 2> {
    let r = x.dims()[0];
    if r >= rows || r == 0 {
        return x;
    }
    occ_sparse::pad_rows(x, rows)
}

#[cfg(test)]
mod tests {
    use super::*;
    /// The float type of a process's first tensor is the one burn 0.21 keeps for the device, so
    /// values are read back converted to f64 (every value here is exact in f32).
    type B = burn::backend::NdArray<f64>;

    fn ramp(dims: [usize; 4], start: f64) -> Tensor<B, 4> {
        let n: usize = dims.iter().product();
        let v: Vec<f64> = (0..n).map(|i| start + i as f64).collect();
        Tensor::from_data(TensorData::new(v, dims), &Default::default())
    }

    /// The rows of NCHW maps are their pixels, channel-last, level after level; each level comes
    /// back as a channel-last view; channel-last maps give the same rows; bad levels are refused.
    #[test]
    fn feature_rows_lay_out_every_level_channel_last() {
        let maps = [ramp([2, 3, 4, 5], 0.0), ramp([2, 3, 2, 2], 1000.0)];
        let rows = FeatureRows::from_nchw(&maps).unwrap();
        assert_eq!(rows.rows.dims(), [2 * 4 * 5 + 2 * 2 * 2, 3]);
        assert_eq!(rows.levels, vec![[2, 4, 5], [2, 2, 2]]);
        assert_eq!((rows.width(), rows.num_images()), (3, 2));
        // Row of pixel (image 1, y 2, x 3) of level 0 (row (1·4 + 2)·5 + 3), and of (image 0, y 1,
        // x 0) of level 1 (row 40 + 2).
        let row = |r: usize| {
            rows.rows
                .clone()
                .narrow(0, r, 1)
                .into_data()
                .convert::<f64>()
                .to_vec::<f64>()
        };
        let at = |l: usize, idx: [usize; 4]| {
            let [_, c, h, w] = maps[l].dims();
            let base = if l == 0 { 0.0 } else { 1000.0 };
            base + (((idx[0] * c + idx[1]) * h + idx[2]) * w + idx[3]) as f64
        };
        assert_eq!(
            row((4 + 2) * 5 + 3).unwrap(),
            (0..3).map(|c| at(0, [1, c, 2, 3])).collect::<Vec<_>>()
        );
        assert_eq!(
            row(40 + 2).unwrap(),
            (0..3).map(|c| at(1, [0, c, 1, 0])).collect::<Vec<_>>()
        );
        let last: Vec<Tensor<B, 4>> = maps
            .iter()
            .map(|m| m.clone().permute([0, 2, 3, 1]))
            .collect();
        for (l, m) in last.iter().enumerate() {
            assert_eq!(rows.level(l).into_data(), m.clone().into_data());
        }
        let again = FeatureRows::from_channel_last(last);
        assert_eq!(again.levels, rows.levels);
        assert_eq!(again.rows.into_data(), rows.rows.clone().into_data());
        let doubled = rows.map_rows(|r| r * 2.0);
        assert_eq!(doubled.levels, rows.levels);
        assert_eq!(
            doubled.level(1).into_data(),
            (rows.level(1) * 2.0).into_data()
        );
        // Levels that disagree on channels or images, an empty level, no levels.
        assert!(FeatureRows::from_nchw(&[maps[0].clone(), ramp([2, 2, 2, 2], 0.0)]).is_err());
        assert!(FeatureRows::from_nchw(&[maps[0].clone(), ramp([1, 3, 2, 2], 0.0)]).is_err());
        assert!(FeatureRows::from_nchw(&[maps[0].clone(), ramp([2, 3, 0, 2], 0.0)]).is_err());
        assert!(FeatureRows::<B>::from_nchw(&[]).is_err());
    }
}
