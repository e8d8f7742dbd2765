//! Learned sub-voxel output head: class logits for the 8 full-resolution children of every
//! `1/2`-resolution output voxel.
//!
//! **Not in the paper.** SparseOcc++ (paper Sec. 4 and 5.4) predicts at `1/2` of the label resolution
//! and upsamples the logits ×2 ("trilinear interpolation" in Sec. 5.4); any upsampling of a `1/2`
//! prediction doubles a one-voxel-thick surface such as the road (a `2×2×2` block can only be all
//! occupied or all empty), which caps the completion precision near 50 % on such surfaces. This head
//! is the learned alternative (a sparse transposed convolution, kernel 2 and stride 2, followed by a
//! per-voxel MLP): every parent `(b, x, y, z)` becomes its children `(b, 2x+dx, 2y+dy, 2z+dz)`
//! (parent-major rows, child index `4dx + 2dy + dz`, the order of the anchor split in
//! [`crate::sparseocc_pp::anchors`]) with feature `parent + E[child]`, and `ReLU → Linear → ReLU → classifier`
//! gives the logits (the classifier is the model's own final linear layer, shared with the `1/2`
//! output it replaces). Children of voxels that were not predicted stay empty, as in the `1/2` output. Switched on
//! by `SparseOccPPConfig::output = SubVoxel` (the synthetic CPU demo uses it: its ground is one
//! voxel thick); the paper settings keep the `1/2` output.

use crate::error::ModelError;
use burn::module::Param;
use burn::nn::{Initializer, Linear, LinearConfig};
use burn::prelude::*;
use burn::tensor::activation::relu;
use occ_sparse::backend::index_tensor;
use occ_sparse::Coord;

/// Configuration of [`SubVoxelHead`].
#[derive(Config, Debug)]
pub struct SubVoxelHeadConfig {
    /// Width of the parent features.
    pub channels: usize,
}

impl SubVoxelHeadConfig {
    /// Initialises the head.
    pub fn init<B: Backend>(&self, device: &B::Device) -> SubVoxelHead<B> {
        let c = self.channels.max(1);
        SubVoxelHead {
            child_embed: Initializer::Normal {
                mean: 0.0,
                std: 1.0,
            }
            .init([8, c], device),
            hidden: LinearConfig::new(c, c).init(device),
        }
    }
}

/// The head (see the module docs).
#[derive(Module, Debug)]
pub struct SubVoxelHead<B: Backend> {
    /// Child-position embedding `E` `[8, C]`, row `4dx + 2dy + dz`.
    pub child_embed: Param<Tensor<B, 2>>,
    /// `C → C`.
    pub hidden: Linear<B>,
}

/// The 8 children of every parent, parent-major, child index `4dx + 2dy + dz`.
pub fn child_coords(parents: &[Coord]) -> Vec<Coord> {
    let mut out = Vec::with_capacity(parents.len() * 8);
    for c in parents {
        for dx in 0..2 {
            for dy in 0..2 {
                for dz in 0..2 {
                    out.push([c[0], 2 * c[1] + dx, 2 * c[2] + dy, 2 * c[3] + dz]);
                }
            }
        }
    }
    out
}

impl<B: occ_sparse::SparseConvBackend> SubVoxelHead<B> {
    /// Logits of the children of `parents`.
    ///
    /// # Shapes
    /// - `feats`: `[N, C]` on the `N` parents `(b, x, y, z)` of the `1/2`-resolution grid
    /// - `classifier`: `C → num_classes`
    /// - returns the `8N` children (full resolution, parent-major) and their logits `[8N, num_classes]`
    pub fn forward(
        &self,
        parents: &[Coord],
        feats: Tensor<B, 2>,
        classifier: &Linear<B>,
    ) -> Result<(Vec<Coord>, Tensor<B, 2>), ModelError> {
        let [n, c] = feats.dims();
        let [_, ce] = self.child_embed.dims();
        if n != parents.len() || c != ce {
            return Err(ModelError::Input(format!(
                "sub-voxel head: features {:?} for {} voxels, head built for {ce} channels",
                feats.dims(),
                parents.len()
            )));
        }
        let children = child_coords(parents);
        let device = feats.device();
        if n == 0 {
            let k = classifier.weight.dims()[1];
            return Ok((children, Tensor::zeros([0, k], &device)));
        }
        let rows: Vec<u32> = (0..n as u32).flat_map(|r| [r; 8]).collect();
        let x = feats.select(0, index_tensor::<B>(&rows, &device))
            + self.child_embed.val().repeat_dim(0, n);
        let logits = crate::profile::linear(
            classifier,
            relu(crate::profile::linear(&self.hidden, relu(x))),
        );
        Ok((children, logits))
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn children_are_parent_major_in_split_order() {
        let c = child_coords(&[[0, 1, 2, 3], [1, 0, 0, 0]]);
        assert_eq!(c.len(), 16);
        assert_eq!(c[0], [0, 2, 4, 6]);
        assert_eq!(c[1], [0, 2, 4, 7]);
        assert_eq!(c[2], [0, 2, 5, 6]);
        assert_eq!(c[4], [0, 3, 4, 6]);
        assert_eq!(c[7], [0, 3, 5, 7]);
        assert_eq!(c[8], [1, 0, 0, 0]);
        assert_eq!(c[15], [1, 1, 1, 1]);
    }
}
