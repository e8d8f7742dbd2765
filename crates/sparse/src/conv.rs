//! Sparse 3D convolution layers: submanifold, regular (dilating or strided), transposed and inverse.
//!
//! Weight layout `[Cout, kx, ky, kz, Cin]` (spconv "KRSC"), cross-correlation: for a regular or
//! submanifold layer `out[o] = sum_k W[:, k, :] @ in[o*stride - padding + k*dilation]`.

use crate::backend::{sparse_conv, SparseConvBackend};
use crate::error::SparseError;
use crate::kernel_map::{conv_map, conv_map_deferred, inverse_of, ConvGeometry, MapKind};
use crate::tensor::SparseTensor;
use burn::module::{Initializer, Param};
use burn::prelude::*;
use serde::{Deserialize, Serialize};

/// The kind of sparse convolution.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash, Serialize, Deserialize)]
pub enum ConvKind {
    /// Output sites = input sites (spconv `SubMConv3d`); kernel centred, stride 1, padding ignored.
    Submanifold,
    /// spconv `SparseConv3d`: stride 1 grows the active set, stride > 1 downsamples.
    Regular,
    /// spconv `SparseConvTranspose3d`.
    Transposed,
    /// spconv `SparseInverseConv3d`: restores the sites that a regular convolution with the same kernel,
    /// stride, padding and dilation took as input, reusing its map.
    Inverse,
}

/// Configuration of [`SparseConv3d`].
#[derive(Config, Debug)]
pub struct SparseConv3dConfig {
    /// Input channels.
    pub channels_in: usize,
    /// Output channels.
    pub channels_out: usize,
    /// Kernel extent (x, y, z).
    pub kernel_size: [usize; 3],
    /// Convolution kind.
    #[config(default = "ConvKind::Submanifold")]
    pub kind: ConvKind,
    /// Stride (regular, transposed, inverse).
    #[config(default = "[1, 1, 1]")]
    pub stride: [usize; 3],
    /// Padding (regular, transposed, inverse).
    #[config(default = "[0, 0, 0]")]
    pub padding: [usize; 3],
    /// Dilation.
    #[config(default = "[1, 1, 1]")]
    pub dilation: [usize; 3],
    /// Output padding (transposed).
    #[config(default = "[0, 0, 0]")]
    pub output_padding: [usize; 3],
    /// Learnable bias.
    #[config(default = false)]
    pub bias: bool,
}

impl SparseConv3dConfig {
    /// The geometry this layer's kernel map is keyed by.
    pub fn geometry(&self) -> ConvGeometry {
        ConvGeometry {
            kernel: self.kernel_size,
            stride: self.stride,
            padding: self.padding,
            dilation: self.dilation,
        }
    }

    /// Initialises the layer (Kaiming-uniform weight, like PyTorch's default conv init).
    pub fn init<B: Backend>(&self, device: &B::Device) -> SparseConv3d<B> {
        let kv: usize = self.kernel_size.iter().product();
        let fan_in = self.channels_in * kv;
        let fan_out = self.channels_out * kv;
        let init = Initializer::KaimingUniform {
            gain: 1.0 / 3.0f64.sqrt(),
            fan_out_only: false,
        };
        let [kx, ky, kz] = self.kernel_size;
        let weight = init.init_with(
            [self.channels_out, kx, ky, kz, self.channels_in],
            Some(fan_in),
            Some(fan_out),
            device,
        );
        let bias = self
            .bias
            .then(|| init.init_with([self.channels_out], Some(fan_in), Some(fan_out), device));
        SparseConv3d {
            weight,
            bias,
            kind: self.kind,
            geometry: self.geometry(),
            output_padding: self.output_padding,
        }
    }
}

/// A sparse 3D convolution layer.
#[derive(Module, Debug)]
pub struct SparseConv3d<B: Backend> {
    /// Weight `[Cout, kx, ky, kz, Cin]`.
    pub weight: Param<Tensor<B, 5>>,
    /// Optional bias `[Cout]`.
    pub bias: Option<Param<Tensor<B, 1>>>,
    kind: ConvKind,
    geometry: ConvGeometry,
    output_padding: [usize; 3],
}

impl<B: SparseConvBackend> SparseConv3d<B> {
    /// Applies the layer.
    ///
    /// # Shapes
    /// - input: N sites x Cin -> output: M sites x Cout (M = N for submanifold)
    pub fn forward(&self, input: SparseTensor<B>) -> crate::error::Result<SparseTensor<B>> {
        sparse_conv3d(
            input,
            self.weight.val(),
            self.bias.as_ref().map(|b| b.val()),
            self.kind,
            self.geometry,
            self.output_padding,
        )
    }

    /// The layer kind.
    pub fn kind(&self) -> ConvKind {
        self.kind
    }
    /// The layer geometry.
    pub fn geometry(&self) -> ConvGeometry {
        self.geometry
    }
}

/// Functional sparse convolution with an explicit weight `[Cout, kx, ky, kz, Cin]`.
pub fn sparse_conv3d<B: SparseConvBackend>(
    input: SparseTensor<B>,
    weight: Tensor<B, 5>,
    bias: Option<Tensor<B, 1>>,
    kind: ConvKind,
    geometry: ConvGeometry,
    output_padding: [usize; 3],
) -> crate::error::Result<SparseTensor<B>> {
    let [cout, kx, ky, kz, cin] = weight.dims();
    if [kx, ky, kz] != geometry.kernel {
        return Err(SparseError::WeightLayout {
            cout,
            kernel: geometry.kernel,
            cin: input.channels(),
            got: weight.dims().to_vec(),
        });
    }
    if cin != input.channels() {
        return Err(SparseError::Shape(format!(
            "input has {} channels but the weight [Cout, kx, ky, kz, Cin] = {:?} expects Cin = {cin}",
            input.channels(),
            weight.dims()
        )));
    }
    if let Some(b) = &bias {
        if b.dims()[0] != cout {
            return Err(SparseError::Shape(format!(
                "bias has {} entries, expected Cout = {cout}",
                b.dims()[0]
            )));
        }
    }
    let set = input.coord_set().clone();
    // A backend that builds its tables on its device gets maps without host pairs.
    let build = if B::builds_maps_on_device() {
        conv_map_deferred
    } else {
        conv_map
    };
    let (out_set, map) = match kind {
        ConvKind::Submanifold => build(&set, MapKind::Submanifold, geometry)?,
        ConvKind::Regular => build(&set, MapKind::Regular, geometry)?,
        ConvKind::Transposed => build(&set, MapKind::Transposed { output_padding }, geometry)?,
        ConvKind::Inverse => inverse_of(&set, geometry)?,
    };
    let kv = kx * ky * kz;
    if crate::flops::enabled() {
        // A map without host pairs is counted from its device table, read after the next sync:
        // counting never builds host pairs the computation does not need.
        let macs_per_pair = (cin * cout) as u64;
        match B::device_pair_count(&map, &input.device()) {
            Some(count) => {
                crate::flops::add_later(Box::new(move || count() as u64 * macs_per_pair))
            }
            None => crate::flops::add(map.num_pairs() as u64 * macs_per_pair),
        }
    }
    let w = weight.reshape([cout, kv, cin]);
    let mut feats = sparse_conv(input.into_feats(), w, map, false);
    if let Some(b) = bias {
        feats = feats + b.unsqueeze_dim(0);
    }
    SparseTensor::from_parts(out_set, feats)
}
