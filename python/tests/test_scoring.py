"""Scores from Python equal the CLI's, to the last digit, on the same folders."""

import json
import shutil

import numpy as np
import pytest

import sparseocc
from conftest import run


def perturbed(classes, seed, n_classes, p=0.3):
    """``classes`` with a share ``p`` of the voxels set to a random class (seeded)."""
    rng = np.random.default_rng(seed)
    out = classes.copy()
    flip = rng.random(out.shape) < p
    out[flip] = rng.integers(0, n_classes, size=int(flip.sum()), dtype=out.dtype)
    return out


def cli_eval(cli, gt, pred, dataset, tmp_path, sequences=None):
    js = tmp_path / f"cli_{dataset}.json"
    cmd = [cli, "eval", "--dataset", dataset, "--gt", gt, "--pred", pred, "--json", js]
    if sequences:
        cmd += ["--sequences", sequences]
    run(cmd)
    return json.loads(js.read_text())


def kitti_predictions(data, out, seqs, seed):
    """A noisy copy of every labelled frame of ``seqs`` as a submission folder (raw ids)."""
    for s in seqs:
        for lab in sorted((data / "sequences" / s / "voxels").glob("*.label")):
            classes = sparseocc.read_voxels(lab, learning=True)
            pred = perturbed(np.where(classes == 255, 0, classes), seed, 20)
            sparseocc.write_voxels(
                out / "sequences" / s / "predictions" / lab.name, pred, learning=True
            )


def test_evaluate_equals_cli_on_synthetic_kitti(tmp_path, cli, kitti_data):
    pred = tmp_path / "pred"
    kitti_predictions(kitti_data, pred, ["00", "08"], seed=1)
    got = sparseocc.evaluate(kitti_data, pred, progress=False)
    assert got == cli_eval(cli, kitti_data, pred, "semantickitti", tmp_path)
    assert got["frames"] == 3 and 0.0 < got["miou"] < 1.0
    one = sparseocc.evaluate(kitti_data, pred, sequences=[8], progress=False)
    assert one == cli_eval(cli, kitti_data, pred, "semantickitti", tmp_path, "08")
    assert one["frames"] == 1


def test_evaluate_equals_cli_with_real_kitti_masks(tmp_path, cli, realdata):
    """Ground truth made from the real scan occupancy, scored under the real ``.invalid`` masks."""
    src = realdata / "semantickitti" / "sequences"
    gt, pred = tmp_path / "gt", tmp_path / "pred"
    n = 0
    for inv in sorted(src.glob("*/voxels/*.invalid")):
        seq, stem = inv.parent.parent.name, inv.stem
        occ = sparseocc.read_voxels(inv.with_suffix(".bin"))
        classes = np.where(occ, 9, 0).astype(np.uint8)  # occupied voxels as "road"
        d = gt / "sequences" / seq / "voxels"
        sparseocc.write_voxels(d / f"{stem}.label", classes, learning=True)
        shutil.copy(inv, d / inv.name)
        sparseocc.write_voxels(
            pred / "sequences" / seq / "predictions" / f"{stem}.label",
            perturbed(classes, n, 20, p=0.1),
            learning=True,
        )
        n += 1
    assert n >= 1
    got = sparseocc.evaluate(gt, pred, progress=False)
    assert got == cli_eval(cli, gt, pred, "semantickitti", tmp_path)
    assert got["frames"] == n


def test_evaluate_equals_cli_on_real_occ3d(tmp_path, cli, realdata):
    gt, pred = tmp_path / "gt", tmp_path / "pred"
    for k, f in enumerate(sorted((realdata / "occ3d").glob("*/labels.npz"))):
        token = f.parent.name
        labels = sparseocc.read_voxels(f)
        assert set(labels) == {"semantics", "mask_lidar", "mask_camera"}
        assert labels["semantics"].shape == (200, 200, 16)
        sparseocc.write_voxels(gt / "scene-0001" / token / "labels.npz", labels)
        p = dict(labels, semantics=perturbed(labels["semantics"], k, 18))
        sparseocc.write_voxels(pred / "scene-0001" / token / "labels.npz", p)
    got = sparseocc.evaluate(gt, pred, dataset="occ3d", progress=False)
    assert got == cli_eval(cli, gt, pred, "occ3d", tmp_path)
    assert got["dataset"] == "occ3d" and got["frames"] >= 1


def test_confusion_and_report_agree_with_the_folder_score(tmp_path, kitti_data):
    lab = kitti_data / "sequences" / "08" / "voxels" / "000000.label"
    gt = sparseocc.read_voxels(lab, learning=True)
    invalid = sparseocc.read_voxels(lab.with_suffix(".invalid"))
    pred = perturbed(np.where(gt == 255, 0, gt), 3, 20)
    sparseocc.write_voxels(tmp_path / "sequences/08/predictions/000000.label", pred, learning=True)
    folder = sparseocc.evaluate(kitti_data, tmp_path, sequences="08", progress=False)
    conf = sparseocc.confusion(pred, gt, invalid)
    assert conf.dtype == np.uint64 and conf.shape == (20, 20)
    assert conf.tolist() == folder["confusion"]
    assert sparseocc.report(conf) == folder
    # Layout and dtype do not matter: a Fortran-order int64 copy gives the same matrix.
    assert (sparseocc.confusion(np.asfortranarray(pred.astype(np.int64)), gt, invalid) == conf).all()
    # Predictions outside the classes count as empty (class 0) and are not lost.
    bad = pred.astype(np.int64)
    bad[0, 0, 0] = 300
    assert sparseocc.confusion(bad, gt).sum() == sparseocc.confusion(pred, gt).sum()


def test_class_names():
    assert sparseocc.class_names()[:2] == ["empty", "car"]
    assert len(sparseocc.class_names("occ3d")) == 18
    assert len(sparseocc.class_names("nuscenes-occupancy")) == 17


def test_scoring_errors(tmp_path, kitti_data):
    with pytest.raises(sparseocc.SparseOccError, match="missing prediction"):
        sparseocc.evaluate(kitti_data, tmp_path / "nothing", progress=False)
    with pytest.raises(sparseocc.SparseOccError, match=str(tmp_path / "nowhere")):
        sparseocc.evaluate(tmp_path / "nowhere", tmp_path, progress=False)
    with pytest.raises(ValueError, match="unknown dataset"):
        sparseocc.evaluate(kitti_data, kitti_data, dataset="kitty")
    with pytest.raises(ValueError, match="shape"):
        sparseocc.confusion(np.zeros((2, 2), dtype=int), np.zeros((2, 3), dtype=int))
    with pytest.raises(ValueError, match="integer"):
        sparseocc.confusion(np.zeros(4), np.zeros(4, dtype=np.uint8))
    with pytest.raises(ValueError, match="square"):
        sparseocc.report(np.zeros((20, 19), dtype=int))
    with pytest.raises(ValueError, match="classes"):
        sparseocc.report(np.zeros((18, 18), dtype=int))
    # Counts that are not counts are refused, not rounded, wrapped or summed past 2^64.
    with pytest.raises(ValueError, match="integer"):
        sparseocc.report(np.full((20, 20), 1.5))
    with pytest.raises(ValueError, match="negative"):
        sparseocc.report(np.full((20, 20), -1))
    with pytest.raises(ValueError, match="2\\^64"):
        sparseocc.report(np.full((20, 20), 2**63, dtype=np.uint64))
