"""Your own data through `motok preprocess` (the default annotations stay with the default data
set), --skip-bad that says each bad file once and why, and writers killed mid-write whose
temporary files the next writer removes."""

from __future__ import annotations

import json
import os
import subprocess
import sys
import time

import pytest
from typer.testing import CliRunner

from motok.cli.main import app
from motok.data.dataset import MotionFile

runner = CliRunner()


@pytest.fixture(scope="module")
def my_bvh(small_dataset, tmp_path_factory):
    """A BVH of our own making: a dataset clip written out by `motok export bvh`."""
    d = tmp_path_factory.mktemp("mine")
    with MotionFile(small_dataset) as mf:
        name = mf.names[0]
    r = runner.invoke(app, ["-q", "export", "bvh", "-d", str(small_dataset), "--clip", name,
                            "-o", str(d / "my_take.bvh")])
    assert r.exit_code == 0, r.output
    return d / "my_take.bvh"


def _preprocess(*args):
    r = runner.invoke(app, ["-q", "preprocess", *map(str, args), "--json"])
    assert r.exit_code == 0, r.output
    return json.loads(r.stdout)


def test_own_bvh_gets_no_captions_and_split_none_unless_annotations_are_given(my_bvh, tmp_path):
    s = _preprocess("-d", my_bvh, "-o", tmp_path / "mine.h5")
    assert s["clips"] == 1 and s["annotations"] is None and s["splits"]["none"] == 1
    with MotionFile(tmp_path / "mine.h5", "motion-dataset") as mf:
        assert mf.names == ["my_take"] and mf.captions(0) == [] and mf.h5["stats"].attrs["split"] == "all"
    ann = tmp_path / "ann"
    (ann / "texts").mkdir(parents=True)
    (ann / "texts" / "my_take.txt").write_text("a person walks.#a/DET person/NOUN walk/VERB#0.0#0.0\n")
    (ann / "train.txt").write_text("my_take\n")
    s = _preprocess("-d", my_bvh, "--annotations", ann, "-o", tmp_path / "captioned.h5")
    assert s["splits"]["train"] == 1 and s["annotations"] == str(ann)
    with MotionFile(tmp_path / "captioned.h5") as mf:
        assert [c[0] for c in mf.captions(0)] == ["a person walks."]
    r = runner.invoke(app, ["preprocess", "--help"], terminal_width=200)
    assert "Bandai-Namco archives only" in r.stdout and "split 'none'" in r.stdout


def test_the_default_annotations_follow_the_default_data_set(bandai_slice, bandai_dir, tmp_path):
    """Inputs inside DATA/bandai-namco/ get DATA/bandai-namco/annotations; the same files elsewhere do not."""
    import shutil
    root = tmp_path / "DATA"
    takes = root / "bandai-namco" / "takes"
    takes.mkdir(parents=True)
    shutil.copytree(bandai_dir / "annotations", root / "bandai-namco" / "annotations")
    for p in sorted(bandai_slice.glob("*.bvh"))[:2]:
        shutil.copy(p, takes / p.name)
    common = ["--limit", "2", "--data-root", root]  # --limit: the splits name clips that are not here
    s = _preprocess("-d", "bandai-namco/takes", *common, "-o", tmp_path / "bandai.h5")
    assert s["annotations"] == str(root / "bandai-namco" / "annotations") and s["splits"]["none"] == 0
    shutil.copytree(takes, tmp_path / "copies")
    s = _preprocess("-d", tmp_path / "copies", *common, "-o", tmp_path / "copies.h5")
    assert s["annotations"] is None and s["splits"]["none"] == 2
    s = _preprocess("-d", "bandai-namco/takes", *common, "--annotations", "none", "-o", tmp_path / "bare.h5")
    assert s["annotations"] is None


