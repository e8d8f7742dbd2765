//! One sparse convolution on plain arrays, in spconv's index layout: for callers outside burn (the
//! Python package's `sparseocc.sparse.conv3d`, the `conv_npy` example).
//!
//! The input is validated as [`CoordSet::new`] validates it (every site inside the batch and spatial
//! shape, no duplicates) and put in (b, x, y, z) order; the kernel map is built on a fresh coordinate
//! set and the features are computed by the host kernels of [`crate::host`] straight on the slices
//! (no tensors; the features are read where they lie, in the caller's row order, and the output is
//! not copied).

use crate::coords::{pack, validate_sorted_order};
use crate::host::{conv_forward, WeightView};
use crate::kernel_map::{conv_map, ConvGeometry, MapKind};
use crate::{Coord, CoordSet, Result, SparseError};
use std::sync::Arc;
use std::time::Instant;

/// Which convolution [`conv3d_arrays`] runs.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum ArrayConvKind {
    /// Submanifold (spconv `SubMConv3d`): the output sites are the input sites.
    Submanifold,
    /// Regular (spconv `SparseConv3d`): every site a kernel offset reaches.
    Regular,
    /// Transposed (spconv `SparseConvTranspose3d`).
    Transposed,
}

impl ArrayConvKind {
    /// spconv's flags: `subm` (submanifold) wins over `transposed`; neither is regular.
    pub fn from_flags(subm: bool, transposed: bool) -> Self {
        match (subm, transposed) {
            (true, _) => ArrayConvKind::Submanifold,
            (false, true) => ArrayConvKind::Transposed,
            (false, false) => ArrayConvKind::Regular,
        }
    }
}

/// The geometry of one [`conv3d_arrays`] call.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct ArrayConvSpec {
    /// Spatial shape `(X, Y, Z)` of the input grid.
    pub spatial_shape: [usize; 3],
    /// Kernel size per axis.
    pub kernel: [usize; 3],
    /// Stride per axis.
    pub stride: [usize; 3],
    /// Padding per axis.
    pub padding: [usize; 3],
    /// Dilation per axis.
    pub dilation: [usize; 3],
    /// Submanifold, regular or transposed.
    pub kind: ArrayConvKind,
    /// Batch size; `None` = the largest batch index + 1.
    pub batch_size: Option<usize>,
}

/// The result of [`conv3d_arrays`].
#[derive(Clone, Debug)]
pub struct ArrayConvOutput {
    /// Output sites `(batch, x, y, z)`, sorted.
    pub coords: Vec<Coord>,
    /// Output features, row-major `[coords.len(), c_out]`.
    pub feats: Vec<f32>,
    /// Output channels.
    pub c_out: usize,
    /// Spatial shape of the output grid.
    pub out_spatial_shape: [usize; 3],
    /// (input, output) pairs of the kernel map over all offsets.
    pub pairs: usize,
    /// Milliseconds to build the kernel map and output sites.
    pub ms_kernel_map: f64,
    /// Milliseconds of the feature compute.
    pub ms_compute: f64,
}

/// Sparse convolution of `feats` (row-major `[N, c_in]`) at `coords` with `weight` (row-major
/// `[c_out, kx, ky, kz, c_in]`, spconv 2.x's layout; cross-correlation, no bias).
///
/// # Shapes
/// - `coords`: `[N]` sites `(batch, x, y, z)`, any order, no duplicates
/// - `feats`: `N * c_in` values
/// - `weight`: `c_out * kx * ky * kz * c_in` values
/// - output: `[M]` sorted sites and `M * c_out` features
///
/// Errors name the offending argument: a site outside the grid or the batch, a duplicate site, a
/// length that does not fit the shapes, an invalid geometry (e.g. an even submanifold kernel).
pub fn conv3d_arrays(
    coords: Vec<Coord>,
    feats: &[f32],
    c_in: usize,
    weight: &[f32],
    c_out: usize,
    spec: &ArrayConvSpec,
) -> Result<ArrayConvOutput> {
    let n = coords.len();
    if c_in == 0 || c_out == 0 {
        return Err(SparseError::Shape(format!(
            "channels must be positive (c_in {c_in}, c_out {c_out})"
        )));
    }
    // Products in checked arithmetic: a wrapped product could equal the slice's length.
    if Some(feats.len()) != n.checked_mul(c_in) {
        return Err(SparseError::Shape(format!(
            "feats has {} values, {n} sites x {c_in} channels need {}",
            feats.len(),
            n as u128 * c_in as u128
        )));
    }
    if spec.kernel.contains(&0) {
        return Err(SparseError::Config(format!(
            "kernel {:?} has a zero extent",
            spec.kernel
        )));
    }
    let kv = spec
        .kernel
        .iter()
        .try_fold(1usize, |p, &k| p.checked_mul(k));
    let want = kv.and_then(|kv| kv.checked_mul(c_out)?.checked_mul(c_in));
    let Some(kv) = kv.filter(|_| want == Some(weight.len())) else {
        return Err(SparseError::WeightLayout {
            cout: c_out,
            kernel: spec.kernel,
            cin: c_in,
            got: vec![weight.len()],
        });
    };
    let batch = spec.batch_size.unwrap_or_else(|| {
        coords
            .iter()
            .map(|c| c[0].max(0) as usize + 1)
            .max()
            .unwrap_or(1)
    });
    let geom = ConvGeometry::new(spec.kernel)
        .with_stride(spec.stride)
        .with_padding(spec.padding)
        .with_dilation(spec.dilation);
    let kind = match spec.kind {
        ArrayConvKind::Submanifold => MapKind::Submanifold,
        ArrayConvKind::Regular => MapKind::Regular,
        ArrayConvKind::Transposed => MapKind::Transposed {
            output_padding: [0; 3],
        },
    };
    // Validation sorts the sites: every map built on sorted input sites yields sorted output sites
    // (submanifold keeps them; regular and transposed number their outputs in key order), so the
    // output needs no sort. The features stay where they are: the map's input rows are renamed
    // back to the caller's rows instead.
    let order = validate_sorted_order(&coords, spec.spatial_shape, batch)?;
    let coords = match &order {
        None => coords,
        Some(order) => order.iter().map(|&row| coords[row as usize]).collect(),
    };
    let set = Arc::new(CoordSet::from_valid_unique(
        coords,
        spec.spatial_shape,
        batch,
        [1, 1, 1],
    ));
    let t0 = Instant::now();
    let (out_set, map) = conv_map(&set, kind, geom)?;
    let map = match &order {
        None => map,
        Some(order) => Arc::new(map.with_input_rows(order)),
    };
    let ms_kernel_map = t0.elapsed().as_secs_f64() * 1e3;
    debug_assert!(out_set.coords().windows(2).all(|w| pack(w[0]) < pack(w[1])));

    let t0 = Instant::now();
    let wv = WeightView {
        d0: c_out,
        k: kv,
        d2: c_in,
        transposed: false,
    };
    let feats = conv_forward::<f32>(feats, weight, wv, &map);
    let ms_compute = t0.elapsed().as_secs_f64() * 1e3;
    Ok(ArrayConvOutput {
        coords: out_set.coords().to_vec(),
        feats,
        c_out,
        out_spatial_shape: out_set.spatial_shape(),
        pairs: map.num_pairs(),
        ms_kernel_map,
        ms_compute,
    })
}
