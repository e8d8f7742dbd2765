//! cubecl kernels of the sparse library, for the cubecl backends (CUDA, WebGPU) behind burn's
//! fusion layer: each kernel has a launcher on the raw `CubeBackend` tensors and a fusion custom
//! op that runs it inside the fused stream (as burn's backend-extension example does for
//! `Fusion<CubeBackend>`). Tested against the NdArray reference by `sparseocc check-backend`
//! (lavapipe when there is no GPU: docs/gpu.md).

use crate::backend::{index_tensor, weight_from_matrix, weight_matrix};
use crate::kernel_map::{ConvGeometry, KernelMap, MapRule, MapSource, Sites};
use crate::rows::RowPlan;
use burn::tensor::backend::Backend;
use burn::tensor::ops::FloatTensor;
use burn::tensor::{DType, Int, Shape, Tensor as BurnTensor, TensorPrimitive};
use burn_cubecl::fusion::FusionCubeRuntime;
use burn_cubecl::kernel::into_contiguous;
use burn_cubecl::ops::numeric::{empty_device_dtype, full_device_dtype};
use burn_cubecl::tensor::CubeTensor;
use burn_cubecl::{BoolElement, CubeBackend, CubeRuntime, FloatElement, IntElement};
use burn_fusion::stream::{Operation, OperationStreams};
use burn_fusion::{Fusion, FusionRuntime, FusionTensor};
use burn_ir::{CustomOpIr, HandleContainer, OperationIr, TensorIr};
use cubecl::prelude::InputScalar;
use cubecl::{calculate_cube_count_elemwise, CubeCount, CubeDim};
use kernel::segment_sum_kernel;
use std::marker::PhantomData;
use std::sync::Arc;

mod kernel {
    use cubecl::prelude::*;

    /// Segment sum over a grouped index list: output value `(r, c)` is the sum of
    /// `values[order[j], c]` for `j` in `offsets[r]..offsets[r + 1]`, in that order. One thread per
    /// output value; no atomics, so the result does not depend on scheduling.
    #[cube(launch_unchecked, address_type = "dynamic")]
    pub(super) fn segment_sum_kernel<F: Numeric, I: Numeric>(
        values: &Tensor<F>,
        order: &Tensor<I>,
        offsets: &Tensor<I>,
        output: &mut Tensor<F>,
        channels: usize,
        #[define(F, I)] _dtypes: [StorageType; 2],
    ) {
        if ABSOLUTE_POS >= output.len() {
            terminate!();
        }
        let row = ABSOLUTE_POS / channels;
        let col = ABSOLUTE_POS % channels;
        let start = usize::cast_from(offsets[row]);
        let end = usize::cast_from(offsets[row + 1]);
        let mut acc = F::from_int(0);
        for j in start..end {
            let h = usize::cast_from(order[j]);
            acc += values[h * channels + col];
        }
        output[ABSOLUTE_POS] = acc;
    }

    /// `x`'s values followed by zeros: output value `j` is `x[j]` below `x`'s length and zero
    /// from there (a contiguous `[n, C]` tensor's rows padded to `[rows, C]`). One unit per
    /// output value.
    #[cube(launch_unchecked, address_type = "dynamic")]
    pub(super) fn pad_rows_kernel<F: Numeric>(
        x: &Tensor<F>,
        output: &mut Tensor<F>,
        #[define(F)] _dtype: StorageType,
    ) {
        if ABSOLUTE_POS >= output.len() {
            terminate!();
        }
        let mut v = F::from_int(0);
        if ABSOLUTE_POS < x.len() {
            v = x[ABSOLUTE_POS];
        }
        output[ABSOLUTE_POS] = v;
    }

    /// Units per side of a cube of the sparse-convolution kernels (`TILE x TILE` units), and the
    /// depth of one step of their inner products (input channels, or rows for the weight gradient).
    pub(super) const TILE: usize = 16;
    /// Output rows of one forward cube (4 per unit).
    pub(super) const FWD_ROWS: usize = 64;
    /// Output channels of one forward cube (2 per unit), and both sides of a weight-gradient
    /// cube's tile (2 x 2 per unit).
    pub(super) const COLS: usize = 32;

    /// Sparse convolution as an implicit GEMM that fetches on demand: output `(r, c)` is
    /// `Σ_k Σ_i x[table[r, k], i] · weight[k · c_in + i, c]` over the present neighbours
    /// (`table[r, k] < n_in`). One cube of `TILE x TILE` units computes a `FWD_ROWS x COLS` output
    /// tile (each unit 4 rows x 2 channels, in registers; rows on the cube's x and z positions,
    /// channel tiles on y), stepping through the kernel offsets and, for each, through the input
    /// channels `TILE` at a time, staged in shared memory. An offset that no row of the tile has
    /// is skipped (no loads, no multiply-adds); neighbours are read straight from `x`, nothing is
    /// gathered into a buffer. Each output is summed by one unit in a fixed order: deterministic,
    /// no atomics. Every size is a runtime value, so the compiled kernel does not depend on the
    /// voxel count.
    #[cube(launch_unchecked, address_type = "dynamic")]
    pub(super) fn sparse_conv_kernel<F: Float, I: Numeric>(
        x: &Tensor<F>,
        table: &Tensor<I>,
        weight: &Tensor<F>,
        output: &mut Tensor<F>,
        n_in: usize,
        n_out: usize,
        kv: usize,
        cin: usize,
        cout: usize,
        #[define(F, I)] _dtypes: [StorageType; 2],
    ) {
        let tx = UNIT_POS_X as usize;
        let ty = UNIT_POS_Y as usize;
        let row_tile = CUBE_POS_Z as usize * CUBE_COUNT_X as usize + CUBE_POS_X as usize;
        let row0 = row_tile * FWD_ROWS;
        let col0 = CUBE_POS_Y as usize * COLS;
        // a[row][i]: FWD_ROWS x TILE; b[i][col]: TILE x COLS.
        let mut a = SharedMemory::<F>::new(FWD_ROWS * TILE);
        let mut b = SharedMemory::<F>::new(TILE * COLS);
        let mut nbr = SharedMemory::<u32>::new(FWD_ROWS);
        let absent = n_in as u32;
        let zero = F::from_int(0);
        let (mut c00, mut c01, mut c10, mut c11) = (zero, zero, zero, zero);
        let (mut c20, mut c21, mut c30, mut c31) = (zero, zero, zero, zero);
        for k in 0..kv {
            if ty < FWD_ROWS / TILE {
                let j = ty * TILE + tx;
                let r = row0 + j;
                let mut v = absent;
                if r < n_out {
                    v = u32::cast_from(table[r * kv + k]);
                }
                nbr[j] = v;
            }
            sync_cube();
            let mut any = false;
            for j in 0..FWD_ROWS {
                if nbr[j] < absent {
                    any = true;
                }
            }
            let mut c0 = 0usize;
            while c0 < cin {
                if any {
                    let ci = c0 + tx;
                    #[unroll]
                    for q in 0..FWD_ROWS / TILE {
                        let rl = ty + q * TILE;
                        let n = nbr[rl];
                        let mut av = zero;
                        if n < absent && ci < cin {
                            av = x[n as usize * cin + ci];
                        }
                        a[rl * TILE + tx] = av;
                    }
                    let wi = c0 + ty;
                    #[unroll]
                    for q in 0..COLS / TILE {
                        let cl = tx + q * TILE;
                        let col = col0 + cl;
                        let mut bv = zero;
                        if wi < cin && col < cout {
                            bv = weight[(k * cin + wi) * cout + col];
                        }
                        b[ty * COLS + cl] = bv;
                    }
                }
                sync_cube();
                if any {
                    for i in 0..TILE {
                        let b0 = b[i * COLS + tx];
                        let b1 = b[i * COLS + tx + TILE];
                        let a0 = a[ty * TILE + i];
                        let a1 = a[(ty + TILE) * TILE + i];
                        let a2 = a[(ty + 2 * TILE) * TILE + i];
                        let a3 = a[(ty + 3 * TILE) * TILE + i];
                        c00 += a0 * b0;
                        c01 += a0 * b1;
                        c10 += a1 * b0;
                        c11 += a1 * b1;
                        c20 += a2 * b0;
                        c21 += a2 * b1;
                        c30 += a3 * b0;
                        c31 += a3 * b1;
                    }
                }
                sync_cube();
                c0 += TILE;
            }
        }
        let (col_a, col_b) = (col0 + tx, col0 + tx + TILE);
        store_pair::<F>(output, row0 + ty, n_out, cout, col_a, col_b, c00, c01);
        store_pair::<F>(
            output,
            row0 + ty + TILE,
            n_out,
            cout,
            col_a,
            col_b,
            c10,
            c11,
        );
        store_pair::<F>(
            output,
            row0 + ty + 2 * TILE,
            n_out,
            cout,
            col_a,
            col_b,
            c20,
            c21,
        );
        store_pair::<F>(
            output,
            row0 + ty + 3 * TILE,
            n_out,
            cout,
            col_a,
            col_b,
            c30,
            c31,
        );
    }

