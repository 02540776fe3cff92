"""Shared fixtures: the real data (Bandai-Namco archives and the HumanML3D golden clip)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from motok.cli.common import choose_mujoco_gl
from motok.data.root import resolve_data_root

choose_mujoco_gl()  # as the motok command does, before any test module imports mujoco


@pytest.fixture(scope="module")
def one_thread():
    """Tiny models on a shared 2-core machine: a second intra-op thread only spin-waits (and a
    second thread makes MuJoCo and torch compete). Modules opt in with
    ``pytestmark = pytest.mark.usefixtures("one_thread")``."""
    import torch

    before = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(before)


@pytest.fixture(scope="session")
def script():
    """``script(name)``: the repository's ``scripts/NAME.py`` as a module (scripts are no package)."""
    import importlib.util

    scripts = Path(__file__).resolve().parents[1] / "scripts"

    def load(name: str):
        spec = importlib.util.spec_from_file_location(name, scripts / f"{name}.py")
        module = importlib.util.module_from_spec(spec)
        spec.loader.exec_module(module)
        return module

    return load


@pytest.fixture(scope="session")
def data_root() -> Path:
    return resolve_data_root()


@pytest.fixture(scope="session")
def bandai_dir(data_root) -> Path:
    return data_root / "bandai-namco"


@pytest.fixture(scope="session")
def bandai2_archive(bandai_dir) -> Path:
    return bandai_dir / "bandai-namco-2.tar.xz"


@pytest.fixture(scope="session")
def golden_dir(data_root) -> Path:
    return data_root / "humanml3d-sample"


@pytest.fixture(scope="session")
def golden_joints(golden_dir) -> np.ndarray:
    return np.load(golden_dir / "new_joints_012314.npy")


@pytest.fixture(scope="session")
def golden_features(golden_dir) -> np.ndarray:
    return np.load(golden_dir / "new_joint_vecs_012314.npy")


SLICE_PATTERN = "dataset-2_walk_normal_*"
LABELLED_PATTERN = "dataset-2_*_00[1-3]"  # 10 contents x 7 styles x 3 takes: 210 clips, 70 label sets


@pytest.fixture(scope="session")
def bandai_slices(tmp_path_factory, bandai2_archive) -> dict[str, Path]:
    """Two folders of real clips pulled out of the archive in one streaming pass per session:
    ``walk``: the 24 `walk_normal` clips (one label); ``labelled``: takes 1-3 of every
    content x style (210 clips), for anything that needs negatives across labels."""
    import fnmatch
    import tarfile

    out = {"walk": tmp_path_factory.mktemp("bandai-slice"), "labelled": tmp_path_factory.mktemp("bandai-labelled")}
    with tarfile.open(bandai2_archive, "r|xz") as tar:
        for m in tar:
            name = Path(m.name).name
            if not (m.isfile() and name.endswith(".bvh")):
                continue
            hits = [k for k, pat in (("walk", SLICE_PATTERN), ("labelled", LABELLED_PATTERN))
                    if fnmatch.fnmatchcase(name, pat + ".bvh")]
            if hits:
                data = tar.extractfile(m).read()
                for k in hits:
                    (out[k] / name).write_bytes(data)
    return out


@pytest.fixture(scope="session")
def bandai_slice(bandai_slices) -> Path:
    return bandai_slices["walk"]


@pytest.fixture(scope="session")
def labelled_dataset(tmp_path_factory, bandai_slices, bandai_dir) -> Path:
    """A real motion-dataset of every content x style label of set 2 (takes 1-3)."""
    from motok.data.preprocess import PreprocessConfig, preprocess

    out = tmp_path_factory.mktemp("labelled-data") / "labelled.h5"
    cfg = PreprocessConfig(data=[str(bandai_slices["labelled"])], annotations=str(bandai_dir / "annotations"),
                           clips=LABELLED_PATTERN, skeleton="bandai21")
    preprocess(cfg, out, command="pytest labelled_dataset")
    return out


@pytest.fixture(scope="session")
def small_dataset(tmp_path_factory, bandai_slice, bandai_dir) -> Path:
    """A real motion-dataset artifact preprocessed from the walk_normal slice."""
    from motok.data.preprocess import PreprocessConfig, preprocess

    out = tmp_path_factory.mktemp("datasets") / "walk_normal.h5"
    cfg = PreprocessConfig(data=[str(bandai_slice)], annotations=str(bandai_dir / "annotations"),
                           clips=SLICE_PATTERN, skeleton="bandai21")
    preprocess(cfg, out, command="pytest small_dataset")
    return out


@pytest.fixture(scope="session")
def hum_path(small_dataset, tmp_path_factory) -> Path:
    """The MuJoCo humanoid built from the walk_normal slice (one build per test session)."""
    from motok.sim.mjcf import build_humanoid

    path = tmp_path_factory.mktemp("humanoid") / "humanoid.xml"
    build_humanoid(small_dataset, path)
    return path


@pytest.fixture(scope="session")
def hum(hum_path):
    from motok.sim.humanoid import load_humanoid

    return load_humanoid(hum_path)


@pytest.fixture(scope="session")
def lib(hum, small_dataset, tmp_path_factory):
    """Every clip of the walk_normal slice as a reference library, cached in the test session only."""
    from motok.sim.reference import load_library

    return load_library(hum, small_dataset, cache_dir=tmp_path_factory.mktemp("reference-cache"))


def unavailable(reason: str):
    """A test whose machine lacks what it needs (root for a tmpfs, Xvfb) skips on a developer's
    machine, saying why; under CI (``CI`` set, as .ci/run is run) it fails instead, so CI runs
    every test or says which one it could not."""
    import os

    if os.environ.get("CI", "").lower() in ("1", "true", "yes"):
        pytest.fail(f"CI must run this test: {reason}")
    pytest.skip(reason)


def require_module(name: str, reason: str):
    """``name`` imported, or the test is `unavailable` (skips locally, fails under CI): the optional
    extras CI installs (gpu, tensorboard) are then tested, never silently skipped."""
    import importlib

    try:
        return importlib.import_module(name)
    except ImportError:
        unavailable(reason)


def assert_cli_accepts(commands) -> None:
    """Each argv (without ``motok``) parses with every option it gives: ``--help`` goes last, and
    click parses all options before it stops, so an unknown option or a missing value fails while
    nothing runs (values are converted later: not checked here). For command lines written outside
    Python (the physics queue, the Makefile's demos), which a renamed option would break hours in."""
    from typer.testing import CliRunner

    from motok.cli.main import app

    runner = CliRunner()
    for argv in commands:
        res = runner.invoke(app, [*argv, "--help"])
        assert res.exit_code == 0 and "Usage:" in res.output, (argv, res.output)
