"""``sparseocc.sparse.conv3d`` against a numpy brute force, the ``conv_npy`` example, and spconv."""

import json
import re
import threading
import time

import numpy as np
import pytest

import sparseocc
from sparseocc.sparse import conv3d
from conftest import run


def random_case(seed, shape=(11, 9, 6), batch=2, n=150, cin=4, cout=5, k=(3, 3, 3)):
    rng = np.random.default_rng(seed)
    total = batch * int(np.prod(shape))
    flat = rng.choice(total, size=min(n, total), replace=False)
    b, rest = np.divmod(flat, int(np.prod(shape)))
    x, rest = np.divmod(rest, shape[1] * shape[2])
    y, z = np.divmod(rest, shape[2])
    coords = np.stack([b, x, y, z], axis=1).astype(np.int32)
    feats = rng.uniform(-1, 1, size=(len(coords), cin)).astype(np.float32)
    weight = rng.uniform(-1, 1, size=(cout, *k, cin)).astype(np.float32)
    return coords, feats, weight


def brute_force(coords, feats, weight, shape, k, s, p, subm=False, transposed=False):
    """``out[o] = sum W[:, k, :] @ x[i]`` over the (input i, offset k, output o) triples, in float64."""
    k, s, p = map(np.asarray, (k, s, p))
    shape = np.asarray(shape)
    if subm:
        out_shape = shape
    elif transposed:
        out_shape = (shape - 1) * s - 2 * p + k
    else:
        out_shape = (shape + 2 * p - k) // s + 1
    inputs = {tuple(c): i for i, c in enumerate(coords.tolist())}
    out = {}
    for c, i in inputs.items():
        for off in np.ndindex(*k):
            off = np.asarray(off)
            x = np.asarray(c[1:])
            if subm:
                o = x + k // 2 - off
            elif transposed:
                o = x * s - p + off
            else:
                t = x + p - off
                if (t % s).any():
                    continue
                o = t // s
            if (o < 0).any() or (o >= out_shape).any():
                continue
            key = (c[0], *o.tolist())
            if subm and key not in inputs:
                continue
            w = weight[:, off[0], off[1], off[2], :].astype(np.float64)
            out[key] = out.get(key, 0) + w @ feats[i].astype(np.float64)
    keys = sorted(out)
    return np.asarray(keys, dtype=np.int32).reshape(-1, 4), np.asarray([out[q] for q in keys])


@pytest.mark.parametrize(
    "kind,k,s,p",
    [
        ("subm", (3, 3, 3), 1, 0),
        ("subm", (3, 3, 1), 1, 0),
        ("regular", (3, 3, 3), 1, 1),
        ("regular", (2, 2, 2), 2, 0),
        ("regular", (3, 3, 3), 2, (1, 1, 0)),
        ("transposed", (2, 2, 2), 2, 0),
    ],
)
def test_conv3d_matches_brute_force(kind, k, s, p):
    coords, feats, weight = random_case(7, k=k)
    shape = (11, 9, 6)
    s3 = (s,) * 3 if isinstance(s, int) else s
    p3 = (p,) * 3 if isinstance(p, int) else p
    oc, of = conv3d(coords, feats, weight, shape, k, s, p, subm=kind == "subm",
                    transposed=kind == "transposed")
    wc, wf = brute_force(coords, feats, weight, shape, k, s3, p3, kind == "subm", kind == "transposed")
    assert oc.dtype == np.int32 and of.dtype == np.float32
    assert (oc == wc).all()
    np.testing.assert_allclose(of, wf, rtol=1e-5, atol=1e-5)


def test_any_memory_layout_gives_the_same_result():
    coords, feats, weight = random_case(3, n=200)
    base = conv3d(coords, feats, weight, (11, 9, 6), 3, subm=True)
    wide = np.zeros((len(coords), 6), dtype=np.int64)
    wide[:, 1:5] = coords
    perm = np.random.default_rng(1).permutation(len(coords))
    variants = [
        (wide[:, 1:5], feats, weight),  # a column slice (not contiguous), int64
        (np.asfortranarray(coords), np.asfortranarray(feats), np.asfortranarray(weight)),
        (coords[::-1], feats[::-1], weight),  # negative strides, reversed rows
        (coords[perm].astype(np.int16), feats[perm].astype(">f4"), weight.astype(">f4")),
        (coords.tolist(), feats.astype(np.float64), weight),
    ]
    for c, f, w in variants:
        oc, of = conv3d(c, f, w, (11, 9, 6), 3, subm=True)
        assert (oc == base[0]).all()
        np.testing.assert_array_equal(of, base[1])


