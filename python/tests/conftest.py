"""Shared fixtures of the Python package's tests.

External folders (``SPARSEOCC_FIXTURES``, ``SPARSEOCC_REALDATA``) and the project's built
binaries (``SPARSEOCC_BIN``: the ``sparseocc`` binary; ``SPARSEOCC_TARGET_DIR``: the cargo target
folder holding ``release/examples/conv_npy``) are optional: a test that needs a missing one is
skipped with the reason, or fails when ``SPARSEOCC_REQUIRE_DATA=1`` (as ``.ci/run`` sets it).
"""

import os
import pathlib
import shutil
import subprocess

import pytest

import sparseocc

REPO = pathlib.Path(__file__).resolve().parents[2]
REQUIRE = os.environ.get("SPARSEOCC_REQUIRE_DATA") == "1"


def need(path, what):
    """``path`` if it exists; else skip (or fail under ``SPARSEOCC_REQUIRE_DATA=1``)."""
    if path is not None and pathlib.Path(path).exists():
        return pathlib.Path(path)
    msg = f"{what} not found ({path}); set the variable named in tests/conftest.py"
    if REQUIRE:
        pytest.fail(msg + " (SPARSEOCC_REQUIRE_DATA=1)")
    pytest.skip(msg)


def _target_dir():
    t = os.environ.get("SPARSEOCC_TARGET_DIR") or os.environ.get("CARGO_TARGET_DIR")
    return pathlib.Path(t) if t else REPO / "target"


@pytest.fixture(scope="session")
def cli():
    """The ``sparseocc`` binary (for the results the Python API must equal)."""
    b = os.environ.get("SPARSEOCC_BIN") or shutil.which("sparseocc")
    if b is None:
        b = _target_dir() / "release" / "sparseocc"
    return need(b, "the sparseocc binary (SPARSEOCC_BIN)")


@pytest.fixture(scope="session")
def conv_npy():
    """occ-sparse's ``conv_npy`` example binary (cargo builds it with the tests)."""
    return need(_target_dir() / "release" / "examples" / "conv_npy", "the conv_npy example (SPARSEOCC_TARGET_DIR)")


@pytest.fixture(scope="session")
def fixtures():
    return need(
        os.environ.get("SPARSEOCC_FIXTURES", str(REPO.parent / "shared" / "fixtures")),
        "external fixtures folder (SPARSEOCC_FIXTURES)",
    )


@pytest.fixture(scope="session")
def realdata():
    return need(
        os.environ.get("SPARSEOCC_REALDATA", str(REPO.parent / "shared" / "realdata")),
        "external real-data folder (SPARSEOCC_REALDATA)",
    )


def run(cmd, **kw):
    """Runs a command (progress bars off), failing the test with its output if it fails."""
    env = dict(os.environ, CI="1")
    r = subprocess.run([str(c) for c in cmd], capture_output=True, text=True, env=env, **kw)
    assert r.returncode == 0, f"{cmd} failed ({r.returncode}):\n{r.stdout}\n{r.stderr}"
    return r


@pytest.fixture(scope="session")
def kitti_data(tmp_path_factory):
    """A small synthetic SemanticKITTI-layout dataset: training sequence 00 (2 frames), 08 (1)."""
    out = tmp_path_factory.mktemp("synth") / "data"
    sparseocc.synth(out, preset="kitti-small", sequences="00:2,08:1", seed=0, progress=False)
    return out


TINY_CONFIG = """
[model]
kind = "sparseocc++"
num_classes = 20
full_dims = [128, 128, 16]
lss_level = 0

[model.encoder.resnet]
depth = 18
base_width = 8
out_indices = [1]

[model.encoder.fpn]
out_channels = 16

[model.sparseocc_pp]
embed_dim = 16
dca_heads = 2
keep_ratios = [1.0, 0.1, 0.1]

[train]
steps = 2
lr = 1e-3
checkpoint_every = 2

[data]
image_width = 160
image_height = 64
train_sequences = ["00"]
val_sequences = ["08"]
"""


@pytest.fixture(scope="session")
def tiny_run(tmp_path_factory, cli, kitti_data):
    """A tiny SparseOcc++ trained for 2 steps by ``sparseocc train`` on ``kitti_data``."""
    root = tmp_path_factory.mktemp("run")
    cfg = root / "tiny.toml"
    cfg.write_text(TINY_CONFIG)
    run_dir = root / "run"
    run([cli, "train", "--config", cfg, "--data", kitti_data, "--out", run_dir])
    return run_dir
