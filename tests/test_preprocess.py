"""`motok preprocess` end to end on real Bandai-Namco clips, and its bad-input handling."""

from __future__ import annotations

import io
import re
import tarfile
from pathlib import Path

import numpy as np
import pytest

from motok.data.annotations import Annotations
from motok.data.bvh import MotionFormatError
from motok.data.dataset import MotionFile
from motok.data.preprocess import PreprocessConfig, preprocess
from motok.data.root import DataRootError, resolve_data_root
from motok.features.humanml3d import feature_slices, recover_from_ric
from motok.skeleton import SkeletonError

from conftest import SLICE_PATTERN


def test_small_dataset_layout(small_dataset, bandai_slice, bandai_dir):
    ann = Annotations.load(bandai_dir / "annotations")
    split_of = ann.split_of()
    with MotionFile(small_dataset, "motion-dataset") as mf:
        assert mf.skeleton.name == "bandai21" and mf.fps == 20.0
        assert len(mf) == len(list(bandai_slice.glob("*.bvh"))) == 24
        assert mf.h5["frames/features"].shape[1] == 251
        assert mf.frame_offsets[0] == 0 and np.all(np.diff(mf.frame_offsets) > 0)
        assert mf.frame_offsets[-1] == len(mf.h5["frames/joints"]) == len(mf.h5["frames/local_quats"])
        for i, name in enumerate(mf.names):
            assert mf.splits[i] == split_of[name]
            assert len(mf.captions(i)) == 3
        # HumanML3D statistics: std is constant inside each feature block
        mean, std = mf.stats()
        assert mf.h5["stats"].attrs["split"] == "train"
        for block, sl in feature_slices(21).items():
            assert np.ptp(std[sl]) < 1e-6, block
        train = np.concatenate([mf.frames("features", i) for i in mf.split_indices("train")])
        np.testing.assert_allclose(mean, train.mean(0), atol=1e-4)
        prov = mf.provenance
        assert prov.config["clips"] == SLICE_PATTERN and len(prov.inputs) == 2 and prov.skipped == []


def test_features_recover_canonical_joints_and_frame_counts(small_dataset, bandai_slice):
    from motok.data.bvh import read_bvh
    with MotionFile(small_dataset) as mf:
        for name in mf.names[:6]:
            c = mf.clip(name)
            rec = recover_from_ric(c.features.astype(np.float64), 21)
            np.testing.assert_allclose(rec, c.joints, atol=1e-4)
            np.testing.assert_allclose(c.root_translation, c.joints[:, 0], atol=1e-6)
            src = read_bvh(bandai_slice / f"{name}.bvh")
            t20 = int(np.floor((src.num_frames - 1) * 20 / 30 + 1e-9)) + 1
            assert c.num_frames == t20 - 1  # features are frame differences
            assert abs(c.joints[..., 1].min()) < 1e-5  # on the floor
            assert c.labels == {"set": 2, "content": "walk", "style": "normal"}


def test_two_jobs_equal_one(bandai_slice, bandai_dir, small_dataset, tmp_path):
    cfg = PreprocessConfig(data=[str(bandai_slice)], annotations=str(bandai_dir / "annotations"),
                           clips=SLICE_PATTERN, skeleton="bandai21", jobs=2)
    out = tmp_path / "j2.h5"
    preprocess(cfg, out, command="test")
    with MotionFile(out) as a, MotionFile(small_dataset) as b:
        assert a.names == b.names
        for key in ("features", "joints", "local_quats"):
            np.testing.assert_array_equal(a.h5["frames"][key][()], b.h5["frames"][key][()])


def _slice_copy(src: Path, dst: Path, n: int) -> list[str]:
    dst.mkdir()
    names = sorted(p.stem for p in src.glob("*.bvh"))[:n]
    for name in names:
        (dst / f"{name}.bvh").write_bytes((src / f"{name}.bvh").read_bytes())
    return names


