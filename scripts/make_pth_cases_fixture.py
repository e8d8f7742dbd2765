#!/usr/bin/env python3
"""Small `torch.save` checkpoints for the occ-model `.pth` reader (crates/model/src/encoder/weights.rs).

Each file holds a few tiny tensors in one of the forms `torch.save` writes that a reader can get wrong; the
Rust test (crates/model/tests/model_f32/pth_cases.rs) loads them through `load_module` and compares every
tensor with the values listed here, in C order:
  dtypes.pth      float16, bfloat16, float64 and float32 tensors (+ an int64 counter the model does not use)
  views.pth       views of one shared storage: a channels_last conv weight, a transposed matrix, a stride-2
                  view and two views at an offset (strides and offsets must be honoured)
  protocol4.pth   torch.save(..., pickle_protocol=4) (FRAME, SHORT_BINUNICODE, STACK_GLOBAL, MEMOIZE)
  checkpoint.pth  a training checkpoint: {"meta": {numpy scalar and array, set, bytes, argparse.Namespace},
                  "state_dict": {...}, "optimizer": {"state": {0: {...}}, ...}} (objects that are not
                  tensors are skipped; the one-entry int-keyed dict is pickled with SETITEM)
  legacy.pth      the pre-1.6 (non-zip) format, which the reader rejects with a parse error
manifest.json lists, per load, the file, the options, the expected tensors and the unused file keys.

Run: /root/venv-spconv/bin/python scripts/make_pth_cases_fixture.py [out_dir]
"""

import argparse
import json
import os
import sys

import numpy as np
import torch


def grid(shift, shape=(2, 3)):
    """Distinct values exactly representable in float16 and bfloat16 (multiples of 1/8, |x| < 4)."""
    n = int(np.prod(shape))
    return (torch.arange(n, dtype=torch.float32) / 8 - 0.25 + shift).reshape(shape)


def expected(state):
    return {k: {"shape": list(v.shape), "values": v.float().contiguous().flatten().tolist()}
            for k, v in state.items() if v.is_floating_point()}


def save(out_dir, name, obj, **kw):
    path = os.path.join(out_dir, name)
    torch.save(obj, path + ".tmp", **kw)
    os.replace(path + ".tmp", path)


def main():
    out_dir = sys.argv[1] if len(sys.argv) > 1 else os.path.join(
        os.path.dirname(os.path.abspath(__file__)), "..", "crates", "model", "tests", "data", "pth_cases")
    os.makedirs(out_dir, exist_ok=True)
    loads = []

    four = {"a": grid(0).half(), "b": grid(1).bfloat16(), "c": grid(2).double(), "d": grid(3)}
    save(out_dir, "dtypes.pth", {**four, "counter": torch.tensor(7)})
    loads.append({"file": "dtypes.pth", "module": "four", "tensors": expected(four), "unused": ["counter"]})

    # One storage of 32 floats; every tensor below is a view of it.
    flat = torch.arange(32, dtype=torch.float32) / 4
    views = {
        # [2, 3, 2, 2] with channels_last strides (12, 1, 6, 3): not C-contiguous.
        "conv.weight": flat[:24].reshape(2, 2, 2, 3).permute(0, 3, 1, 2),
        # Contiguous at offset 24.
        "conv.bias": flat[24:26],
        # [4, 3] transpose of a [3, 4] block: strides (1, 4).
        "transposed": flat[:12].reshape(3, 4).t(),
        # Every other element: strides (6, 2).
        "strided": flat[::2][:6].view(2, 3),
        # Contiguous [2, 3] at offset 5.
        "offset": flat[5:11].view(2, 3),
    }
    assert not views["conv.weight"].is_contiguous()
    assert views["conv.weight"].is_contiguous(memory_format=torch.channels_last)
    assert views["transposed"].stride() == (1, 4) and views["strided"].stride() == (6, 2)
    assert all(v.untyped_storage().data_ptr() == flat.untyped_storage().data_ptr() for v in views.values())
    save(out_dir, "views.pth", views)
    loads.append({"file": "views.pth", "module": "views", "tensors": expected(views), "unused": []})

    p4 = {k: grid(i + 4) for i, k in enumerate("abcd")}
    save(out_dir, "protocol4.pth", p4, pickle_protocol=4)
    loads.append({"file": "protocol4.pth", "module": "four", "tensors": expected(p4), "unused": []})

    sd = {k: grid(i + 8) for i, k in enumerate("abcd")}
    ckpt = {
        "meta": {
            "epoch": 3,
            "best_score": np.float64(0.5),
            "classes": np.arange(3),
            "seen": {1, 2},
            "tag": b"xy",
            "args": argparse.Namespace(lr=0.1),
        },
        "state_dict": sd,
        "optimizer": {"state": {0: {"momentum_buffer": grid(12)}}, "param_groups": [{"lr": 0.1, "params": [0]}]},
    }
    save(out_dir, "checkpoint.pth", ckpt)
    loads.append({"file": "checkpoint.pth", "module": "four", "top_level_key": "state_dict",
                  "tensors": expected(sd), "unused": []})
    loads.append({"file": "checkpoint.pth", "module": "four", "key_prefix": "state_dict.",
                  "tensors": expected(sd), "unused": ["optimizer.state.0.momentum_buffer"]})

    save(out_dir, "legacy.pth", {"a": grid(0)}, _use_new_zipfile_serialization=False)
    loads.append({"file": "legacy.pth", "module": "four", "error": "Parse"})

    manifest = {"generator": "scripts/make_pth_cases_fixture.py", "torch": torch.__version__, "loads": loads}
    tmp = os.path.join(out_dir, "manifest.json.tmp")
    with open(tmp, "w") as f:
        json.dump(manifest, f, indent=1)
        f.write("\n")
    os.replace(tmp, os.path.join(out_dir, "manifest.json"))
    total = sum(os.path.getsize(os.path.join(out_dir, f)) for f in os.listdir(out_dir))
    print("total bytes", total)


if __name__ == "__main__":
    main()
