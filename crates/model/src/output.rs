//! The model output: class logits on a sparse set of voxels, losses, statistics.

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
    /// Named loss terms (present when the batch had targets).
    pub losses: Vec<(String, Tensor<B, 1>)>,
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
        let u = self.upsample.max(1);
        for (c, &cls) in self.coords.iter().zip(&am) {
            let b = c[0] as usize;
            if b >= batch_size {
                continue;
            }
            for dx in 0..u {
                for dy in 0..u {
                    for dz in 0..u {
                        let (x, y, z) = (
                            c[1] as usize * u + dx,
                            c[2] as usize * u + dy,
                            c[3] as usize * u + dz,
                        );
                        if x < fx && y < fy && z < fz {
                            out[b][(x * fy + y) * fz + z] = cls as u8;
                        }
                    }
                }
            }
        }
        out
    }
}
