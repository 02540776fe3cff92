"""An existing output file that motok did not write is never replaced, whatever its type; one
motok wrote is replaced (atomically). How motok knows its own: motok.cli.output_files.OWN."""

from __future__ import annotations

import numpy as np
from typer.testing import CliRunner

from motok.cli.main import app
from motok.cli.output_files import foreign_file
from motok.marks import MD_MARK

runner = CliRunner()
FRAMES = [np.full((16, 16, 3), v, dtype=np.uint8) for v in (0, 128, 255)]


def _ours(tmp_path):
    """One file of each type, written by motok's own writers."""
    from motok.atomic import write_json
    from motok.eval.motion_matching import save as save_mm
    from motok.render.plot import plot_curves
    from motok.render.video import write_video
    out = {}
    for suffix in (".gif", ".mp4"):
        out[suffix] = write_video(FRAMES, tmp_path / f"ours{suffix}", fps=10)
    out[".png"] = plot_curves([{"step": 0, "loss": 1.0}, {"step": 1, "loss": 0.5}], tmp_path / "ours.png", x="step")
    out[".json"] = write_json(tmp_path / "ours.json", {"kind": "control-expert-eval", "schema_version": 1})
    rep = {"rows": [], "threshold": 1.0, "percentile": 5, "clips": 0, "split": "test"}
    try:
        save_mm(rep, [tmp_path / "ours.md"])
    except (KeyError, TypeError):  # a report without rows the table needs: write the mark the same way
        (tmp_path / "ours.md").write_text(MD_MARK + "\n| a |\n")
    out[".md"] = tmp_path / "ours.md"
    return out


def test_every_output_type_tells_motoks_files_from_foreign_ones(hum_path, tmp_path):
    for suffix, path in {**_ours(tmp_path), ".xml": hum_path}.items():
        assert foreign_file(path) is None, (suffix, path.read_bytes()[:200])
        foreign = tmp_path / f"foreign{suffix}"
        foreign.write_bytes(b'{"title": "my notes"}\n' if suffix == ".json" else b"# my notes\n")
        why = foreign_file(foreign)
        assert why and str(foreign) in why and "not even with --force" in why and "\n" not in why, why
    bvh = tmp_path / "walk.bvh"  # a BVH has no room for a mark: an existing one is never replaced
    bvh.write_text("HIERARCHY\n")
    assert "BVH has no room" in foreign_file(bvh)
    assert foreign_file(tmp_path / "absent.gif") is None  # a new file is no one's


def test_commands_refuse_a_foreign_video_picture_bvh_and_report_in_one_line(small_dataset, tmp_path):
    cases = [["render", "-d", str(small_dataset), "--clip", "0", "-o"],
             ["export", "bvh", "-d", str(small_dataset), "--clip", "0", "-o"]]
    for args, name in [(cases[0], "x.gif"), (cases[0], "x.mp4"), (cases[0], "x.png"), (cases[1], "x.bvh")]:
        foreign = tmp_path / name
        foreign.write_bytes(b"somebody's file")
        r = runner.invoke(app, ["-q", *args, str(foreign)])
        assert r.exit_code == 2 and str(foreign) in r.output, r.output
        assert len(r.output.strip().splitlines()) == 1 and foreign.read_bytes() == b"somebody's file", r.output
    # motok's own video and picture are replaced, run after run
    for name in ("ours.gif", "ours.png"):
        for _ in range(2):
            r = runner.invoke(app, ["-q", *cases[0], str(tmp_path / name)])
            assert r.exit_code == 0, r.output


def test_the_reports_written_beside_an_output_are_checked_too(tmp_path):
    import pytest

    from motok.cli.output_files import refuse_foreign
    from motok.control.track import report_path
    from motok.errors import UserError
    beside = report_path(tmp_path / "walk_sim.h5")  # control track's walk_sim.track.json
    beside.write_text('{"mine": true}\n')
    with pytest.raises(UserError, match=f"^-o {beside} exists and is not a motok report"):
        refuse_foreign(beside, "-o")
    beside.write_text('{"kind": "control-track", "schema_version": 1}\n')
    refuse_foreign(beside, "-o")  # motok's own report: replaced


def test_plot_without_out_checks_its_default_output_as_it_checks_out(tmp_path):
    run = tmp_path / "run"
    run.mkdir()
    (run / "metrics.jsonl").write_text('{"iteration": 1, "loss": 1.0}\n{"iteration": 2, "loss": 0.5}\n')
    curves = run / "curves.png"
    curves.write_bytes(b"somebody's picture")  # not motok's: refused before any drawing, in one line
    r = runner.invoke(app, ["-q", "plot", str(run)])
    assert r.exit_code == 2 and f"{curves} exists and is not a PNG that motok wrote" in r.output, r.output
    assert len(r.output.strip().splitlines()) == 1 and curves.read_bytes() == b"somebody's picture"
    curves.unlink()
    for _ in range(2):  # motok's own picture is replaced, run after run, and no lock is left behind
        r = runner.invoke(app, ["-q", "plot", str(run)])
        assert r.exit_code == 0 and foreign_file(curves) is None, r.output
    assert sorted(p.name for p in run.iterdir()) == ["curves.png", "metrics.jsonl"]
    r = runner.invoke(app, ["-q", "plot", str(tmp_path)])  # a folder that is no run: said, nothing written
    assert r.exit_code == 2 and "not a run folder (it has no metrics.jsonl)" in r.output, r.output
    assert not (tmp_path / "curves.png").exists()
    (tmp_path / "busy").mkdir()
    (tmp_path / "busy" / "metrics.jsonl").write_text('{"iteration": 1, "loss": 1.0}\n')
    (tmp_path / "busy" / "curves.png").mkdir()  # the default output is a folder
    r = runner.invoke(app, ["-q", "plot", str(tmp_path / "busy")])
    assert r.exit_code == 2 and "is a folder" in r.output, r.output