def _never_parse(monkeypatch):
    """Make parsing a clip fail the test: checks that come before any work must not reach it."""
    import motok.data.preprocess as pre

    def parse(*a, **k):
        raise AssertionError("a clip was parsed before the inputs were checked")
    monkeypatch.setattr(pre, "_load", parse)


def test_bad_clip_stops_or_is_skipped(bandai_slice, bandai_dir, tmp_path):
    d = tmp_path / "in"
    names = _slice_copy(bandai_slice, d, 3)
    bad = d / f"{names[1]}.bvh"
    lines = bad.read_text().splitlines()
    bad.write_text("\n".join(lines[:-5]) + "\n")  # truncated motion block
    cfg = PreprocessConfig(data=[str(d)], annotations=str(bandai_dir / "annotations"), clips=SLICE_PATTERN,
                           limit=None)
    out = tmp_path / "x.h5"
    with pytest.raises(MotionFormatError, match=names[1]):
        preprocess(PreprocessConfig(**{**cfg.__dict__, "annotations": None}), out)
    assert not out.exists()
    skip = PreprocessConfig(**{**cfg.__dict__, "annotations": None, "skip_bad": True})
    summary = preprocess(skip, out)
    assert summary["clips"] == 2 and len(summary["skipped"]) == 1
    with MotionFile(out) as mf:
        assert names[1] not in mf.names
        assert names[1] in mf.provenance.skipped[0]["input"]


def test_split_naming_missing_clip(bandai_slice, bandai_dir, tmp_path):
    d = tmp_path / "in"
    _slice_copy(bandai_slice, d, 3)
    cfg = PreprocessConfig(data=[str(d)], annotations=str(bandai_dir / "annotations"), clips=SLICE_PATTERN)
    with pytest.raises(MotionFormatError, match=r"(train|val|test)\.txt.*line \d+.*not among the inputs"):
        preprocess(cfg, tmp_path / "x.h5")


def test_clip_without_caption_file(bandai_slice, tmp_path, monkeypatch):
    """Caption files and the reference clip are checked before any clip is parsed."""
    d = tmp_path / "in"
    names = _slice_copy(bandai_slice, d, 2)
    _never_parse(monkeypatch)
    ann = tmp_path / "ann"
    (ann / "texts").mkdir(parents=True)
    (ann / "texts" / f"{names[0]}.txt").write_text("a person walks.#a/DET person/NOUN walk/VERB#0.0#0.0\n")
    (ann / "train.txt").write_text("\n".join(names) + "\n")
    cfg = PreprocessConfig(data=[str(d)], annotations=str(ann))
    with pytest.raises(MotionFormatError, match=f"{names[1]}.*no caption file"):
        preprocess(cfg, tmp_path / "x.h5")
    (ann / "texts" / f"{names[1]}.txt").write_text("a person walks.#tokens#1.0\n")
    with pytest.raises(MotionFormatError, match=r"line 1.*4 fields"):
        preprocess(cfg, tmp_path / "x.h5")
    with pytest.raises(KeyError, match="reference_clip 'nope' is not among the 2 clip"):
        preprocess(PreprocessConfig(data=[str(d)], annotations=None, reference_clip="nope"), tmp_path / "x.h5")


def test_unknown_skeleton_and_empty_archive(bandai_slice, tmp_path):
    d = tmp_path / "in"
    _slice_copy(bandai_slice, d, 1)
    with pytest.raises(SkeletonError, match="unknown skeleton 'smpl99'"):
        preprocess(PreprocessConfig(data=[str(d)], annotations=None, skeleton="smpl99"), tmp_path / "x.h5")
    empty = tmp_path / "empty.tar.gz"
    with tarfile.open(empty, "w:gz") as tar:
        info = tarfile.TarInfo("README.md")
        info.size = 5
        tar.addfile(info, io.BytesIO(b"hello"))
    with pytest.raises(MotionFormatError, match="empty.tar.gz"):
        preprocess(PreprocessConfig(data=[str(empty)], annotations=None), tmp_path / "x.h5")


