"""`sparseocc.sparse.conv3d` against a live spconv 2.3.8 (CPU) on fresh seeded random inputs.

Skipped unless torch and spconv are importable (e.g. /root/venv-spconv: torch + spconv==2.3.8). spconv runs with
one PyTorch thread: spconv 2.3.8's CPU convolution gives wrong features with more than one thread
(scripts/compare_spconv.py measures that). Correctness only: same output site set, features matched by site
within |a - b| <= 1e-4 + 1e-4 * |b| (b = spconv). No timing assertions.
"""
import numpy as np
import pytest

torch = pytest.importorskip("torch")
spc = pytest.importorskip("spconv.pytorch")
sparse = pytest.importorskip("sparseocc.sparse")

TOL = 1e-4


@pytest.fixture(autouse=True)
def one_torch_thread():
    before = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(before)


def triple(v):
    return (int(v),) * 3 if np.isscalar(v) else tuple(int(a) for a in v)


def random_case(seed, shape, n_per_batch, batch, cin, cout, kernel):
    rng = np.random.default_rng(seed)
    sx, sy, sz = shape
    rows = []
    for b in range(batch):
        lin = rng.choice(sx * sy * sz, size=n_per_batch, replace=False)
        x, rem = np.divmod(lin, sy * sz)
        y, z = np.divmod(rem, sz)
        rows.append(np.stack([np.full_like(x, b), x, y, z], axis=1))
    coords = np.concatenate(rows).astype(np.int32)
    coords = np.ascontiguousarray(coords[rng.permutation(len(coords))])
    k = triple(kernel)
    feats = rng.standard_normal((len(coords), cin)).astype(np.float32)
    weight = (rng.standard_normal((cout, *k, cin)) / np.sqrt(np.prod(k) * cin)).astype(np.float32)
    return coords, feats, weight


