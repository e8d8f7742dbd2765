//! Sparse max pooling with any box kernel: the maximum over the active inputs under the window
//! (spconv `SparseMaxPool3d`: inactive sites do not count as zeros).

use crate::backend::index_tensor;
use crate::kernel_map::{conv_map, ConvGeometry, MapKind};
use crate::tensor::SparseTensor;
use burn::prelude::*;

/// Configuration of [`SparseMaxPool3d`].
#[derive(Config, Debug)]
pub struct SparseMaxPool3dConfig {
    /// Window extent (x, y, z).
    pub kernel_size: [usize; 3],
    /// Stride; defaults to the kernel size.
    #[config(default = "None")]
    pub stride: Option<[usize; 3]>,
    /// Padding.
    #[config(default = "[0, 0, 0]")]
    pub padding: [usize; 3],
    /// Dilation.
    #[config(default = "[1, 1, 1]")]
    pub dilation: [usize; 3],
}

impl SparseMaxPool3dConfig {
    /// Builds the (parameter-free) layer.
    pub fn init(&self) -> SparseMaxPool3d {
        SparseMaxPool3d {
            geometry: ConvGeometry {
                kernel: self.kernel_size,
                stride: self.stride.unwrap_or(self.kernel_size),
                padding: self.padding,
                dilation: self.dilation,
            },
        }
    }
}

/// Sparse max pooling.
#[derive(Clone, Debug)]
pub struct SparseMaxPool3d {
    geometry: ConvGeometry,
}

impl SparseMaxPool3d {
    /// The pooling geometry (its map is shared with a regular convolution of the same geometry, and an
    /// inverse convolution can restore its input sites).
    pub fn geometry(&self) -> ConvGeometry {
        self.geometry
    }

    /// Applies the pooling. The winning input of every (output, channel) is found on the host; the values
    /// are then gathered on the device, so the gradient flows to the winners.
    ///
    /// # Shapes
    /// - input: N sites x C -> output: M sites x C
    pub fn forward<B: Backend>(
        &self,
        input: SparseTensor<B>,
    ) -> crate::error::Result<SparseTensor<B>> {
        let set = input.coord_set().clone();
        let (out_set, map) = conv_map(&set, MapKind::Regular, self.geometry)?;
        let c = input.channels();
        let n = input.num_active();
        let device = input.device();
        let vals: Vec<f32> = input.feats_to_vec();
        let m = map.n_out();
        let mut best = vec![f32::NEG_INFINITY; m * c];
        let mut arg = vec![u32::MAX; m * c];
        for k in 0..map.kernel_volume() {
            let (ins, outs) = map.pairs(k);
            for (&i, &o) in ins.iter().zip(outs) {
                let (i, o) = (i as usize, o as usize);
                for ch in 0..c {
                    let v = vals[i * c + ch];
                    let slot = o * c + ch;
                    // Ties go to the lowest input row, so the choice is deterministic.
                    if v > best[slot]
                        || (v == best[slot] && (i as u32) < arg[slot])
                        || arg[slot] == u32::MAX
                    {
                        best[slot] = v;
                        arg[slot] = i as u32;
                    }
                }
            }
        }
        let flat_idx: Vec<u32> = arg
            .iter()
            .enumerate()
            .map(|(slot, &i)| i * c as u32 + (slot % c) as u32)
            .collect();
        let flat = input.into_feats().reshape([n * c]);
        let out = if m == 0 {
            Tensor::zeros([0, c], &device)
        } else {
            flat.select(0, index_tensor::<B>(&flat_idx, &device))
                .reshape([m, c])
        };
        SparseTensor::from_parts(out_set, out)
    }
}