@pytest.fixture
def mixed(my_bvh, golden_dir, tmp_path):
    """A folder of one good take and one bad file of each kind."""
    d = tmp_path / "mixed"
    d.mkdir()
    text = my_bvh.read_text()
    (d / "good.bvh").write_text(text)
    (d / "junk.bvh").write_text("not a BVH\n")
    (d / "still.bvh").write_text(text.split("MOTION")[0] + "MOTION\nFrames: 0\nFrame Time: 0.05\n")
    (d / "trunc.bvh").write_text("\n".join(text.splitlines()[:-20]) + "\n")
    (d / "zz_other_skeleton.npy").write_bytes((golden_dir / "new_joints_012314.npy").read_bytes())
    (d / "bad.npy").write_bytes(b"\x93NUMPY garbage")
    return d


def test_skip_bad_names_each_file_once_with_its_reason(mixed, tmp_path):
    s = _preprocess("-d", mixed, "--skip-bad", "-o", tmp_path / "x.h5")
    assert s["clips"] == 1
    skipped = {os.path.basename(e["input"]): e["error"] for e in s["skipped"]}
    assert sorted(skipped) == ["bad.npy", "junk.bvh", "still.bvh", "trunc.bvh", "zz_other_skeleton.npy"]
    for e in s["skipped"]:
        line = f"{e['input']}: {e['error']}"
        assert line.count(os.path.basename(e["input"])) == 1 and "?" not in e["input"], line
    assert "Frames: 0" in skipped["still.bvh"] and "22 joints" in skipped["zz_other_skeleton.npy"]
    with MotionFile(tmp_path / "x.h5") as mf:
        assert mf.provenance.skipped == s["skipped"]


def test_when_everything_is_skipped_the_first_cause_is_kept(mixed, tmp_path):
    for p in ("good.bvh", "zz_other_skeleton.npy"):
        (mixed / p).unlink()
    r = runner.invoke(app, ["preprocess", "-d", str(mixed), "--skip-bad", "-o", str(tmp_path / "x.h5")])
    assert r.exit_code == 2 and len(r.output.strip().splitlines()) == 1, r.output
    assert "all 4 clip(s) matching '*' were bad" in r.output and "bad.npy: not a readable .npy array" in r.output
    assert not (tmp_path / "x.h5").exists()


WRITER = """
import sys, time
from motok.atomic import atomic_path
with atomic_path(sys.argv[1]) as tmp:
    tmp.write_bytes(b"half")
    print(tmp, flush=True)
    time.sleep(60)
"""


def _writer(target):
    p = subprocess.Popen([sys.executable, "-c", WRITER, str(target)], stdout=subprocess.PIPE, text=True)
    return p, p.stdout.readline().strip()


def test_temporary_files_of_killed_writers_are_removed_by_the_next_writer(tmp_path):
    from pathlib import Path

    from motok.atomic import atomic_path, temp_name
    target = tmp_path / "walk.h5"
    target.write_bytes(b"old")
    alive, alive_tmp = _writer(target)
    dead, dead_tmp = _writer(target)
    try:
        dead.kill()  # SIGKILL: no finally block runs
        dead.wait()
        assert Path(dead_tmp).exists() and target.read_bytes() == b"old"
        # The name is what docs/artifacts.md says: .STEM.HOST.PID.RANDOM.partSUFFIX
        assert Path(dead_tmp).name.startswith(".walk.") and Path(dead_tmp).name.endswith(".part.h5")
        assert Path(dead_tmp).name.split(".")[3] == str(dead.pid)
        assert temp_name(target).split(".")[2] == Path(dead_tmp).name.split(".")[2]  # this host
        with atomic_path(target) as tmp:
            tmp.write_bytes(b"new")
        assert target.read_bytes() == b"new"
        assert not Path(dead_tmp).exists()  # the dead writer's leftover is gone
        assert Path(alive_tmp).exists()  # a running writer's file is left alone
    finally:
        alive.kill()
        alive.wait()
    time.sleep(0.05)
    (tmp_path / "other.h5").write_bytes(b"x")
    with atomic_path(tmp_path / "other.h5") as tmp:  # another target's writer leaves walk.h5's files alone
        tmp.write_bytes(b"y")
    assert Path(alive_tmp).exists()
    with atomic_path(target) as tmp:
        tmp.write_bytes(b"newer")
    assert sorted(p.name for p in tmp_path.iterdir()) == ["other.h5", "walk.h5"]
