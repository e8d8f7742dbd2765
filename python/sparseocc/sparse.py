"""Sparse 3D convolution on numpy arrays, in spconv's index layout (``occ_sparse`` in Rust)."""

import numpy as _np

from . import _native

__all__ = ["conv3d"]


def conv3d(coords, feats, weight, spatial_shape, kernel, stride=1, padding=0, dilation=1,
           subm=False, transposed=False, batch_size=None):
    """One sparse convolution (cross-correlation, no bias) on the CPU.

    - ``coords``: integer ``[N, 4]`` active sites ``(batch, x, y, z)``, any order, no duplicates;
    - ``feats``: ``[N, Cin]`` features; ``weight``: ``[Cout, kx, ky, kz, Cin]`` (spconv 2.x);
    - ``spatial_shape``: the grid ``(X, Y, Z)``; ``kernel``, ``stride``, ``padding``,
      ``dilation``: an int or three;
    - ``subm=True``: submanifold (spconv ``SubMConv3d``: the output sites are the input sites);
      ``transposed=True``: spconv ``SparseConvTranspose3d``; else spconv ``SparseConv3d``;
    - ``batch_size``: default the largest batch index + 1.

    Returns ``(out_coords, out_feats)``: int32 ``[M, 4]`` sorted by ``(b, x, y, z)`` and float32
    ``[M, Cout]``. Inputs may have any memory layout (views, Fortran order, either byte order);
    they are read in logical order. C-contiguous ``float32`` features and weights are read in
    place (no copy) while the GIL is released, as numpy's own functions do: do not write them
    from another thread during the call.
    """
    c = _np.asarray(coords)
    if c.dtype.kind not in "iu":
        raise ValueError(f"coords must be an integer array, got dtype {c.dtype}")
    return _native.conv3d(
        c.astype(_np.int64, copy=False),
        _np.asarray(feats, dtype=_np.float32),
        _np.asarray(weight, dtype=_np.float32),
        spatial_shape, kernel, stride, padding, dilation, bool(subm), bool(transposed),
        batch_size,
    )
