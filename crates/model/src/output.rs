//! The model output: class logits on a sparse set of voxels, losses, statistics.

use crate::loss::LossKey;
use burn::prelude::*;

/// What every model returns.
#[derive(Clone, Debug)]
pub struct ModelOutput<B: Backend> {
    /// Predicted sites `(b, x, y, z)` on the output grid `out_dims`.
    pub coords: Vec<[i32; 4]>,
    /// Class logits `[N, num_classes]` (class 0 = empty) for each predicted site.
    pub logits: Tensor<B, 2>,
    /// Shape of the grid the sites live on.
    pub out_dims: [usize; 3],
    /// Full-resolution voxels per output voxel along each axis (2 when predicting at 1/2 resolution).
    pub upsample: usize,
    /// Loss terms by name (present when the batch had targets).
    pub losses: Vec<(LossKey, Tensor<B, 1>)>,
    /// Active voxels (or other counts) per stage, for benchmarks and logs.
    pub stats: Vec<(String, usize)>,
}

impl<B: Backend> ModelOutput<B> {
    /// Sum of the loss terms, if any.
    pub fn total_loss(&self) -> Option<Tensor<B, 1>> {
        self.losses
            .iter()
            .map(|(_, l)| l.clone())
            .reduce(|a, b| a + b)
    }

    /// Dense full-resolution class votes `[B][X*Y*Z*C]` (`C = num_classes`, class fastest): the
    /// softmax of each predicted site, copied to its `upsample^3` children; voxels of sites that were
    /// not predicted get an all-zero row (no vote). Its argmax is [`Self::dense_prediction`] (up to
    /// ties; an all-zero row argmaxes to class 0, empty). Summing it over test-time augmentations is
    /// what it is for: the sum averages the passes that predicted a voxel and leaves out those that
    /// did not, so a voxel found by one pass only keeps that pass's classes. (Counting an unpredicted
    /// voxel as certainly empty instead would make the mean an AND of the passes' sparse sets.)
    pub fn dense_probabilities(&self, batch_size: usize, full_dims: [usize; 3]) -> Vec<Vec<f32>> {
        let [fx, fy, fz] = full_dims;
        let c = self.logits.dims()[1].max(1);
        let mut out = vec![vec![0f32; fx * fy * fz * c]; batch_size];
        if self.coords.is_empty() {
            return out;
        }
        let probs: Vec<f32> = burn::tensor::activation::softmax(self.logits.clone(), 1)
            .into_data()
            .convert::<f32>()
            .to_vec::<f32>()
            .unwrap_or_default();
        if probs.len() != self.coords.len() * c {
            return out;
        }
        for (site, p) in self.coords.iter().zip(probs.chunks(c)) {
            self.for_each_child(site, batch_size, full_dims, |b, v| {
                out[b][v * c..(v + 1) * c].copy_from_slice(p)
            });
        }
        out
    }

    /// Dense full-resolution class grids `[B][X*Y*Z]`: argmax at each predicted site, copied to its
    /// `upsample^3` children; sites that were not predicted are empty (0).
    pub fn dense_prediction(&self, batch_size: usize, full_dims: [usize; 3]) -> Vec<Vec<u8>> {
        let [fx, fy, fz] = full_dims;
        let mut out = vec![vec![0u8; fx * fy * fz]; batch_size];
        if self.coords.is_empty() {
            return out;
        }
        let am: Vec<i64> = self
            .logits
            .clone()
            .argmax(1)
            .into_data()
            .convert::<i64>()
            .to_vec::<i64>()
            .unwrap_or_default();
        for (site, &cls) in self.coords.iter().zip(&am) {
            self.for_each_child(site, batch_size, full_dims, |b, v| out[b][v] = cls as u8);
        }
        out
    }

    /// Calls `f(b, v)` for the flat full-resolution index `v` (`[X][Y][Z]`) of every child voxel of
    /// output `site` (its `upsample^3` block, clipped to `full_dims`); nothing for items
    /// `b >= batch_size`.
    fn for_each_child(
        &self,
        site: &[i32; 4],
        batch_size: usize,
        full_dims: [usize; 3],
        mut f: impl FnMut(usize, usize),
    ) {
        let [fx, fy, fz] = full_dims;
        let u = self.upsample.max(1);
        let b = site[0] as usize;
        if site.iter().any(|&v| v < 0) || b >= batch_size {
            return;
        }
        for dx in 0..u {
            for dy in 0..u {
                for dz in 0..u {
                    let (x, y, z) = (
                        site[1] as usize * u + dx,
                        site[2] as usize * u + dy,
                        site[3] as usize * u + dz,
                    );
                    if x < fx && y < fy && z < fz {
                        f(b, (x * fy + y) * fz + z);
                    }
                }
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use burn::backend::NdArray;

    type B = NdArray<f32>;

    #[test]
    fn dense_probabilities_are_the_softmax_at_the_sites_and_no_vote_elsewhere() {
        let device = Default::default();
        let logits = Tensor::<B, 2>::from_data(
            TensorData::new(vec![0.0f32, 2.0, -1.0, 1.0, 0.5, 3.0], [2, 3]),
            &device,
        );
        let out = ModelOutput::<B> {
            coords: vec![[0, 0, 1, 0], [1, 1, 0, 1]],
            logits,
            out_dims: [2, 2, 2],
            upsample: 2,
            losses: vec![],
            stats: vec![],
        };
        let full = [4, 4, 4];
        let probs = out.dense_probabilities(2, full);
        let classes = out.dense_prediction(2, full);
        assert_eq!(probs.len(), 2);
        for (b, (p, cls)) in probs.iter().zip(&classes).enumerate() {
            assert_eq!(p.len(), 64 * 3);
            // One site per item, 8 children each: 8 rows sum to 1, the other 56 are all zero.
            let mut voted = 0;
            for (v, pv) in p.chunks(3).enumerate() {
                let sum = pv.iter().sum::<f32>();
                assert!(
                    (sum - 1.0).abs() < 1e-6 || sum == 0.0,
                    "item {b} voxel {v}: {pv:?}"
                );
                voted += usize::from(sum > 0.0);
                let arg = (0..3)
                    .rev()
                    .max_by(|&i, &j| pv[i].total_cmp(&pv[j]))
                    .unwrap();
                assert_eq!(arg as u8, cls[v], "item {b} voxel {v}");
            }
            assert_eq!(voted, 8, "item {b}");
        }
        // Site (0, 0, 1, 0) covers full-resolution x 0..2, y 2..4, z 0..2 of item 0: voxel (1, 3, 1).
        let e = [0.0f32.exp(), 2.0f32.exp(), (-1.0f32).exp()];
        let s: f32 = e.iter().sum();
        let (x, y, z) = (1, 3, 1);
        let i = ((x * 4 + y) * 4 + z) * 3;
        for k in 0..3 {
            assert!((probs[0][i + k] - e[k] / s).abs() < 1e-6);
        }
        // A voxel no site covers has no vote (and its prediction is empty).
        assert_eq!(&probs[0][0..3], &[0.0, 0.0, 0.0]);
        assert_eq!(classes[0][0], 0);
        assert_eq!(classes[1][((2 * 4) * 4 + 2) as usize], 2);
    }
}
