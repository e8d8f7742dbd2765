"""``Model``: a trained run from Python equals ``sparseocc infer`` on the same inputs."""

import numpy as np
import pytest

import sparseocc
from conftest import run


def test_predict_equals_infer_image(tmp_path, cli, tiny_run, kitti_data):
    seq = kitti_data / "sequences" / "08"
    image, calib = seq / "image_2" / "000000.png", seq / "calib.txt"
    out = tmp_path / "infer"
    run([cli, "infer", "--checkpoint", tiny_run, "--image", image, "--calib", calib, "--out", out])
    want = sparseocc.read_voxels(out / "000000.label", learning=True)

    model = sparseocc.Model.load(tiny_run)
    assert model.kind == "sparseocc++" and model.grid_shape == (128, 128, 16)
    assert model.class_names[0] == "empty" and "sparseocc++" in repr(model)
    rgb = sparseocc.read_image(image)
    assert rgb.dtype == np.uint8 and rgb.ndim == 3 and rgb.shape[2] == 3
    got = model.predict(rgb, calib)
    assert got.dtype == np.uint8 and got.shape == (128, 128, 16)
    assert (got == want).all()
    # The calibration as matrices, the image as a Fortran-order copy: the same prediction.
    rows = {}
    for line in calib.read_text().splitlines():
        if ":" in line:
            k, v = line.split(":", 1)
            if k.strip() in ("P2", "Tr"):
                rows[k.strip()] = np.array(v.split(), dtype=np.float64).reshape(3, 4)
    assert (model.predict(np.asfortranarray(rgb), rows) == want).all()


def test_predict_frame_equals_infer_on_the_dataset(tmp_path, cli, tiny_run, kitti_data):
    out = tmp_path / "infer"
    run([cli, "infer", "--checkpoint", tiny_run, "--data", kitti_data, "--sequences", "08",
         "--out", out, "--render", "0"])
    want = sparseocc.read_voxels(out / "sequences/08/predictions/000000.label", learning=True)
    got = sparseocc.Model.load(tiny_run / "checkpoint").predict_frame(kitti_data, "08", "000000")
    assert (got == want).all()


def test_predict_on_a_real_kitti_image(tiny_run, realdata):
    seq = realdata / "semantickitti" / "sequences" / "08"
    model = sparseocc.Model.load(tiny_run)
    got = model.predict(sparseocc.read_image(seq / "image_2" / "000000.png"), seq / "calib.txt")
    assert got.shape == model.grid_shape and got.max() < 20


def test_model_errors(tmp_path, tiny_run, kitti_data):
    with pytest.raises(sparseocc.SparseOccError, match="not a training run"):
        sparseocc.Model.load(tmp_path)
    model = sparseocc.Model.load(tiny_run)
    calib = kitti_data / "sequences" / "08" / "calib.txt"
    with pytest.raises(ValueError, match=r"\[H, W, 3\]"):
        model.predict(np.zeros((10, 10), dtype=np.uint8), calib)
    with pytest.raises(sparseocc.SparseOccError, match="principal point"):
        model.predict(np.zeros((40, 2000, 3), dtype=np.uint8), calib)
    with pytest.raises(ValueError, match="calib"):
        model.predict(np.zeros((185, 613, 3), dtype=np.uint8), 42)
    image = sparseocc.read_image(kitti_data / "sequences" / "08" / "image_2" / "000000.png")
    p2 = np.array([[360.77, 0, 304.78, 0], [0, 360.77, 86.43, 0], [0, 0, 1, 0]])
    tr = np.array([[0, -1, 0, 0], [0, 0, -1, -0.15], [1, 0, 0, -0.27]])
    # Any array-like of numbers is a matrix: integers, nested lists.
    rot = np.array([[0, -1, 0, 0], [0, 0, -1, 0], [1, 0, 0, 0]])
    want = model.predict(image, {"P2": p2, "Tr": rot.astype(np.float64)})
    assert (model.predict(image, {"P2": p2.tolist(), "Tr": rot.tolist()}) == want).all()
    assert (model.predict(image, {"P2": p2, "Tr": rot}) == want).all()
    with pytest.raises(ValueError, match="pinhole"):
        model.predict(image, {"P2": np.zeros((3, 4)), "Tr": tr})
    skew = p2.copy()
    skew[0, 1] = 3.0
    with pytest.raises(ValueError, match="pinhole"):
        model.predict(image, {"P2": skew, "Tr": tr})
    with pytest.raises(ValueError, match="rotation"):
        model.predict(image, {"P2": p2, "Tr": tr * 1000})
    with pytest.raises(ValueError, match=r"calib\['Tr'\] must be a 3x4 array of numbers"):
        model.predict(image, {"P2": p2, "Tr": "x"})
    with pytest.raises(ValueError, match="uint8.*got dtype float32"):
        model.predict(image.astype(np.float32) / 255, calib)
    with pytest.raises(sparseocc.SparseOccError, match="no frame 999999"):
        model.predict_frame(kitti_data, "08", "999999")
    with pytest.raises(sparseocc.SparseOccError, match="no such file|not found"):
        sparseocc.read_image(tmp_path / "none.png")
    # An image cut short is refused, not decoded with a grey remainder.
    whole = (kitti_data / "sequences" / "08" / "image_2" / "000000.png").read_bytes()
    (tmp_path / "cut.png").write_bytes(whole[: len(whole) // 2])
    with pytest.raises(sparseocc.SparseOccError, match="cut.png.*truncated"):
        sparseocc.read_image(tmp_path / "cut.png")