    /// Writes `va`, `vb` at `(r, col_a)`, `(r, col_b)` of a `[n_rows, cols]` output, each where in
    /// range.
    #[cube]
    #[allow(clippy::too_many_arguments)]
    fn store_pair<F: Float>(
        output: &mut Tensor<F>,
        r: usize,
        n_rows: usize,
        cols: usize,
        col_a: usize,
        col_b: usize,
        va: F,
        vb: F,
    ) {
        if r < n_rows {
            if col_a < cols {
                output[r * cols + col_a] = va;
            }
            if col_b < cols {
                output[r * cols + col_b] = vb;
            }
        }
    }

    /// Weight gradient of [`sparse_conv_kernel`], in `splits` partial sums over row ranges:
    /// `partial[s, k · c_in + i, c] = Σ_r x[table[r, k], i] · dy[r, c]` over the rows `r` of range
    /// `s` (`rows_per_split` rows each) whose neighbour at offset `k` is present. One cube of
    /// `TILE x TILE` units per (offset, `COLS`-wide input-channel tile, `COLS`-wide output-channel
    /// tile) on x (`k` slowest) and per range on y, each unit 2 x 2 values in registers, the rows
    /// `TILE` at a time through shared memory; a row step with no neighbour at `k` is skipped. No
    /// atomics: the ranges are summed by [`sum_partials_kernel`].
    #[cube(launch_unchecked, address_type = "dynamic")]
    pub(super) fn sparse_conv_weight_grad_kernel<F: Float, I: Numeric>(
        x: &Tensor<F>,
        dy: &Tensor<F>,
        table: &Tensor<I>,
        partial: &mut Tensor<F>,
        n_in: usize,
        n_out: usize,
        kv: usize,
        cin: usize,
        cout: usize,
        rows_per_split: usize,
        #[define(F, I)] _dtypes: [StorageType; 2],
    ) {
        let tx = UNIT_POS_X as usize;
        let ty = UNIT_POS_Y as usize;
        let ci_tiles = cin.div_ceil(COLS);
        let co_tiles = cout.div_ceil(COLS);
        let pos = CUBE_POS_X as usize;
        let k = pos / (ci_tiles * co_tiles);
        let rest = pos % (ci_tiles * co_tiles);
        let ci0 = (rest / co_tiles) * COLS;
        let co0 = (rest % co_tiles) * COLS;
        let split = CUBE_POS_Y as usize;
        let start = split * rows_per_split;
        let mut end = start + rows_per_split;
        if end > n_out {
            end = n_out;
        }
        // a[row][i]: TILE x COLS input channels; b[row][c]: TILE x COLS of dy.
        let mut a = SharedMemory::<F>::new(TILE * COLS);
        let mut b = SharedMemory::<F>::new(TILE * COLS);
        let mut nbr = SharedMemory::<u32>::new(TILE);
        let absent = n_in as u32;
        let zero = F::from_int(0);
        let (mut c00, mut c01, mut c10, mut c11) = (zero, zero, zero, zero);
        let mut r0 = start;
        while r0 < end {
            if ty == 0 {
                let r = r0 + tx;
                let mut v = absent;
                if r < end {
                    v = u32::cast_from(table[r * kv + k]);
                }
                nbr[tx] = v;
            }
            sync_cube();
            let mut any = false;
            for j in 0..TILE {
                if nbr[j] < absent {
                    any = true;
                }
            }
            if any {
                let mine = nbr[ty];
                let r = r0 + ty;
                #[unroll]
                for q in 0..COLS / TILE {
                    let l = tx + q * TILE;
                    let i = ci0 + l;
                    let mut av = zero;
                    if mine < absent && i < cin {
                        av = x[mine as usize * cin + i];
                    }
                    a[ty * COLS + l] = av;
                    let c = co0 + l;
                    let mut bv = zero;
                    if mine < absent && c < cout {
                        bv = dy[r * cout + c];
                    }
                    b[ty * COLS + l] = bv;
                }
            }
            sync_cube();
            if any {
                for j in 0..TILE {
                    let a0 = a[j * COLS + ty];
                    let a1 = a[j * COLS + ty + TILE];
                    let b0 = b[j * COLS + tx];
                    let b1 = b[j * COLS + tx + TILE];
                    c00 += a0 * b0;
                    c01 += a0 * b1;
                    c10 += a1 * b0;
                    c11 += a1 * b1;
                }
            }
            sync_cube();
            r0 += TILE;
        }
        // The partial sums of range `split` as a `[K · C_in, C_out]` block of rows.
        let row_base = split * kv * cin + k * cin;
        let rows_end = row_base + cin;
        let (o0, o1) = (co0 + tx, co0 + tx + TILE);
        store_pair::<F>(
            partial,
            row_base + ci0 + ty,
            rows_end,
            cout,
            o0,
            o1,
            c00,
            c01,
        );
        store_pair::<F>(
            partial,
            row_base + ci0 + ty + TILE,
            rows_end,
            cout,
            o0,
            o1,
            c10,
            c11,
        );
    }

    /// `out[j] = Σ_s partial[s · len + j]` over `splits` partial sums, in order, one unit per value.
    #[cube(launch_unchecked, address_type = "dynamic")]
    pub(super) fn sum_partials_kernel<F: Float>(
        partial: &Tensor<F>,
        output: &mut Tensor<F>,
        splits: usize,
        #[define(F)] _dtype: StorageType,
    ) {
        if ABSOLUTE_POS >= output.len() {
            terminate!();
        }
        let len = output.len();
        let mut acc = F::from_int(0);
        for s in 0..splits {
            acc += partial[s * len + ABSOLUTE_POS];
        }
        output[ABSOLUTE_POS] = acc;
    }

