"""sparseocc: vision-based 3D semantic occupancy prediction (SparseOcc, SparseOcc++) from Python.

A thin layer over the Rust library that the ``sparseocc`` command runs:

- ``evaluate`` scores a prediction folder with the official protocol (SemanticKITTI SSC,
  Occ3D-nuScenes, nuScenes-Occupancy) and returns what ``sparseocc eval --json`` writes;
  ``confusion`` / ``report`` do the same on numpy arrays.
- ``synth`` generates synthetic driving scenes in the real datasets' layouts.
- ``read_voxels`` / ``write_voxels`` read and write SemanticKITTI ``.label`` / ``.bin`` /
  ``.invalid`` / ``.occluded`` files and Occ3D ``labels.npz``.
- ``Model`` loads a training run and predicts from a camera image or a dataset frame.
- ``sparseocc.sparse.conv3d`` is one sparse 3D convolution in spconv's index layout.

Errors from files and folders raise ``SparseOccError`` with the file and the problem in the
message; bad arguments raise ``ValueError``. Long calls release the GIL.
"""

import numpy as _np

from . import _native
from ._native import Model, SparseOccError, __version__
from . import sparse

__all__ = [
    "Model",
    "SparseOccError",
    "__version__",
    "class_names",
    "confusion",
    "evaluate",
    "read_image",
    "read_voxels",
    "report",
    "sparse",
    "synth",
    "write_voxels",
]


def _int_array(name, a):
    """``a`` as an int64 array (any integer or bool dtype, any layout); floats are refused."""
    a = _np.asarray(a)
    if a.dtype.kind not in "iub":
        raise ValueError(f"{name} must be an integer array, got dtype {a.dtype}")
    return a.astype(_np.int64, copy=False)


def evaluate(gt_root, pred_root, dataset="semantickitti", sequences=None, progress=True):
    """Scores the predictions below ``pred_root`` against the ground truth below ``gt_root``.

    ``dataset``: ``"semantickitti"``, ``"occ3d"`` or ``"nuscenes-occupancy"``; ``sequences``:
    SemanticKITTI sequence ids, Occ3D scene names or nuScenes-Occupancy scene tokens (default
    every one with labels). Returns the report as ``sparseocc eval --json`` writes it (``iou``,
    ``miou``, ``per_class``, ``confusion``, ...; fractions in [0, 1], ``None`` where undefined).
    """
    if isinstance(sequences, str):
        sequences = [s.strip() for s in sequences.split(",")]
    elif sequences is not None:
        sequences = [str(s) for s in sequences]
    return _native.evaluate(str(gt_root), str(pred_root), dataset, sequences, progress)


def confusion(pred, gt, invalid=None, *, visible=None, dataset="semantickitti"):
    """The confusion matrix ``conf[pred][gt]`` (uint64, ``[C, C]``) of one frame's class arrays.

    ``pred`` and ``gt`` are integer arrays of one shape. Ground-truth values outside the
    dataset's classes (e.g. 255) are not scored; predicted values outside them count as the
    empty class. ``invalid`` (SemanticKITTI ``.invalid``: voxels equal to 1 are left out) or
    ``visible`` (Occ3D ``mask_camera``: only nonzero voxels are scored) select voxels. Sum the
    matrices of several frames and pass the sum to ``report``.
    """
    inv = None if invalid is None else _int_array("invalid", invalid)
    vis = None if visible is None else _int_array("visible", visible)
    return _native.confusion(_int_array("pred", pred), _int_array("gt", gt), inv, vis, dataset)


def report(confusion, dataset="semantickitti", frames=1):
    """The metrics of a confusion matrix ``conf[pred][gt]``, with the keys of ``evaluate``.

    ``confusion``: non-negative integer counts ``[C, C]`` (as ``confusion`` returns them, or
    their sum over frames); floats and negative counts are refused, not rounded or wrapped.
    """
    c = _np.asarray(confusion)
    if c.dtype.kind not in "iu":
        raise ValueError(f"confusion must be an integer array of counts, got dtype {c.dtype}")
    if c.ndim != 2 or c.shape[0] != c.shape[1]:
        raise ValueError(f"confusion must be a square matrix [C, C], got shape {c.shape}")
    if c.dtype.kind == "i" and c.size and c.min() < 0:
        raise ValueError(f"confusion has a negative count ({c.min()})")
    return _native.report(c.astype(_np.uint64, copy=False), dataset, frames)


def class_names(dataset="semantickitti"):
    """Class names of a dataset's protocol, indexed by class id."""
    return _native.class_names(dataset)


def synth(out, preset="kitti-small", sequences="00:20,08:5", seed=0, image_size=None, progress=True):
    """Generates synthetic driving scenes below ``out`` (as ``sparseocc synth``).

    ``preset``: ``"kitti"``, ``"kitti-small"`` (SemanticKITTI layout) or ``"surround"`` (Occ3D,
    six cameras); ``sequences``: ``"00:40,08:10"`` or ``"10-49:4"`` (a range of sequences of 4
    frames), or a dict ``{"00": 40, "08": 10}``; ``image_size``: ``(width, height)``. Same seed,
    same files. Writes ``out/synth_summary.json`` and returns it as a dict.
    """
    if isinstance(sequences, dict):
        sequences = ",".join(f"{k}:{int(v)}" for k, v in sequences.items())
    if image_size is not None:
        image_size = (int(image_size[0]), int(image_size[1]))
    return _native.synth(str(out), preset, sequences, int(seed), image_size, progress)


def read_voxels(path, learning=False):
    """Reads a voxel file by its name.

    - ``.label`` (SemanticKITTI): raw uint16 label ids ``[X, Y, Z]``; with ``learning=True`` the
      20 learning classes (uint8, 255 = ignored).
    - ``.bin`` / ``.invalid`` / ``.occluded``: a bool array ``[X, Y, Z]``.
    - ``labels.npz`` (Occ3D): a dict of uint8 arrays ``semantics``, ``mask_lidar``, ``mask_camera``.

    The grid of a SemanticKITTI file comes from its size (256x256x32, or its 1/2 or 1/4), or from
    a ``synthetic.json`` in a folder above it.
    """
    return _native.read_voxels(str(path), learning)


def write_voxels(path, data, learning=False):
    """Writes a voxel file by its name (the folder is created; the file appears complete or not at
    all). ``data`` as ``read_voxels`` returns it: an ``[X, Y, Z]`` array of raw ids (``.label``;
    learning classes with ``learning=True``), of 0/1 (``.bin`` / ``.invalid`` / ``.occluded``), or a
    dict with ``semantics`` (0..17) and optionally the masks (default all 1) for ``labels.npz``.
    What the reader would refuse or read differently is refused: values out of range, a key other
    than the three of ``labels.npz``, and a SemanticKITTI array whose shape is not the grid the
    reader finds from its size (the file stores no shape: a transposed ``[Z, Y, X]`` array would
    be read back as ``[X, Y, Z]``).
    """
    if isinstance(data, dict):
        data = {k: _int_array(k, v) for k, v in data.items()}
    else:
        data = _int_array("data", data)
    _native.write_voxels(str(path), data, learning)


def read_image(path):
    """A PNG or JPEG camera image as ``[H, W, 3]`` uint8 RGB (the decoder the datasets use)."""
    return _native.read_image(str(path))
