//! `SparseTensor`: active sites on the host, their features on the burn device.

use crate::backend::index_tensor;
use crate::coords::{Coord, CoordSet};
use crate::error::{Result, SparseError};
use burn::prelude::*;
use burn::tensor::TensorData;
use std::sync::Arc;

/// A sparse voxel tensor: `N` active sites `(batch, x, y, z)` with features `[N, C]`.
///
/// Cloning is cheap (the coordinate set is shared). Tensors produced from one another by submanifold
/// layers, norms or activations share the same [`CoordSet`], and with it the cached kernel maps.
#[derive(Clone, Debug)]
pub struct SparseTensor<B: Backend> {
    coords: Arc<CoordSet>,
    feats: Tensor<B, 2>,
}

impl<B: Backend> SparseTensor<B> {
    /// Builds a tensor from a coordinate list and features; validates ranges, duplicates and row counts.
    ///
    /// # Shapes
    /// - coords: N rows of `(batch, x, y, z)`, feats: `[N, C]`
    pub fn new(
        coords: Vec<Coord>,
        feats: Tensor<B, 2>,
        spatial_shape: [usize; 3],
        batch_size: usize,
    ) -> Result<Self> {
        let set = CoordSet::new(coords, spatial_shape, batch_size)?;
        Self::from_parts(Arc::new(set), feats)
    }

    /// Pairs an existing coordinate set with features (one row per site).
    pub fn from_parts(coords: Arc<CoordSet>, feats: Tensor<B, 2>) -> Result<Self> {
        let [n, _] = feats.dims();
        if n != coords.len() {
            return Err(SparseError::Shape(format!(
                "{} coordinates but {} feature rows",
                coords.len(),
                n
            )));
        }
        Ok(Self { coords, feats })
    }

    /// The same sites with other features (e.g. after an activation).
    pub fn with_feats(&self, feats: Tensor<B, 2>) -> Result<Self> {
        Self::from_parts(self.coords.clone(), feats)
    }

    /// Applies a row-wise function to the features (activations, norms, linear layers).
    pub fn map_feats(self, f: impl FnOnce(Tensor<B, 2>) -> Tensor<B, 2>) -> Result<Self> {
        let coords = self.coords;
        Self::from_parts(coords, f(self.feats))
    }

    /// The coordinate set.
    pub fn coord_set(&self) -> &Arc<CoordSet> {
        &self.coords
    }
    /// The coordinates.
    pub fn coords(&self) -> &[Coord] {
        self.coords.coords()
    }
    /// The features `[N, C]`.
    pub fn feats(&self) -> &Tensor<B, 2> {
        &self.feats
    }
    /// Consumes the tensor, returning its features.
    pub fn into_feats(self) -> Tensor<B, 2> {
        self.feats
    }
    /// Number of active sites.
    pub fn num_active(&self) -> usize {
        self.coords.len()
    }
    /// Number of feature channels.
    pub fn channels(&self) -> usize {
        self.feats.dims()[1]
    }
    /// Spatial shape (x, y, z).
    pub fn spatial_shape(&self) -> [usize; 3] {
        self.coords.spatial_shape()
    }
    /// Batch size.
    pub fn batch_size(&self) -> usize {
        self.coords.batch_size()
    }
    /// Tensor stride.
    pub fn tensor_stride(&self) -> [usize; 3] {
        self.coords.tensor_stride()
    }
    /// Device of the features.
    pub fn device(&self) -> B::Device {
        self.feats.device()
    }

    /// Scatters the features into a dense grid; inactive sites are zero. Differentiable.
    ///
    /// # Shapes
    /// - returns `[B, C, X, Y, Z]`
    pub fn to_dense(&self) -> Tensor<B, 5>
    where
        B: crate::SparseConvBackend,
    {
        let [sx, sy, sz] = self.spatial_shape();
        let b = self.batch_size();
        let c = self.channels();
        let lin: Vec<u32> = self
            .coords
            .linear_indices()
            .into_iter()
            .map(|i| i as u32)
            .collect();
        let cells = b * sx * sy * sz;
        // Sites lie inside the grid (checked when the coordinate set was built), and row indices
        // are 32-bit here as before.
        let plan = crate::rows::RowPlan::new(lin, cells)
            .expect("active sites index a grid of fewer than 2^32 cells");
        let flat = crate::rows::scatter_add_rows(self.feats.clone(), &Arc::new(plan));
        flat.reshape([b, sx, sy, sz, c]).permute([0, 4, 1, 2, 3])
    }

    /// Sparse tensor of the sites of a dense grid where any channel is non-zero (as SparseOcc builds its
    /// input from the LSS volume). Differentiable with respect to the kept values.
    ///
    /// # Shapes
    /// - dense: `[B, C, X, Y, Z]`
    pub fn from_dense(dense: Tensor<B, 5>) -> Result<Self> {
        let [b, c, sx, sy, sz] = dense.dims();
        let device = dense.device();
        let rows = dense
            .permute([0, 2, 3, 4, 1])
            .reshape([b * sx * sy * sz, c]);
        let nonzero = rows.clone().abs().sum_dim(1).greater_elem(0.0);
        let mask: Vec<bool> = nonzero.into_data().iter::<bool>().collect();
        let mut coords = Vec::new();
        let mut idx = Vec::new();
        for (lin, &m) in mask.iter().enumerate() {
            if m {
                let z = lin % sz;
                let y = (lin / sz) % sy;
                let x = (lin / (sz * sy)) % sx;
                let bb = lin / (sz * sy * sx);
                coords.push([bb as i32, x as i32, y as i32, z as i32]);
                idx.push(lin as u32);
            }
        }
        let feats = if idx.is_empty() {
            Tensor::zeros([0, c], &device)
        } else {
            rows.select(0, index_tensor::<B>(&idx, &device))
        };
        let set = CoordSet::from_valid_unique(coords, [sx, sy, sz], b, [1, 1, 1]);
        Self::from_parts(Arc::new(set), feats)
    }

    /// Features as a host `Vec<f32>` (row-major `[N, C]`), for tests and I/O.
    pub fn feats_to_vec(&self) -> Vec<f32> {
        self.feats
            .clone()
            .into_data()
            .convert::<f32>()
            .to_vec::<f32>()
            .unwrap_or_default()
    }

    /// A tensor with sites sorted by (b, x, y, z) (outputs of this library are already sorted; inputs
    /// given by a user may not be).
    pub fn sorted(&self) -> Self {
        let order = self.coords.sorted_order();
        if order.iter().enumerate().all(|(i, &o)| i == o) {
            return self.clone();
        }
        let coords: Vec<Coord> = order.iter().map(|&i| self.coords.coords()[i]).collect();
        let idx: Vec<u32> = order.iter().map(|&i| i as u32).collect();
        let set = CoordSet::from_valid_unique(
            coords,
            self.spatial_shape(),
            self.batch_size(),
            self.tensor_stride(),
        );
        Self {
            coords: Arc::new(set),
            feats: self
                .feats
                .clone()
                .select(0, index_tensor::<B>(&idx, &self.device())),
        }
    }
}

/// Features of a dense `[N, C]` host array as a device tensor (helper for examples and tests).
pub fn feats_from_vec<B: Backend>(
    v: Vec<f32>,
    n: usize,
    c: usize,
    device: &B::Device,
) -> Tensor<B, 2> {
    Tensor::from_data(TensorData::new(v, [n, c]), device)
}