    /// The rule and grid of a kernel map built on the device ([`super::build_gather_table`]);
    /// all runtime values.
    #[derive(CubeLaunch, CubeType)]
    pub struct MapDims {
        /// Kernel extents along y and z, and the kernel volume.
        pub ky: usize,
        pub kz: usize,
        pub kv: usize,
        /// Stride, padding and dilation per axis.
        pub sx: usize,
        pub sy: usize,
        pub sz: usize,
        pub px: usize,
        pub py: usize,
        pub pz: usize,
        pub dx: usize,
        pub dy: usize,
        pub dz: usize,
        /// The input sites' grid `(X, Y, Z)` and batch size.
        pub gx: usize,
        pub gy: usize,
        pub gz: usize,
        pub batch: usize,
        /// The output sites' grid `(X, Y, Z)`.
        pub ox: usize,
        pub oy: usize,
        pub oz: usize,
        /// Input sites (the table's "absent" value).
        pub n_in: usize,
    }

    /// Row of every input site written into its cell of the dense grid: `grid[cells[r]] = r`
    /// (`cells`: each site's linear index `((b · X + x) · Y + y) · Z + z`). Sites are unique, so
    /// no two units write one cell.
    #[cube(launch_unchecked, address_type = "dynamic")]
    pub(super) fn site_grid_kernel<I: Numeric>(
        cells: &Tensor<I>,
        grid: &mut Tensor<I>,
        dims: &MapDims,
        #[define(I)] _dtype: StorageType,
    ) {
        if ABSOLUTE_POS >= dims.n_in {
            terminate!();
        }
        let cell = usize::cast_from(cells[ABSOLUTE_POS]);
        grid[cell] = I::cast_from(ABSOLUTE_POS);
    }

    /// Input coordinate along one axis that output coordinate `o` reaches through kernel index
    /// `k` (`kernel_map::MapSource::input_of`); `extent` where a backward rule's division is not
    /// exact. The caller checks `0 <= c < extent`.
    #[cube]
    #[allow(clippy::too_many_arguments)]
    fn axis_input(
        o: i32,
        k: i32,
        s: i32,
        p: i32,
        d: i32,
        extent: i32,
        #[comptime] forward: bool,
    ) -> i32 {
        let mut c = extent;
        if forward {
            c = o * s - p + k * d;
        } else {
            let t = o + p - k * d;
            if t >= 0 && t % s == 0 {
                c = t / s;
            }
        }
        c
    }

    /// The gather table of a kernel map: entry `(o, k)` is the row of the input site that output
    /// site `o` reaches through offset `k`, read from the dense grid of [`site_grid_kernel`]
    /// (`n_in` where that site is absent or off the grid). One unit per entry; no atomics.
    #[cube(launch_unchecked, address_type = "dynamic")]
    pub(super) fn gather_table_kernel<I: Numeric>(
        outputs: &Tensor<I>,
        grid: &Tensor<I>,
        table: &mut Tensor<I>,
        dims: &MapDims,
        #[comptime] forward: bool,
        #[define(I)] _dtype: StorageType,
    ) {
        if ABSOLUTE_POS >= table.len() {
            terminate!();
        }
        let cell = usize::cast_from(outputs[ABSOLUTE_POS / dims.kv]);
        let k = ABSOLUTE_POS % dims.kv;
        let kx = i32::cast_from(k / (dims.ky * dims.kz));
        let ky = i32::cast_from((k / dims.kz) % dims.ky);
        let kz = i32::cast_from(k % dims.kz);
        let b = i32::cast_from(cell / (dims.ox * dims.oy * dims.oz));
        let cx = axis_input(
            i32::cast_from((cell / (dims.oy * dims.oz)) % dims.ox),
            kx,
            i32::cast_from(dims.sx),
            i32::cast_from(dims.px),
            i32::cast_from(dims.dx),
            i32::cast_from(dims.gx),
            forward,
        );
        let cy = axis_input(
            i32::cast_from((cell / dims.oz) % dims.oy),
            ky,
            i32::cast_from(dims.sy),
            i32::cast_from(dims.py),
            i32::cast_from(dims.dy),
            i32::cast_from(dims.gy),
            forward,
        );
        let cz = axis_input(
            i32::cast_from(cell % dims.oz),
            kz,
            i32::cast_from(dims.sz),
            i32::cast_from(dims.pz),
            i32::cast_from(dims.dz),
            i32::cast_from(dims.gz),
            forward,
        );
        let on_grid = b >= 0
            && b < i32::cast_from(dims.batch)
            && cx >= 0
            && cx < i32::cast_from(dims.gx)
            && cy >= 0
            && cy < i32::cast_from(dims.gy)
            && cz >= 0
            && cz < i32::cast_from(dims.gz);
        let mut row = I::cast_from(dims.n_in);
        if on_grid {
            let lin = ((usize::cast_from(b) * dims.gx + usize::cast_from(cx)) * dims.gy
                + usize::cast_from(cy))
                * dims.gz
                + usize::cast_from(cz);
            row = grid[lin];
        }
        table[ABSOLUTE_POS] = row;
    }
}

/// An uninitialised `[rows, channels]` output in `like`'s dtype on its device, and the launch
/// grid of one unit per output value (`None` for an output without values: nothing to launch).
fn rows_output<R: CubeRuntime>(
    like: &CubeTensor<R>,
    rows: usize,
    channels: usize,
) -> (CubeTensor<R>, Option<(CubeCount, CubeDim)>) {
    let output = empty_device_dtype(
        like.client.clone(),
        like.device.clone(),
        Shape::new([rows, channels]),
        like.dtype,
    );
    let units = rows * channels;
    if units == 0 {
        return (output, None);
    }
    let cube_dim = CubeDim::new(&like.client, units);
    let cube_count = calculate_cube_count_elemwise(&like.client, units, cube_dim);
    (output, Some((cube_count, cube_dim)))
}

/// Launches [`segment_sum_kernel`] on raw cubecl tensors.
///
/// # Shapes
/// - values: `[H, C]`, order: `[H]`, offsets: `[n_out + 1]` -> `[n_out, C]`
pub fn segment_sum<R: CubeRuntime>(
    values: CubeTensor<R>,
    order: CubeTensor<R>,
    offsets: CubeTensor<R>,
    n_out: usize,
) -> CubeTensor<R> {
    let values = into_contiguous(values);
    let order = into_contiguous(order);
    let offsets = into_contiguous(offsets);
    let channels = values.meta.shape()[1];
    let (output, grid) = rows_output(&values, n_out, channels);
    let Some((cube_count, cube_dim)) = grid else {
        return output;
    };
    let client = values.client.clone();
    let address_type = address_type_of(&[&values, &order, &offsets, &output]);
    let dtypes = [values.dtype.into(), order.dtype.into()];
    // SAFETY: every index is in range: `RowPlan` checks `dest < n_out`, so `order` holds input
    // rows `< H` and `offsets` is non-decreasing up to `H`; the output position is bounds-checked.
    unsafe {
        segment_sum_kernel::launch_unchecked(
            &client,
            cube_count,
            cube_dim,
            address_type,
            values.into_tensor_arg(),
            order.into_tensor_arg(),
            offsets.into_tensor_arg(),
            output.clone().into_tensor_arg(),
            channels,
            dtypes,
        )
    };
    output
}

