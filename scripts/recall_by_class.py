#!/usr/bin/env python3
"""Where the predicted voxels find the objects: for the valid ground-truth voxels of one sequence, the
share predicted occupied (any class), split by class and by visibility (in the camera's view and seen
from the frame's position, in view but `.occluded`, out of view), and split by position (lateral |y|
band x forward x band, non-ground classes only).

usage: python3 scripts/recall_by_class.py DATA PRED SEQ
    DATA: a SemanticKITTI-layout root (`sparseocc synth` / `sparseocc demo` data/)
    PRED: the root holding `sequences/SEQ/predictions/*.label` (`sparseocc demo` predictions/, or the
          `--out` of `sparseocc infer`)
Grid: the `kitti-small` preset (128 x 128 x 16 voxels of 0.4 m from (0, -25.6, -2.2) m); the image
size is read from the first PNG of image_2/. Needs numpy.
"""
import glob
import os
import struct
import sys

import numpy as np

from invalid_share import GROUND, LEARNING_MAP

NAMES = ["empty", "car", "bicycle", "motorcycle", "truck", "other-vehicle", "person", "bicyclist",
         "motorcyclist", "road", "parking", "sidewalk", "other-ground", "building", "fence",
         "vegetation", "trunk", "terrain", "pole", "traffic-sign"]
DIMS, VOXEL_M, ORIGIN_M = (128, 128, 16), 0.4, np.array([0.0, -25.6, -2.2])
Y_BANDS = [0, 3, 6, 9, 13, 26]
X_BANDS = [0, 10, 20, 52]


def read_calib(path):
    cal = {}
    for line in open(path):
        if ":" in line:
            key, val = line.split(":", 1)
            cal[key.strip()] = np.array(val.split(), float)
    p2 = cal["P2"].reshape(3, 4)
    tr = np.eye(4)
    tr[:3] = cal["Tr"].reshape(3, 4)
    return p2, tr


def main(data, pred, seq):
    lut = np.full(65536, 255, np.uint8)
    for raw, cls in LEARNING_MAP.items():
        lut[raw] = cls
    sdir = os.path.join(data, "sequences", seq)
    p2, tr = read_calib(os.path.join(sdir, "calib.txt"))
    png = sorted(glob.glob(os.path.join(sdir, "image_2", "*.png")))[0]
    width, height = struct.unpack(">II", open(png, "rb").read()[16:24])
    ii, jj, kk = np.meshgrid(*[np.arange(d) for d in DIMS], indexing="ij")
    centres = np.stack([ii, jj, kk], -1).reshape(-1, 3) * VOXEL_M + ORIGIN_M + VOXEL_M / 2
    h = np.c_[centres, np.ones(len(centres))] @ tr.T @ p2.T
    with np.errstate(divide="ignore", invalid="ignore"):
        u, v = h[:, 0] / h[:, 2], h[:, 1] / h[:, 2]
    in_view = (h[:, 2] > 0.1) & (u >= 0) & (u < width) & (v >= 0) & (v < height)
    x, y = centres[:, 0], np.abs(centres[:, 1])
    by_class = np.zeros((20, 6), np.int64)
    by_pos = np.zeros((len(Y_BANDS) - 1, len(X_BANDS) - 1, 2), np.int64)
    for label_path in sorted(glob.glob(os.path.join(sdir, "voxels", "*.label"))):
        stem = os.path.basename(label_path)[: -len(".label")]
        labels = lut[np.fromfile(label_path, np.uint16)]
        invalid = np.unpackbits(np.fromfile(label_path[:-6] + ".invalid", np.uint8)).astype(bool)
        occluded = np.unpackbits(np.fromfile(label_path[:-6] + ".occluded", np.uint8)).astype(bool)
        pred_path = os.path.join(pred, "sequences", seq, "predictions", stem + ".label")
        hit = lut[np.fromfile(pred_path, np.uint16)] > 0
        for cls in range(1, 20):
            m = (labels == cls) & ~invalid
            for i, part in enumerate([m & in_view & ~occluded, m & in_view & occluded, m & ~in_view]):
                by_class[cls, 2 * i] += part.sum()
                by_class[cls, 2 * i + 1] += (part & hit).sum()
        ng = (labels > 0) & (labels < 255) & ~np.isin(labels, GROUND) & ~invalid
        for a in range(len(Y_BANDS) - 1):
            for b in range(len(X_BANDS) - 1):
                m = ng & (y >= Y_BANDS[a]) & (y < Y_BANDS[a + 1]) & (x >= X_BANDS[b]) & (x < X_BANDS[b + 1])
                by_pos[a, b] += [m.sum(), (m & hit).sum()]
    print(f"sequence {seq}, image {width}x{height}")
    print("class: voxels; share (recall) in view and seen | in view, occluded | out of view")
    for cls in range(1, 20):
        s = by_class[cls]
        n = s[0] + s[2] + s[4]
        if n == 0:
            continue
        parts = [f"{s[2 * i] / n:.2f} ({s[2 * i + 1] / max(s[2 * i], 1):.2f})" for i in range(3)]
        print(f"{NAMES[cls]:14s} {n:6d}; " + " | ".join(parts))
    print("non-ground voxels by position: voxels (recall); rows |y| in m, columns x in m")
    print("           " + "".join(f"x {X_BANDS[b]:2d}-{X_BANDS[b + 1]:2d}       " for b in range(len(X_BANDS) - 1)))
    for a in range(len(Y_BANDS) - 1):
        cells = [f"{by_pos[a, b, 0]:6d} ({by_pos[a, b, 1] / max(by_pos[a, b, 0], 1):.2f})  "
                 for b in range(len(X_BANDS) - 1)]
        print(f"|y| {Y_BANDS[a]:2d}-{Y_BANDS[a + 1]:2d}  " + "".join(cells))


if __name__ == "__main__":
    if len(sys.argv) != 4:
        sys.exit(__doc__)
    main(*sys.argv[1:])