def run_spconv(coords, feats, weight, shape, batch, kernel, stride, padding, subm):
    k = triple(kernel)
    cout, cin = weight.shape[0], weight.shape[-1]
    kw = dict(bias=False, algo=spc.ConvAlgo.Native)
    if subm:
        layer = spc.SubMConv3d(cin, cout, k, padding=tuple(a // 2 for a in k), **kw)
    else:
        layer = spc.SparseConv3d(cin, cout, k, stride=stride, padding=padding, **kw)
    # spconv 2.x's weight layout is [Cout, kx, ky, kz, Cin], the same as sparseocc's.
    assert tuple(layer.weight.shape) == weight.shape
    with torch.no_grad():
        layer.weight.copy_(torch.from_numpy(weight))
        out = layer(spc.SparseConvTensor(torch.from_numpy(feats), torch.from_numpy(coords), list(shape), batch))
    return out.indices.numpy(), out.features.numpy(), tuple(out.spatial_shape)


def keys(coords, shape):
    c = np.asarray(coords).astype(np.int64)
    return ((c[:, 0] * shape[0] + c[:, 1]) * shape[1] + c[:, 2]) * shape[2] + c[:, 3]


def assert_same(ours, theirs, out_shape):
    (oc, of), (sc, sf) = ours, theirs
    assert oc.dtype == np.int32 and of.dtype == np.float32
    assert oc.ndim == 2 and oc.shape[1] == 4 and of.shape[0] == oc.shape[0]
    ko, ks = keys(oc, out_shape), keys(sc, out_shape)
    assert (np.diff(ko) > 0).all(), "sparseocc's output sites are not sorted by (b, x, y, z) / not unique"
    missing, extra = np.setdiff1d(ks, ko), np.setdiff1d(ko, ks)
    assert len(missing) == 0 and len(extra) == 0 and len(ko) == len(ks), (
        f"site sets differ: {len(missing)} spconv sites missing, {len(extra)} extra (of {len(ks)})")
    order = np.argsort(ks)
    sf = sf[order].astype(np.float64)
    diff = np.abs(of.astype(np.float64) - sf)
    bad = diff > TOL + TOL * np.abs(sf)
    assert not bad.any(), (
        f"{int(bad.sum())} features differ; max abs diff {diff.max():.3e}, max |spconv| {np.abs(sf).max():.3e}")


CASES = [
    # name, seed, shape, n per batch, batch, cin, cout, kernel, stride, padding, subm
    ("subm_k3_b1", 11, (64, 64, 16), 3000, 1, 16, 32, 3, 1, 1, True),
    ("subm_k331_b2", 12, (48, 40, 12), 2000, 2, 32, 16, (3, 3, 1), 1, (1, 1, 0), True),
    ("conv_k3_s1_p1_b2", 13, (64, 64, 16), 1500, 2, 16, 48, 3, 1, 1, False),
    ("conv_k2_s2_b2_odd_shape", 14, (63, 50, 15), 2500, 2, 64, 32, 2, 2, 0, False),
    ("conv_k3_s2_p1_b1", 15, (64, 64, 16), 3000, 1, 32, 64, 3, 2, 1, False),
    ("conv_k331_p110_b1", 16, (64, 64, 16), 2000, 1, 32, 16, (3, 3, 1), 1, (1, 1, 0), False),
]


@pytest.mark.parametrize("case", CASES, ids=[c[0] for c in CASES])
def test_conv3d_matches_spconv(case):
    _, seed, shape, n, batch, cin, cout, kernel, stride, padding, subm = case
    coords, feats, weight = random_case(seed, shape, n, batch, cin, cout, kernel)
    sc, sf, out_shape = run_spconv(coords, feats, weight, shape, batch, kernel, stride, padding, subm)
    ours = sparse.conv3d(coords, feats, weight, shape, kernel, stride=stride, padding=padding, subm=subm,
                         batch_size=batch)
    assert len(sc) > 0
    assert_same(ours, (sc, sf), out_shape)


def view_of(kind, a):
    """An array equal to `a` in logical (C) order but with another memory layout and/or dtype."""
    if kind == "c":
        return a
    if kind == "int64_column_slice":  # a [N, 4] column slice of a wider int64 array; neighbours hold garbage
        wide = np.full((a.shape[0], a.shape[1] + 3), -99, dtype=np.int64)
        wide[:, 2:2 + a.shape[1]] = a
        return wide[:, 2:2 + a.shape[1]]
    if kind == "fortran":
        return np.asfortranarray(a)
    if kind == "float64_fortran":
        return np.asfortranarray(a.astype(np.float64))
    if kind == "bigendian_every_other_column":
        big = np.zeros((a.shape[0], a.shape[1] * 2), dtype=">f4")
        big[:, ::2] = a
        return big[:, ::2]
    if kind == "permuted_view":  # [Cout, kx, ky, kz, Cin] as a transposed view of a [Cin, kx, ky, kz, Cout] array
        return np.ascontiguousarray(np.transpose(a, (4, 1, 2, 3, 0))).transpose(4, 1, 2, 3, 0)
    raise ValueError(kind)


LAYOUTS = [
    # id, coords layout, feats layout, weight layout
    ("coords_int64_column_slice", "int64_column_slice", "c", "c"),
    ("coords_fortran_int32", "fortran", "c", "c"),
    ("feats_float64_fortran", "c", "float64_fortran", "c"),
    ("feats_bigendian_strided", "c", "bigendian_every_other_column", "c"),
    ("weight_permuted_view", "c", "c", "permuted_view"),
    ("weight_fortran", "c", "c", "fortran"),
    ("all_strided_views", "int64_column_slice", "bigendian_every_other_column", "permuted_view"),
]


@pytest.mark.parametrize("layout", LAYOUTS, ids=[l[0] for l in LAYOUTS])
def test_conv3d_reads_non_contiguous_inputs(layout):
    """Inputs given as non-contiguous views / Fortran order / other dtypes must be read in logical order:
    the result must match spconv on the contiguous int32 / float32 arrays (and sparseocc on them, exactly)."""
    _, kc, kf, kw = layout
    shape, batch, kernel, stride, padding = (40, 36, 12), 2, 3, 2, 1
    coords, feats, weight = random_case(21, shape, 1500, batch, 24, 40, kernel)
    sc, sf, out_shape = run_spconv(coords, feats, weight, shape, batch, kernel, stride, padding, False)
    c_v, f_v, w_v = view_of(kc, coords), view_of(kf, feats), view_of(kw, weight)
    for kind, v, a in ((kc, c_v, coords), (kf, f_v, feats), (kw, w_v, weight)):
        assert np.array_equal(v, a)
        assert kind == "c" or not v.flags["C_CONTIGUOUS"]

    ours = sparse.conv3d(c_v, f_v, w_v, shape, kernel, stride=stride, padding=padding)
    assert_same(ours, (sc, sf), out_shape)
    ref = sparse.conv3d(coords, feats, weight, shape, kernel, stride=stride, padding=padding)
    assert np.array_equal(ours[0], ref[0]) and np.array_equal(ours[1], ref[1])