def test_equals_the_conv_npy_example(tmp_path, conv_npy):
    coords, feats, weight = random_case(5, shape=(20, 16, 8), n=600, cin=8, cout=6)
    for i, (name, a) in enumerate([("c", coords), ("f", feats), ("w", weight)]):
        np.save(tmp_path / f"{name}.npy", a)
    for extra, kw in [(["--subm"], dict(subm=True)), (["--stride", "2", "--padding", "1"],
                                                         dict(stride=2, padding=1))]:
        run([conv_npy, "--coords", tmp_path / "c.npy", "--feats", tmp_path / "f.npy",
             "--weight", tmp_path / "w.npy", "--spatial-shape", "20,16,8", "--kernel", "3",
             "--repeat", "1", "--out-coords", tmp_path / "oc.npy", "--out-feats", tmp_path / "of.npy",
             *extra])
        oc, of = conv3d(coords, feats, weight, (20, 16, 8), 3, **kw)
        assert (oc == np.load(tmp_path / "oc.npy")).all()
        np.testing.assert_array_equal(of, np.load(tmp_path / "of.npy"))


def _ints(repr_, key):
    m = re.search(key + r"=\[([^\]]*)\]", repr_)
    return tuple(int(v) for v in m.group(1).split(",")) if m else None


def test_spconv_fixtures(fixtures):
    """Every single-layer case of the spconv 2.3.8 fixtures (discovered from the manifest)."""
    d = fixtures / "spconv"
    manifest = json.loads((d / "manifest.json").read_text())
    coords = np.load(d / "input_coords_bxyz.npy")
    feats = np.load(d / "input_feats.npy")
    shape = tuple(manifest["spatial_shape_xyz"])
    tol = manifest["tolerance"]
    n = 0
    for name, case in manifest["cases"].items():
        layer = case.get("layer", "")
        if not (d / f"{name}_weight.npy").exists() or not layer.startswith(("SubMConv3d", "SparseConv3d")):
            continue  # multi-layer cases (inverse) are covered by the Rust tests
        weight = np.load(d / f"{name}_weight.npy")
        oc, of = conv3d(coords, feats, weight, shape, _ints(layer, "kernel_size"),
                        _ints(layer, "stride"), _ints(layer, "padding"),
                        subm=layer.startswith("SubMConv3d"), batch_size=manifest["batch"])
        want_c = np.load(d / f"{name}_out_coords_bxyz.npy")
        want_f = np.load(d / f"{name}_out_feats.npy")
        assert (oc == want_c).all(), name
        assert np.abs(of - want_f).max() <= tol, name
        n += 1
    assert n >= 1


def test_bad_input_is_a_clear_error():
    coords, feats, weight = random_case(2, n=10)
    with pytest.raises(ValueError, match="duplicate coordinate"):
        conv3d(np.concatenate([coords, coords[:1]]), np.concatenate([feats, feats[:1]]), weight,
               (11, 9, 6), 3, subm=True)
    bad = coords.copy()
    bad[0, 1] = 11
    with pytest.raises(ValueError, match="outside the spatial shape"):
        conv3d(bad, feats, weight, (11, 9, 6), 3, subm=True)
    with pytest.raises(ValueError, match=r"weight must be \[Cout, 3, 3, 3, Cin=4\]"):
        conv3d(coords, feats, weight[..., :2], (11, 9, 6), 3)
    with pytest.raises(ValueError, match="coords must be"):
        conv3d(coords[:, :3], feats, weight, (11, 9, 6), 3)
    with pytest.raises(ValueError, match="integer"):
        conv3d(coords.astype(np.float32), feats, weight, (11, 9, 6), 3)
    with pytest.raises(ValueError, match="fit int32"):
        conv3d(coords.astype(np.int64) + 2**40, feats, weight, (11, 9, 6), 3)
    with pytest.raises(ValueError):
        conv3d(coords, feats, weight[:, :2, :2, :2], (11, 9, 6), 2, subm=True)  # even subm kernel
    # Geometry beyond the largest grid axis: was a division by zero (stride) or a silent
    # truncation to 0 (padding) in the int32 site arithmetic.
    for geometry in ({"stride": 2**40}, {"padding": 2**40}, {"dilation": 2**20},
                     {"stride": 2**20, "transposed": True}):
        with pytest.raises(ValueError, match="at most 32768"):
            conv3d(coords, feats, weight, (11, 9, 6), 3, **geometry)
    with pytest.raises(ValueError, match="output spatial shape"):
        conv3d(coords, feats, weight, (11, 9, 6), 3, padding=20000)


def test_the_gil_is_released_during_the_work():
    coords, feats, weight = random_case(4, shape=(96, 96, 32), n=60000, cin=32, cout=32)
    done = threading.Event()
    seconds = []

    def work():
        t0 = time.perf_counter()
        conv3d(coords, feats, weight, (96, 96, 32), 3, subm=True)
        seconds.append(time.perf_counter() - t0)
        done.set()

    t = threading.Thread(target=work)
    ticks = 0
    t.start()
    while not done.is_set():
        ticks += 1
        time.sleep(0.001)
    t.join()
    # With the GIL held for the whole call this loop could not run while it lasts.
    assert ticks >= 0.25 * seconds[0] / 0.002, (ticks, seconds)