/// Launches [`kernel::pad_rows_kernel`] on a raw cubecl tensor: `x` with zero rows appended up
/// to `rows` rows, in one kernel (burn's `cat` with a zero block is a fill and two copies).
///
/// # Shapes
/// - x: `[n, C]` (`0 < n <= rows`) -> `[rows, C]`
pub fn pad_rows<R: CubeRuntime>(x: CubeTensor<R>, rows: usize) -> CubeTensor<R> {
    let x = into_contiguous(x);
    let channels = x.meta.shape()[1];
    let (output, grid) = rows_output(&x, rows, channels);
    let Some((cube_count, cube_dim)) = grid else {
        return output;
    };
    let client = x.client.clone();
    let address_type = address_type_of(&[&x, &output]);
    let dtype = x.dtype.into();
    // SAFETY: the output position is bounds-checked against the output and read from `x` only
    // below `x`'s length; `x` is contiguous, so its first values are its rows in order.
    unsafe {
        kernel::pad_rows_kernel::launch_unchecked(
            &client,
            cube_count,
            cube_dim,
            address_type,
            x.into_tensor_arg(),
            output.clone().into_tensor_arg(),
            dtype,
        )
    };
    output
}

/// Marks the runtime and element types an op is for, without holding any.
type TypesOf<R, F, I, BT> = PhantomData<fn() -> (R, F, I, BT)>;

/// What a [`register_cube_op`] op runs: the raw cubecl tensors of its inputs, in order (float,
/// int and bool alike), to its outputs, in order.
pub type CubeLauncher<R> = Arc<dyn Fn(Vec<CubeTensor<R>>) -> Vec<CubeTensor<R>> + Send + Sync>;

/// A fusion custom op running a [`CubeLauncher`] on the raw cubecl tensors of its inputs, inside
/// the fused stream (burn's backend-extension pattern for `Fusion<CubeBackend>`).
struct CubeOp<R: CubeRuntime, F, I, BT> {
    desc: CustomOpIr,
    launch: CubeLauncher<R>,
    _backend: TypesOf<R, F, I, BT>,
}

impl<R: CubeRuntime, F, I, BT> std::fmt::Debug for CubeOp<R, F, I, BT> {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("CubeOp").field("desc", &self.desc).finish()
    }
}

impl<R, F, I, BT> Operation<FusionCubeRuntime<R>> for CubeOp<R, F, I, BT>
where
    R: CubeRuntime,
    F: FloatElement,
    I: IntElement,
    BT: BoolElement,
{
    fn execute(
        &self,
        handles: &mut HandleContainer<<FusionCubeRuntime<R> as FusionRuntime>::FusionHandle>,
    ) {
        type Raw<R, F, I, BT> = CubeBackend<R, F, I, BT>;
        // A cubecl tensor is the same handle whatever its kind (its dtype travels with it).
        let inputs = self
            .desc
            .inputs
            .iter()
            .map(|t| handles.get_float_tensor::<Raw<R, F, I, BT>>(t))
            .collect();
        let results = (self.launch)(inputs);
        assert_eq!(
            results.len(),
            self.desc.outputs.len(),
            "{}: the launcher returned {} tensors for {} outputs",
            self.desc.id,
            results.len(),
            self.desc.outputs.len()
        );
        for (out, result) in self.desc.outputs.iter().zip(results) {
            handles.register_float_tensor::<Raw<R, F, I, BT>>(&out.id, result);
        }
    }
}

/// Registers a fusion custom op named `name` that runs `launch` on `inputs` and yields one tensor
/// per `outputs` entry (its shape and dtype), on the inputs' fusion streams. How the sparse
/// library's kernels, and those of crates above it (the model's DCA sampling), enter a fused
/// cubecl backend.
pub fn register_cube_op<R, F, I, BT>(
    name: &'static str,
    inputs: Vec<FusionTensor<FusionCubeRuntime<R>>>,
    outputs: &[(Shape, DType)],
    launch: CubeLauncher<R>,
) -> Vec<FusionTensor<FusionCubeRuntime<R>>>
where
    R: CubeRuntime,
    F: FloatElement,
    I: IntElement,
    BT: BoolElement,
{
    let client = inputs
        .first()
        .expect("a cube op has at least one input")
        .client
        .clone();
    let streams = OperationStreams::with_inputs(inputs.iter());
    let outs: Vec<TensorIr> = outputs
        .iter()
        .map(|(shape, dtype)| TensorIr::uninit(client.create_empty_handle(), shape.clone(), *dtype))
        .collect();
    let irs: Vec<TensorIr> = inputs.into_iter().map(|t| t.into_ir()).collect();
    let desc = CustomOpIr::new(name, &irs, &outs);
    client.register(
        streams,
        OperationIr::Custom(desc.clone()),
        CubeOp::<R, F, I, BT> {
            desc,
            launch,
            _backend: PhantomData,
        },
    )
}

/// [`register_cube_op`] with one output of `shape` in the first input's dtype.
pub fn register_one<R, F, I, BT>(
    name: &'static str,
    inputs: Vec<FusionTensor<FusionCubeRuntime<R>>>,
    shape: Shape,
    launch: impl Fn(Vec<CubeTensor<R>>) -> CubeTensor<R> + Send + Sync + 'static,
) -> FusionTensor<FusionCubeRuntime<R>>
where
    R: CubeRuntime,
    F: FloatElement,
    I: IntElement,
    BT: BoolElement,
{
    let dtype = inputs
        .first()
        .expect("a cube op has at least one input")
        .dtype;
    register_cube_op::<R, F, I, BT>(
        name,
        inputs,
        &[(shape, dtype)],
        Arc::new(move |t| vec![launch(t)]),
    )
    .pop()
    .expect("one output")
}

/// The `N` inputs a launcher was registered with.
pub fn inputs_of<R: CubeRuntime, const N: usize>(t: Vec<CubeTensor<R>>) -> [CubeTensor<R>; N] {
    let n = t.len();
    t.try_into()
        .unwrap_or_else(|_| panic!("a cube op registered with {N} inputs got {n}"))
}

/// Row scatter-add ([`crate::rows`]) on a fused cubecl backend, as a [`segment_sum`] over the
/// plan's grouped rows.
pub fn fusion_scatter_add_rows<R, F, I, BT>(
    values: FloatTensor<Fusion<CubeBackend<R, F, I, BT>>>,
    plan: &RowPlan,
) -> FloatTensor<Fusion<CubeBackend<R, F, I, BT>>>
where
    R: CubeRuntime,
    F: FloatElement,
    I: IntElement,
    BT: BoolElement,
{
    type Fused<R, F, I, BT> = Fusion<CubeBackend<R, F, I, BT>>;
    let values =
        BurnTensor::<Fused<R, F, I, BT>, 2>::from_primitive(TensorPrimitive::Float(values));
    let device = values.device();
    let order = index_tensor::<Fused<R, F, I, BT>>(plan.order(), &device).into_primitive();
    let offsets = index_tensor::<Fused<R, F, I, BT>>(plan.offsets(), &device).into_primitive();
    let values = values.into_primitive().tensor();
    let shape = Shape::new([plan.n_out(), values.shape[1]]);
    let n_out = plan.n_out();
    register_one::<R, F, I, BT>(
        "occ_sparse::segment_sum",
        vec![values, order, offsets],
        shape,
        move |t| {
            let [values, order, offsets] = inputs_of(t);
            segment_sum(values, order, offsets, n_out)
        },
    )
}

