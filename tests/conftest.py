"""Shared fixtures: the real data (Bandai-Namco archives and the HumanML3D golden clip)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from motok.data.root import resolve_data_root


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


@pytest.fixture(scope="session")
def bandai_slice(tmp_path_factory, bandai2_archive) -> Path:
    """The 24 `walk_normal` clips of set 2, pulled out of the real archive once per session."""
    import fnmatch
    import tarfile

    out = tmp_path_factory.mktemp("bandai-slice")
    with tarfile.open(bandai2_archive, "r|xz") as tar:
        for m in tar:
            name = Path(m.name).name
            if m.isfile() and fnmatch.fnmatchcase(name, SLICE_PATTERN + ".bvh"):
                (out / name).write_bytes(tar.extractfile(m).read())
    return out


@pytest.fixture(scope="session")
def small_dataset(tmp_path_factory, bandai_slice, bandai_dir) -> Path:
    """A real motion-dataset artifact preprocessed from the walk_normal slice."""
    from motok.data.preprocess import PreprocessConfig, preprocess

    out = tmp_path_factory.mktemp("datasets") / "walk_normal.h5"
    cfg = PreprocessConfig(inputs=[str(bandai_slice)], annotations=str(bandai_dir / "annotations"),
                           pattern=SLICE_PATTERN, skeleton="bandai21")
    preprocess(cfg, out, command="pytest small_dataset")
    return out
