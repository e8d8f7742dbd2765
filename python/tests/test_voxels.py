"""Voxel files and synthetic scenes from Python."""

import json
import os

import numpy as np
import pytest

import sparseocc


def test_synth_writes_the_dataset_and_its_summary(tmp_path, kitti_data):
    summary = json.loads((kitti_data / "synth_summary.json").read_text())
    assert summary["frames"] == 3 and summary["preset"] == "kitti-small"
    again = sparseocc.synth(tmp_path / "again", sequences={"08": 1}, seed=0, progress=False)
    assert again["frames"] == 1 and again["sequences"][0]["name"] == "08"
    # Same seed, same files.
    a = (kitti_data / "sequences/08/voxels/000000.label").read_bytes()
    b = (tmp_path / "again/sequences/08/voxels/000000.label").read_bytes()
    assert a == b
    with pytest.raises(ValueError, match="preset"):
        sparseocc.synth(tmp_path / "x", preset="mars")
    with pytest.raises(ValueError, match="sequence"):
        sparseocc.synth(tmp_path / "x", sequences="00")


def test_kitti_files_round_trip(tmp_path, kitti_data):
    d = kitti_data / "sequences" / "08" / "voxels"
    raw = sparseocc.read_voxels(d / "000000.label")
    assert raw.dtype == np.uint16 and raw.shape == (128, 128, 16)
    learning = sparseocc.read_voxels(d / "000000.label", learning=True)
    assert learning.dtype == np.uint8 and learning.max() <= 255
    for ext in ("bin", "invalid", "occluded"):
        bits = sparseocc.read_voxels(d / f"000000.{ext}")
        assert bits.dtype == np.bool_ and bits.shape == (128, 128, 16)
        out = tmp_path / "copy" / f"000000.{ext}"
        sparseocc.write_voxels(out, bits)
        assert out.read_bytes() == (d / f"000000.{ext}").read_bytes()
    out = tmp_path / "a" / "b" / "000000.label"  # folders are created
    sparseocc.write_voxels(out, raw)
    assert out.read_bytes() == (d / "000000.label").read_bytes()
    # Any layout: a Fortran-order copy writes the same file.
    sparseocc.write_voxels(out, np.asfortranarray(raw))
    assert out.read_bytes() == (d / "000000.label").read_bytes()
    # Learning classes written as a submission read back as the same classes (255 -> 0 "empty"
    # has no raw id of its own, so compare where labelled).
    sparseocc.write_voxels(out, learning, learning=True)
    back = sparseocc.read_voxels(out, learning=True)
    assert (back[learning != 255] == learning[learning != 255]).all()
    # Nothing but the outputs in the folders (writes are atomic: no temporary files left).
    left = sorted(p.name for p in (tmp_path / "a" / "b").iterdir())
    assert left == ["000000.label"]


def test_occ3d_round_trip_and_refusals(tmp_path):
    rng = np.random.default_rng(0)
    sem = rng.integers(0, 18, size=(10, 8, 4), dtype=np.uint8)
    p = tmp_path / "scene" / "tok" / "labels.npz"
    sparseocc.write_voxels(p, {"semantics": sem})
    back = sparseocc.read_voxels(p)
    assert (back["semantics"] == sem).all() and back["mask_camera"].all()
    with np.load(p) as z:  # numpy reads what we write
        assert (z["semantics"] == sem).all()
    bad = sem.copy()
    bad[1, 2, 3] = 18
    with pytest.raises(sparseocc.SparseOccError, match="semantics value 18"):
        sparseocc.write_voxels(tmp_path / "bad" / "labels.npz", {"semantics": bad})
    with pytest.raises(sparseocc.SparseOccError, match="mask_camera value 2"):
        sparseocc.write_voxels(
            tmp_path / "bad" / "labels.npz", {"semantics": sem, "mask_camera": np.full(sem.shape, 2)}
        )
    with pytest.raises(ValueError, match="shape"):
        sparseocc.write_voxels(
            tmp_path / "bad" / "labels.npz", {"semantics": sem, "mask_lidar": np.ones((2, 2, 2), dtype=np.uint8)}
        )
    # A misspelt mask is refused (it would have been written as all ones).
    with pytest.raises(ValueError, match="unknown key 'mask_camara'"):
        sparseocc.write_voxels(
            tmp_path / "bad" / "labels.npz", {"semantics": sem, "mask_camara": np.zeros(sem.shape, dtype=np.uint8)}
        )
    assert not (tmp_path / "bad" / "labels.npz").exists()
    assert os.listdir(tmp_path / "bad") == []


def test_bad_voxel_files_and_values(tmp_path):
    with pytest.raises(sparseocc.SparseOccError, match="matches no SemanticKITTI grid"):
        (tmp_path / "odd.label").write_bytes(b"\0" * 10)
        sparseocc.read_voxels(tmp_path / "odd.label")
    with pytest.raises(sparseocc.SparseOccError, match="no such file"):
        sparseocc.read_voxels(tmp_path / "missing.bin")
    with pytest.raises(sparseocc.SparseOccError, match="unknown voxel file"):
        sparseocc.read_voxels(tmp_path / "x.txt")
    with pytest.raises(sparseocc.SparseOccError, match="not 0/1"):
        sparseocc.write_voxels(tmp_path / "x.invalid", np.full((8, 8, 8), 3))
    with pytest.raises(ValueError, match="does not fit a uint16"):
        sparseocc.write_voxels(tmp_path / "x.label", np.full((8, 8, 8), 70000))
    with pytest.raises(ValueError, match="learning class 20"):
        sparseocc.write_voxels(tmp_path / "x.label", np.full((8, 8, 8), 20), learning=True)
    with pytest.raises(ValueError, match="3D"):
        sparseocc.write_voxels(tmp_path / "x.label", np.zeros((8, 8), dtype=np.uint16))
    with pytest.raises(ValueError, match="integer"):
        sparseocc.write_voxels(tmp_path / "x.label", np.zeros((8, 8, 8)))
    # A .label stores no shape: an array the reader would take for another grid is refused.
    with pytest.raises(sparseocc.SparseOccError, match=r"read back as \[128, 128, 16\]"):
        sparseocc.write_voxels(tmp_path / "x.label", np.zeros((16, 128, 128), dtype=np.uint16))
    with pytest.raises(sparseocc.SparseOccError, match="match no grid"):
        sparseocc.write_voxels(tmp_path / "x.bin", np.zeros((8, 8, 8), dtype=np.uint8))
    with pytest.raises(ValueError, match="a dict is for an Occ3D labels.npz"):
        sparseocc.write_voxels(tmp_path / "x.label", {"semantics": np.zeros((8, 8, 8), dtype=np.uint8)})
    assert sorted(os.listdir(tmp_path)) == ["odd.label"]