/// Row padding ([`crate::pad_rows`]) on a fused cubecl backend: one [`pad_rows`] kernel. An
/// input without rows takes the portable path (a kernel would bind an empty buffer).
pub fn fusion_pad_rows<R, F, I, BT>(
    x: FloatTensor<Fusion<CubeBackend<R, F, I, BT>>>,
    rows: usize,
) -> FloatTensor<Fusion<CubeBackend<R, F, I, BT>>>
where
    R: CubeRuntime,
    F: FloatElement,
    I: IntElement,
    BT: BoolElement,
{
    if x.shape[0] == 0 {
        return crate::rows::pad_rows_portable::<Fusion<CubeBackend<R, F, I, BT>>>(x, rows);
    }
    let shape = Shape::new([rows, x.shape[1]]);
    register_one::<R, F, I, BT>("occ_sparse::pad_rows", vec![x], shape, move |t| {
        let [x] = inputs_of(t);
        pad_rows(x, rows)
    })
}

/// Largest cube count along one dimension (WebGPU's limit; CUDA's y and z have the same one).
const MAX_CUBES_PER_DIM: usize = 65_535;

/// Most values of the weight gradient's partial sums ([`sparse_conv_weight_grad_fetch`]).
const MAX_PARTIAL_ELEMS: usize = 1 << 22;

/// Address type wide enough for every tensor of a launch.
pub fn address_type_of<R: CubeRuntime>(tensors: &[&CubeTensor<R>]) -> cubecl::prelude::AddressType {
    tensors
        .iter()
        .map(|t| t.required_address_type())
        .max()
        .unwrap_or_default()
}

/// Launches [`kernel::sparse_conv_kernel`] on raw cubecl tensors: the sparse convolution of `x`
/// over a kernel map's gather table (input row of each output and offset, `n_in` where absent).
///
/// # Shapes
/// - x: `[n_in, C_in]`, table: `[n_out · K]`, weight: `[K · C_in, C_out]` -> `[n_out, C_out]`
pub fn sparse_conv_fetch<R: CubeRuntime>(
    x: CubeTensor<R>,
    table: CubeTensor<R>,
    weight: CubeTensor<R>,
    kv: usize,
) -> CubeTensor<R> {
    let x = into_contiguous(x);
    let table = into_contiguous(table);
    let weight = into_contiguous(weight);
    let [n_in, cin] = [x.meta.shape()[0], x.meta.shape()[1]];
    let cout = weight.meta.shape()[1];
    let n_out = table.meta.shape()[0] / kv.max(1);
    let output = empty_device_dtype(
        x.client.clone(),
        x.device.clone(),
        Shape::new([n_out, cout]),
        x.dtype,
    );
    if n_out == 0 || cout == 0 {
        return output;
    }
    let tile = kernel::TILE;
    let row_tiles = n_out.div_ceil(kernel::FWD_ROWS);
    let count_x = row_tiles.min(MAX_CUBES_PER_DIM);
    let count_z = row_tiles.div_ceil(count_x);
    let cube_count = CubeCount::Static(
        count_x as u32,
        cout.div_ceil(kernel::COLS) as u32,
        count_z as u32,
    );
    let client = x.client.clone();
    let address_type = address_type_of(&[&x, &table, &weight, &output]);
    let dtypes = [x.dtype.into(), table.dtype.into()];
    // SAFETY: every read is guarded: table entries are read for rows `< n_out` only and are
    // either `n_in` (absent, never dereferenced) or an input row `< n_in` (the map's invariant);
    // weight reads are bounded by `k < K`, `i < C_in`, `c < C_out`; writes by `r < n_out`.
    unsafe {
        kernel::sparse_conv_kernel::launch_unchecked(
            &client,
            cube_count,
            CubeDim::new_2d(tile as u32, tile as u32),
            address_type,
            x.into_tensor_arg(),
            table.into_tensor_arg(),
            weight.into_tensor_arg(),
            output.clone().into_tensor_arg(),
            n_in,
            n_out,
            kv,
            cin,
            cout,
            dtypes,
        )
    };
    output
}

/// Launches [`kernel::sparse_conv_weight_grad_kernel`] and [`kernel::sum_partials_kernel`]: the
/// weight gradient of [`sparse_conv_fetch`] as a `[K · C_in, C_out]` matrix. The rows are cut
/// into a number of ranges fixed by the layer's shape (at most 64, and at most 2^22 partial
/// values), so that the compiled kernels and the summation order do not depend on the voxel
/// count.
///
/// # Shapes
/// - x: `[n_in, C_in]`, dy: `[n_out, C_out]`, table: `[n_out · K]` -> `[K · C_in, C_out]`
pub fn sparse_conv_weight_grad_fetch<R: CubeRuntime>(
    x: CubeTensor<R>,
    dy: CubeTensor<R>,
    table: CubeTensor<R>,
    kv: usize,
) -> CubeTensor<R> {
    let x = into_contiguous(x);
    let dy = into_contiguous(dy);
    let table = into_contiguous(table);
    let [n_in, cin] = [x.meta.shape()[0], x.meta.shape()[1]];
    let [n_out, cout] = [dy.meta.shape()[0], dy.meta.shape()[1]];
    let len = kv * cin * cout;
    let client = x.client.clone();
    let output = empty_device_dtype(
        client.clone(),
        x.device.clone(),
        Shape::new([kv * cin, cout]),
        x.dtype,
    );
    if len == 0 {
        return output;
    }
    let tile = kernel::TILE;
    let splits = (MAX_PARTIAL_ELEMS / len).clamp(1, 64);
    let rows_per_split = n_out.div_ceil(splits).div_ceil(tile).max(1) * tile;
    let partial = empty_device_dtype(
        client.clone(),
        x.device.clone(),
        Shape::new([splits, kv * cin, cout]),
        x.dtype,
    );
    let tiles = kv * cin.div_ceil(kernel::COLS) * cout.div_ceil(kernel::COLS);
    let address_type = address_type_of(&[&x, &dy, &table, &partial]);
    let dtypes = [x.dtype.into(), table.dtype.into()];
    let f_dtype = x.dtype.into();
    // SAFETY: table entries are read for rows `< n_out` only, and are `n_in` (never
    // dereferenced) or an input row `< n_in`; dy is read for rows with a present neighbour; every
    // partial value `(split, k · C_in + i, c)` is written once, `i < C_in`, `c < C_out` (ranges
    // past `n_out` write zeros).
    unsafe {
        kernel::sparse_conv_weight_grad_kernel::launch_unchecked(
            &client,
            CubeCount::Static(tiles as u32, splits as u32, 1),
            CubeDim::new_2d(tile as u32, tile as u32),
            address_type,
            x.into_tensor_arg(),
            dy.into_tensor_arg(),
            table.into_tensor_arg(),
            partial.clone().into_tensor_arg(),
            n_in,
            n_out,
            kv,
            cin,
            cout,
            rows_per_split,
            dtypes,
        )
    };
    let cube_dim = CubeDim::new(&client, len);
    let cube_count = calculate_cube_count_elemwise(&client, len, cube_dim);
    let address_type = address_type_of(&[&partial, &output]);
    // SAFETY: `partial` holds `splits · len` values; the output position is bounds-checked.
    unsafe {
        kernel::sum_partials_kernel::launch_unchecked(
            &client,
            cube_count,
            cube_dim,
            address_type,
            partial.into_tensor_arg(),
            output.clone().into_tensor_arg(),
            splits,
            f_dtype,
        )
    };
    output
}