def test_data_root_resolution(monkeypatch, tmp_path):
    monkeypatch.setenv("MOTOK_DATA", str(tmp_path / "nowhere"))
    with pytest.raises(DataRootError, match="BandaiNamcoResearchInc"):
        resolve_data_root()
    monkeypatch.setenv("MOTOK_DATA", str(tmp_path))
    assert resolve_data_root() == tmp_path
    assert resolve_data_root(tmp_path) == tmp_path


def test_npy_joints_through_the_whole_pipeline_match_golden_features(golden_dir, golden_features, tmp_path):
    """HumanML3D's own joints, preprocessed as a .npy input with the legacy switch, give back the
    official feature vectors (the Gaussian filter's reach from the clip end excluded)."""
    out = tmp_path / "golden.h5"
    cfg = PreprocessConfig(data=[str(golden_dir / "new_joints_012314.npy")], annotations=None,
                           skeleton="smpl22", legacy=True)
    summary = preprocess(cfg, out)
    assert summary["clips"] == 1 and summary["feature_dim"] == 263
    with MotionFile(out) as mf:
        feats = mf.frames("features", "new_joints_012314")
        assert mf.splits == ["none"] and mf.h5["stats"].attrs["split"] == "all"
    assert feats.shape == (169, 263)
    for block, sl in feature_slices(22).items():
        err = np.abs(feats[:89, sl] - golden_features[:89, sl]).max()
        assert err < 1e-4, f"{block}: {err}"


def test_split_files_are_checked_before_any_clip_is_parsed(bandai_slice, bandai_dir, tmp_path, monkeypatch):
    """The default annotations cover both sets: a set-2-only input without --clips stops at once,
    on one line naming the split file, the line and the clip, with the --clips that fits; a
    compressed archive is listed, not parsed, to know that."""
    from typer.testing import CliRunner

    from motok.cli.main import app

    tar = tmp_path / "walks.tar.xz"
    with tarfile.open(tar, "w:xz") as t:
        for p in sorted(bandai_slice.glob("*.bvh"))[:3]:
            t.add(p, arcname=f"walks/{p.name}")
    _never_parse(monkeypatch)
    for inp in (bandai_slice, tar):
        r = CliRunner().invoke(app, ["preprocess", "-d", str(inp), "--annotations", str(bandai_dir / "annotations"),
                                     "-o", str(tmp_path / "x.h5")])
        assert r.exit_code == 2 and len(r.output.strip().splitlines()) == 1, r.output
        assert re.search(r"annotations/(train|val|test)\.txt, line \d+: names clip 'dataset-1_\w+', which is not "
                         r"among the inputs", r.output), r.output
        assert "--clips 'dataset-2_walk_normal_*'" in r.output
    assert not (tmp_path / "x.h5").exists()


def test_npy_fps_is_the_rate_of_joint_arrays_and_is_said(golden_dir, tmp_path):
    """A (T, J, 3) array stores no rate: --npy-fps gives it (default 20, HumanML3D's) and a note
    says which was assumed; at 40 fps the 170 frames are 4.2 s, resampled to 85 at 20 fps."""
    import json

    from typer.testing import CliRunner

    from motok.cli.main import app

    src = golden_dir / "new_joints_012314.npy"
    r = CliRunner().invoke(app, ["preprocess", "-d", str(src), "--npy-fps", "40", "--json", "-o",
                                 str(tmp_path / "g.h5")])
    assert r.exit_code == 0, r.output
    summary = json.loads(r.stdout)
    assert summary["source_frames"] == 170 and summary["frames"] == 85 - 1
    assert "read as 40 fps (--npy-fps)" in r.stderr
    with MotionFile(tmp_path / "g.h5") as mf:
        assert mf.h5["clips/source_fps"][0] == 40.0 and mf.provenance.config["npy_fps"] == 40.0
    r = CliRunner().invoke(app, ["preprocess", "-d", str(src), "--npy-fps", "0", "-o", str(tmp_path / "h.h5")])
    assert r.exit_code == 2 and "--npy-fps 0.0 must be > 0" in r.output
