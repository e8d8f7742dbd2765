#!/usr/bin/env python3
"""Share of the volume marked `.invalid`, and of the occupied / non-ground voxels that are valid, for
every SemanticKITTI-layout frame under the given dataset roots (real or `sparseocc synth` output).

usage: python3 scripts/invalid_share.py ROOT [ROOT ...]     (needs numpy)

A frame without a `.label` (real frames shipped without labels) reports the invalid share alone.
"""
import glob
import os
import sys

import numpy as np

# SemanticKITTI learning map (config/semantic-kitti.yaml); unknown raw ids are ignored (255).
LEARNING_MAP = {0: 0, 1: 255, 10: 1, 11: 2, 13: 5, 15: 3, 16: 5, 18: 4, 20: 5, 30: 6, 31: 7, 32: 8,
                40: 9, 44: 10, 48: 11, 49: 12, 50: 13, 51: 14, 52: 255, 60: 9, 70: 15, 71: 16, 72: 17,
                80: 18, 81: 19, 99: 255, 252: 1, 253: 7, 254: 6, 255: 8, 256: 5, 257: 5, 258: 4, 259: 5}
GROUND = [9, 10, 11, 12, 17]  # road, parking, sidewalk, other-ground, terrain


def main(roots):
    lut = np.full(65536, 255, np.uint8)
    for raw, cls in LEARNING_MAP.items():
        lut[raw] = cls
    shares = []
    for root in roots:
        for inv_path in sorted(glob.glob(os.path.join(root, "sequences", "*", "voxels", "*.invalid"))):
            invalid = np.unpackbits(np.fromfile(inv_path, np.uint8))
            shares.append(invalid.mean())
            line = f"{inv_path}: invalid {invalid.mean():.3f}"
            label_path = inv_path[: -len(".invalid")] + ".label"
            if os.path.exists(label_path):
                labels = lut[np.fromfile(label_path, np.uint16)]
                occupied = (labels > 0) & (labels < 255)
                non_ground = occupied & ~np.isin(labels, GROUND)
                valid = invalid == 0
                line += (f", occupied valid {(occupied & valid).sum() / max(occupied.sum(), 1):.3f}"
                         f", non-ground valid {(non_ground & valid).sum()} of {non_ground.sum()}")
            print(line)
    if shares:
        s = np.sort(np.array(shares))
        print(f"{len(s)} frames: invalid mean {s.mean():.3f}, median {np.median(s):.3f}, "
              f"10th-90th percentile {np.percentile(s, 10):.3f}-{np.percentile(s, 90):.3f}")


if __name__ == "__main__":
    if len(sys.argv) < 2:
        sys.exit(__doc__)
    main(sys.argv[1:])