crate::env_switch! {
    /// How the cubecl backends compute a sparse convolution whose map has a gather table.
    pub enum CubeConv: "SPARSEOCC_CUBE_CONV" {
        /// `fetch` (the default): the `#[cube]` kernels of this module ([`sparse_conv_fetch`],
        /// [`sparse_conv_weight_grad_fetch`]): neighbours read on demand, absent ones skipped
        /// by tile.
        Fetch = "fetch",
        /// `gather-gemm`: the portable burn-op path ([`crate::backend::conv_forward_portable`]):
        /// the `[rows, K·C_in]` block gathered into a buffer, then cubecl's matrix product
        /// (tensor cores where there are).
        GatherGemm = "gather-gemm",
    }
}

/// Declares a switch of the cubecl paths that the environment chooses once: an enum whose first
/// variant is the default, with `ENV` (the variable), `current()` (the process's choice, read by
/// [`env_choice`]) and `as_str()` (the name the variable takes).
#[macro_export]
macro_rules! env_switch {
    (
        $(#[$meta:meta])*
        $vis:vis enum $name:ident: $env:literal {
            $($(#[$vmeta:meta])* $variant:ident = $text:literal),+ $(,)?
        }
    ) => {
        $(#[$meta])*
        #[derive(Clone, Copy, Debug, PartialEq, Eq)]
        $vis enum $name {
            $($(#[$vmeta])* $variant),+
        }

        impl $name {
            /// The environment variable that chooses (the first variant when unset or empty).
            pub const ENV: &'static str = $env;

            /// The process's choice, read from `ENV` once; an unknown value is reported on
            /// standard error and the default kept.
            pub fn current() -> Self {
                static CHOICE: std::sync::OnceLock<$name> = std::sync::OnceLock::new();
                *CHOICE.get_or_init(|| {
                    $crate::cube::env_choice(Self::ENV, &[$(($text, Self::$variant)),+])
                })
            }

            /// Its name, as `ENV` takes it.
            pub fn as_str(self) -> &'static str {
                match self {
                    $(Self::$variant => $text),+
                }
            }
        }
    };
}

/// The value of environment variable `env` among `choices` (name, value); the first choice when
/// it is unset or empty. An unknown value is reported on standard error and the first choice kept.
/// How the cubecl paths' switches (`SPARSEOCC_CUBE_*`) read the environment.
pub fn env_choice<T: Copy>(env: &str, choices: &[(&'static str, T)]) -> T {
    let (default_name, default) = choices[0];
    match std::env::var(env) {
        Err(_) => default,
        Ok(v) if v.is_empty() => default,
        Ok(v) => choices
            .iter()
            .find(|(name, _)| *name == v)
            .map(|&(_, c)| c)
            .unwrap_or_else(|| {
                let names: Vec<_> = choices.iter().map(|(n, _)| format!("`{n}`")).collect();
                eprintln!(
                    "warning: {env}={v:?} is not one of {}; using `{default_name}`",
                    names.join(", ")
                );
                default
            }),
    }
}

crate::env_switch! {
    /// Where the cubecl backends build the gather tables of their kernel maps.
    pub enum CubeMaps: "SPARSEOCC_CUBE_MAPS" {
        /// `device` (the default): on the device, from the maps' sites (`build_gather_table`);
        /// the host computes only the output sites of strided and transposed convolutions, and
        /// builds no pairs.
        Device = "device",
        /// `host`: on the host ([`crate::kernel_map::conv_map`]), uploaded once per map.
        Host = "host",
    }
}

/// Most cells of the dense grid `build_gather_table` indexes the input sites with (1 GiB of
/// `i32`); a map over a larger grid gets its table from the host.
pub const MAX_DEVICE_GRID: usize = 1 << 28;

/// Cells of a side's grid (`batch · X · Y · Z`).
fn grid_cells(sites: &Sites) -> Option<usize> {
    sites
        .shape
        .iter()
        .try_fold(sites.batch, |acc, &d| acc.checked_mul(d))
}

/// What [`build_gather_table`] needs of a map besides its sites: host values only, so that the
/// device op that builds the table holds neither the coordinate lists nor the sites' device copies
/// (a device tensor dropped inside a device op would re-enter the device's queue).
#[derive(Clone, Copy, Debug)]
struct TablePlan {
    rule: MapRule,
    geometry: ConvGeometry,
    n_in: usize,
    n_out: usize,
    in_shape: [usize; 3],
    out_shape: [usize; 3],
    batch: usize,
    /// Cells of the dense grid of the input sites.
    cells: usize,
}

impl TablePlan {
    /// The plan of a map, if a device can build its table: both sides non-empty, both grids within
    /// [`MAX_DEVICE_GRID`] cells (so linear indices fit the int type).
    fn of(source: &MapSource) -> Option<Self> {
        let cells = grid_cells(&source.inputs)?;
        let nonempty = !source.inputs.coords.is_empty() && !source.outputs.coords.is_empty();
        let fits = cells <= MAX_DEVICE_GRID && grid_cells(&source.outputs)? <= MAX_DEVICE_GRID;
        (nonempty && fits).then_some(Self {
            rule: source.rule,
            geometry: source.geometry,
            n_in: source.inputs.coords.len(),
            n_out: source.outputs.coords.len(),
            in_shape: source.inputs.shape,
            out_shape: source.outputs.shape,
            batch: source.inputs.batch,
            cells,
        })
    }
}

/// Builds a kernel map's gather table on the device from its sites (crate-private: the cell
/// indices must come from a [`MapSource`], whose sites lie on their grids, and `plan` from the
/// same source): the input sites' rows are written into a dense grid of their cells (spconv 1.x's
/// dense index; a bounded voxel grid needs no hash), then every (output row, offset) reads the
/// cell its rule reaches. Integer work, no atomics: the table equals [`KernelMap::gather_table`]
/// entry for entry.
///
/// # Shapes
/// - inputs: `[n_in]`, outputs: `[n_out]` (each site's linear index in its grid, the int dtype)
///   -> `[n_out · K]`
fn build_gather_table<R: CubeRuntime>(
    inputs: CubeTensor<R>,
    outputs: CubeTensor<R>,
    plan: &TablePlan,
) -> CubeTensor<R> {
    let inputs = into_contiguous(inputs);
    let outputs = into_contiguous(outputs);
    let g = &plan.geometry;
    let (n_in, n_out, kv, cells) = (plan.n_in, plan.n_out, g.volume(), plan.cells);
    let client = inputs.client.clone();
    let dtype = inputs.dtype;
    let grid = full_device_dtype(
        client.clone(),
        Shape::new([cells]),
        inputs.device.clone(),
        InputScalar::new(n_in, dtype),
        dtype,
    );
    let table = empty_device_dtype(
        client.clone(),
        inputs.device.clone(),
        Shape::new([n_out * kv]),
        dtype,
    );
    let [gx, gy, gz] = plan.in_shape;
    let [ox, oy, oz] = plan.out_shape;
    let dims = || {
        kernel::MapDimsLaunch::new(
            g.kernel[1],
            g.kernel[2],
            kv,
            g.stride[0],
            g.stride[1],
            g.stride[2],
            g.padding[0],
            g.padding[1],
            g.padding[2],
            g.dilation[0],
            g.dilation[1],
            g.dilation[2],
            gx,
            gy,
            gz,
            plan.batch,
            ox,
            oy,
            oz,
            n_in,
        )
    };
    let address_type = address_type_of(&[&inputs, &outputs, &grid, &table]);
    let dim = CubeDim::new(&client, n_in);
    let count = calculate_cube_count_elemwise(&client, n_in, dim);
    // SAFETY: the sites are valid for their grid (a `CoordSet` checks them), so every cell index
    // is below `cells`; the unit count bounds the rows read.
    unsafe {
        kernel::site_grid_kernel::launch_unchecked(
            &client,
            count,
            dim,
            address_type,
            inputs.into_tensor_arg(),
            grid.clone().into_tensor_arg(),
            dims(),
            dtype.into(),
        )
    };
    let units = n_out * kv;
    let dim = CubeDim::new(&client, units);
    let count = calculate_cube_count_elemwise(&client, units, dim);
    // SAFETY: a cell is read only when every coordinate lies on the grid; the table position is
    // bounds-checked.
    unsafe {
        kernel::gather_table_kernel::launch_unchecked(
            &client,
            count,
            dim,
            address_type,
            outputs.into_tensor_arg(),
            grid.into_tensor_arg(),
            table.clone().into_tensor_arg(),
            dims(),
            plan.rule == MapRule::Forward,
            dtype.into(),
        )
    };
    table
}

/// The sites of one side of a map as an int tensor of their linear indices `[n]` on `device`
/// (4 bytes a site to upload), once per coordinate set and device ([`Sites::device_table`]): the
/// maps built on one set share the upload.
fn sites_tensor<B: Backend>(sites: &Sites, device: &B::Device) -> BurnTensor<B, 1, Int>
where
    B::Device: Send + Sync,
{
    let (_, t) = sites.device_table::<(B::Device, BurnTensor<B, 1, Int>)>(
        |(d, _)| d == device,
        || {
            let [sx, sy, sz] = sites.shape;
            // Valid sites lie on their grid, whose cells fit in `u32` (`TablePlan::of`).
            let cells: Vec<u32> = sites
                .coords
                .iter()
                .map(|c| {
                    (((c[0] as usize * sx + c[1] as usize) * sy + c[2] as usize) * sz
                        + c[3] as usize) as u32
                })
                .collect();
            (device.clone(), index_tensor::<B>(&cells, device))
        },
    );
    t
}

/// The map's gather table on `device` as an int tensor, once per map and device
/// ([`KernelMap::device_table`]): built there ([`build_gather_table`]) for a deferred map whose
/// host pairs do not exist, else the host table uploaded. `None` when the map has no gather table.
fn device_gather_table<R, F, I, BT>(
    map: &KernelMap,
    device: &burn::tensor::Device<Fusion<CubeBackend<R, F, I, BT>>>,
) -> Option<FusionTensor<FusionCubeRuntime<R>>>
where
    R: CubeRuntime,
    F: FloatElement,
    I: IntElement,
    BT: BoolElement,
{
    type Fused<R, F, I, BT> = Fusion<CubeBackend<R, F, I, BT>>;
    let on_device = map
        .source()
        .filter(|_| !map.has_host_pairs())
        .and_then(|s| Some((s, TablePlan::of(s)?)));
    if on_device.is_none() && map.gather_table().is_none() {
        return None;
    }
    let (_, table) = map.device_table::<(_, BurnTensor<Fused<R, F, I, BT>, 1, Int>)>(
        |(d, _)| d == device,
        || {
            let table = match on_device {
                Some((source, plan)) => {
                    let inputs = sites_tensor::<Fused<R, F, I, BT>>(&source.inputs, device);
                    let outputs = sites_tensor::<Fused<R, F, I, BT>>(&source.outputs, device);
                    let shape = Shape::new([map.n_out() * map.kernel_volume()]);
                    // The op keeps the plan only (host values; see `TablePlan`).
                    let t = register_one::<R, F, I, BT>(
                        "occ_sparse::build_gather_table",
                        vec![inputs.into_primitive(), outputs.into_primitive()],
                        shape,
                        move |t| {
                            let [inputs, outputs] = inputs_of(t);
                            build_gather_table(inputs, outputs, &plan)
                        },
                    );
                    BurnTensor::from_primitive(t)
                }
                None => index_tensor::<Fused<R, F, I, BT>>(
                    map.gather_table().expect("checked above"),
                    device,
                ),
            };
            (device.clone(), table)
        },
    );
    Some(table.into_primitive())
}

/// [`device_gather_table`] read back to the host (what `check-backend` compares with
/// [`KernelMap::gather_table`]).
pub fn read_device_gather_table<R, F, I, BT>(
    map: &KernelMap,
    device: &burn::tensor::Device<Fusion<CubeBackend<R, F, I, BT>>>,
) -> Option<Vec<u32>>
where
    R: CubeRuntime,
    F: FloatElement,
    I: IntElement,
    BT: BoolElement,
{
    let t = device_gather_table::<R, F, I, BT>(map, device)?;
    let t = BurnTensor::<Fusion<CubeBackend<R, F, I, BT>>, 1, Int>::from_primitive(t);
    let v = t.into_data().convert::<i64>().to_vec::<i64>().ok()?;
    Some(v.into_iter().map(|x| x as u32).collect())
}

/// The pair count of a map without host pairs, from [`device_gather_table`] (its entries below
/// `n_in`), as a count to call later: the table is queued now and read back when the count is
/// called. `None` for a map with host pairs (count those) or without a gather table.
pub fn device_pair_count<R, F, I, BT>(
    map: &KernelMap,
    device: &burn::tensor::Device<Fusion<CubeBackend<R, F, I, BT>>>,
) -> Option<Box<dyn FnOnce() -> usize>>
where
    R: CubeRuntime,
    F: FloatElement,
    I: IntElement,
    BT: BoolElement,
{
    if map.has_host_pairs() {
        return None;
    }
    let t = device_gather_table::<R, F, I, BT>(map, device)?;
    let n_in = map.n_in() as i64;
    Some(Box::new(move || {
        let t = BurnTensor::<Fusion<CubeBackend<R, F, I, BT>>, 1, Int>::from_primitive(t);
        // A failed read shows again at the next read of a result; count nothing here.
        t.into_data()
            .convert::<i64>()
            .to_vec::<i64>()
            .map_or(0, |v| v.into_iter().filter(|&i| i < n_in).count())
    }))
}

/// Sparse convolution on a fused cubecl backend with [`sparse_conv_fetch`]; `Err` with the
/// inputs when the map has no gather table or the process chose [`CubeConv::GatherGemm`].
///
/// # Shapes
/// - x: `[map.n_in(), C_in]`, w: `[D0, K, D2]` -> `[map.n_out(), C_out]`
#[allow(clippy::type_complexity)]
pub fn fusion_sparse_conv<R, F, I, BT>(
    x: FloatTensor<Fusion<CubeBackend<R, F, I, BT>>>,
    w: FloatTensor<Fusion<CubeBackend<R, F, I, BT>>>,
    map: &KernelMap,
    transposed: bool,
) -> Result<
    FloatTensor<Fusion<CubeBackend<R, F, I, BT>>>,
    (
        FloatTensor<Fusion<CubeBackend<R, F, I, BT>>>,
        FloatTensor<Fusion<CubeBackend<R, F, I, BT>>>,
    ),
>
where
    R: CubeRuntime,
    F: FloatElement,
    I: IntElement,
    BT: BoolElement,
{
    type Fused<R, F, I, BT> = Fusion<CubeBackend<R, F, I, BT>>;
    if CubeConv::current() != CubeConv::Fetch {
        return Err((x, w));
    }
    let w = BurnTensor::<Fused<R, F, I, BT>, 3>::from_primitive(TensorPrimitive::Float(w));
    let device = w.device();
    let Some(table) = device_gather_table::<R, F, I, BT>(map, &device) else {
        return Err((x, w.into_primitive().tensor()));
    };
    let wm = weight_matrix(w, transposed).into_primitive().tensor();
    let shape = Shape::new([map.n_out(), wm.shape[1]]);
    let kv = map.kernel_volume();
    Ok(register_one::<R, F, I, BT>(
        "occ_sparse::sparse_conv_fetch",
        vec![x, wm, table],
        shape,
        move |t| {
            let [x, w, table] = inputs_of(t);
            sparse_conv_fetch(x, table, w, kv)
        },
    ))
}

/// Weight gradient of [`fusion_sparse_conv`] with [`sparse_conv_weight_grad_fetch`]; `Err` with
/// the inputs in the same cases.
///
/// # Shapes
/// - x: `[n_in, C_in]`, dy: `[n_out, C_out]` -> `[D0, K, D2]`
#[allow(clippy::type_complexity)]
pub fn fusion_sparse_conv_weight_grad<R, F, I, BT>(
    x: FloatTensor<Fusion<CubeBackend<R, F, I, BT>>>,
    dy: FloatTensor<Fusion<CubeBackend<R, F, I, BT>>>,
    map: &KernelMap,
    wshape: [usize; 3],
    transposed: bool,
) -> Result<
    FloatTensor<Fusion<CubeBackend<R, F, I, BT>>>,
    (
        FloatTensor<Fusion<CubeBackend<R, F, I, BT>>>,
        FloatTensor<Fusion<CubeBackend<R, F, I, BT>>>,
    ),
>
where
    R: CubeRuntime,
    F: FloatElement,
    I: IntElement,
    BT: BoolElement,
{
    type Fused<R, F, I, BT> = Fusion<CubeBackend<R, F, I, BT>>;
    if CubeConv::current() != CubeConv::Fetch {
        return Err((x, dy));
    }
    let x = BurnTensor::<Fused<R, F, I, BT>, 2>::from_primitive(TensorPrimitive::Float(x));
    let device = x.device();
    let x = x.into_primitive().tensor();
    let Some(table) = device_gather_table::<R, F, I, BT>(map, &device) else {
        return Err((x, dy));
    };
    let kv = map.kernel_volume();
    let (cin, cout) = (x.shape[1], dy.shape[1]);
    let dw = register_one::<R, F, I, BT>(
        "occ_sparse::sparse_conv_weight_grad_fetch",
        vec![x, dy, table],
        Shape::new([kv * cin, cout]),
        move |t| {
            let [x, dy, table] = inputs_of(t);
            sparse_conv_weight_grad_fetch(x, dy, table, kv)
        },
    );
    let dw = BurnTensor::<Fused<R, F, I, BT>, 2>::from_primitive(TensorPrimitive::Float(dw));
    Ok(weight_from_matrix(dw, wshape, transposed)
        .into_primitive()
        .tensor())
}

/// This file's text, for `check-cuda-source` to find every launchable kernel declared here in
/// [`cuda_source_kernels`] (`occ_sparse::cuda_source::launchable_kernels`).
#[cfg(feature = "cuda-source")]
pub const KERNEL_SOURCE: &str = include_str!("cube.rs");

/// Every configuration of this file's kernels that a CUDA launch can compile, for
/// `sparseocc check-cuda-source` (crate::cuda_source): each kernel with the element types
/// `float` / `int` (the backend's), both address types (`address_type_of` picks one by buffer
/// length), every flag value and the cube shapes its launcher uses (`CubeDim::new` for the
/// one-unit-per-value kernels, the `TILE x TILE` cubes of the convolution kernels).
#[cfg(feature = "cuda-source")]
pub fn cuda_source_kernels(
    client: &cubecl::prelude::ComputeClient<crate::cuda_source::OfflineCuda>,
    float: cubecl::ir::StorageType,
    int: cubecl::ir::StorageType,
) -> Vec<Box<dyn cubecl::prelude::CubeKernel>> {
    use crate::cuda_source::{elementwise_cube_dims, launch_settings, OfflineCuda as R};
    use cubecl::prelude::{CubeKernel, TensorCompilationArg};
    use kernel::*;
    let t = || TensorCompilationArg { inplace: None };
    let map = || MapDimsCompilationArg {
        ky: (),
        kz: (),
        kv: (),
        sx: (),
        sy: (),
        sz: (),
        px: (),
        py: (),
        pz: (),
        dx: (),
        dy: (),
        dz: (),
        gx: (),
        gy: (),
        gz: (),
        batch: (),
        ox: (),
        oy: (),
        oz: (),
        n_in: (),
    };
    let c = || client.clone();
    let ft = [float, int];
    let mut k: Vec<Box<dyn CubeKernel>> = Vec::new();
    for s in launch_settings(&elementwise_cube_dims(client)) {
        let s = || s.clone();
        k.push(Box::new(segment_sum_kernel::SegmentSumKernel::<R>::new(
            s(),
            c(),
            t(),
            t(),
            t(),
            t(),
            (),
            ft,
        )));
        k.push(Box::new(pad_rows_kernel::PadRowsKernel::<R>::new(
            s(),
            c(),
            t(),
            t(),
            float,
        )));
        k.push(Box::new(sum_partials_kernel::SumPartialsKernel::<R>::new(
            s(),
            c(),
            t(),
            t(),
            (),
            float,
        )));
        k.push(Box::new(site_grid_kernel::SiteGridKernel::<R>::new(
            s(),
            c(),
            t(),
            t(),
            map(),
            int,
        )));
        for forward in [false, true] {
            k.push(Box::new(gather_table_kernel::GatherTableKernel::<R>::new(
                s(),
                c(),
                t(),
                t(),
                t(),
                map(),
                forward,
                int,
            )));
        }
    }
    let tile = CubeDim::new_2d(TILE as u32, TILE as u32);
    for s in launch_settings(&[tile]) {
        let s = || s.clone();
        k.push(Box::new(sparse_conv_kernel::SparseConvKernel::<R>::new(
            s(),
            c(),
            t(),
            t(),
            t(),
            t(),
            (),
            (),
            (),
            (),
            (),
            ft,
        )));
        k.push(Box::new(
            sparse_conv_weight_grad_kernel::SparseConvWeightGradKernel::<R>::new(
                s(),
                c(),
                t(),
                t(),
                t(),
                t(),
                (),
                (),
                (),
                (),
                (),
                (),
                ft,
            ),
        ));
    }
    k
}
