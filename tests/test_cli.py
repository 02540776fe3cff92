"""The command line, driven as a user would: info, render, export, errors."""

from __future__ import annotations

import json

import numpy as np
from typer.testing import CliRunner

from motok import __version__
from motok.cli.main import app
from motok.data.bvh import read_bvh
from motok.data.dataset import MotionFile

runner = CliRunner()


def test_version_and_help():
    r = runner.invoke(app, ["--version"])
    assert r.exit_code == 0 and __version__ in r.output
    r = runner.invoke(app, ["--help"])
    assert r.exit_code == 0 and "preprocess" in r.output and "export" in r.output


def test_info_json(small_dataset):
    r = runner.invoke(app, ["info", str(small_dataset), "--json"])
    assert r.exit_code == 0, r.output
    d = json.loads(r.output)
    assert d["kind"] == "motion-dataset" and d["schema_version"] == 1 and d["clips"] == 24
    assert d["datasets"]["frames/features"]["shape"][1] == 251
    assert sum(d["splits"].values()) == 24 and d["captions"]
    assert d["provenance"]["machine"]["packages"]["numpy"] == np.__version__
    r = runner.invoke(app, ["info", str(small_dataset)])  # the plain print names the machine in one line
    assert r.exit_code == 0 and f"numpy {np.__version__} (" in r.output, r.output


def test_render_and_export(small_dataset, tmp_path):
    with MotionFile(small_dataset) as mf:
        name = mf.names[0]
        joints = mf.clip(name).joints
    gif = tmp_path / "a.gif"
    r = runner.invoke(app, ["--quiet", "render", str(small_dataset), "--clip", name, "-o", str(gif),
                            "--max-frames", "20"])
    assert r.exit_code == 0, r.output
    assert gif.stat().st_size > 1000
    for order in ("ZXY", "XYZ"):
        bvh = tmp_path / f"a_{order}.bvh"
        r = runner.invoke(app, ["export", "bvh", str(small_dataset), "--clip", name, "-o", str(bvh), "--order", order])
        assert r.exit_code == 0, r.output
        back = read_bvh(bvh)
        assert back.num_frames == len(joints) and abs(back.fps - 20.0) < 1e-3
        pos = back.global_positions() * 0.01
        err = np.linalg.norm(pos - joints, axis=-1).max()
        assert err < 1e-3, f"{order}: {err * 1000:.3f} mm"


def test_errors_are_one_clear_line(small_dataset, tmp_path):
    r = runner.invoke(app, ["render", str(small_dataset), "--clip", "no-such-clip", "-o", str(tmp_path / "a.gif")])
    assert r.exit_code == 2 and "no clip named 'no-such-clip'" in r.output
    r = runner.invoke(app, ["info", str(tmp_path / "missing.h5")])
    assert r.exit_code == 2 and "no such file" in r.output
    r = runner.invoke(app, ["preprocess", "-o", str(tmp_path / "x.h5"), "--set", "bogus=1"])
    assert r.exit_code == 2 and "bogus" in r.output
