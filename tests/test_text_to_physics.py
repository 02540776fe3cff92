"""Text -> kinematic motion -> simulated motion in one step (motok.control.text_to_physics,
`motok gpt sample --prior PRIOR` / `--expert RUN`), on the tiny GPT of tiny_runs.py and an
untrained (2-iteration) hybrid prior: what is checked is the plumbing (the kinematic motion is
the GPT's, the output is the tracking of it, every reader takes both files, failures are one
line), not how well an untrained prior walks."""

from __future__ import annotations

import json

import numpy as np
import pytest
from typer.testing import CliRunner

from motok.data.dataset import MotionFile
from motok.errors import UserError
from motok.eval.metrics import mpjpe
import tiny_runs

tree = tiny_runs.tree  # the tiny tokenizer + GPT (a module fixture)

pytestmark = pytest.mark.usefixtures("one_thread")

TEXTS = ["a person walks forward", "someone waves"]
SAMPLING = dict(num_samples=1, seed=3, seconds=1.6)  # 8 tokens at rate 4: 32 frames at 20 fps


cache, controllers = tiny_runs.cache, tiny_runs.controllers  # the reference cache; (prior, expert)


@pytest.fixture(scope="module")
def simulated(tree, controllers, tmp_path_factory):
    """One library call: two texts, tracked by the prior, rendered and exported."""
    from motok.control.text_to_physics import text_to_physics

    out = tmp_path_factory.mktemp("t2p") / "walk_sim.h5"
    res = text_to_physics(tree / "gpt", TEXTS, out, prior=controllers[0], render=out.with_suffix(".gif"),
                          bvh=out.with_suffix(".bvh"), **SAMPLING)
    return out, res


def test_the_kinematic_motion_is_the_gpts_and_the_output_its_tracking(tree, simulated):
    from motok.gpt.sample import sample

    out, res = simulated
    kin = out.with_name("walk_sim.kinematic.h5")
    assert res["output"] == str(out) and res["kinematic"] == str(kin) and res["controller_kind"] == "control-prior"
    plain = out.with_name("plain.h5")
    sample(tree / "gpt", TEXTS, plain, **SAMPLING)
    with MotionFile(kin, "motion") as k, MotionFile(plain, "motion") as p:
        assert list(k.names) == list(p.names) and len(k) == 2
        for n in k.names:  # exactly what `gpt sample` makes with the same options
            assert np.array_equal(k.clip(n).joints, p.clip(n).joints)
        names, fps = list(k.names), k.fps
        kinematic = {n: k.clip(n) for n in names}
    per = res["per_clip"]
    assert list(per) == names and [per[n]["text"] for n in names] == TEXTS
    with MotionFile(out, "motion") as sim:
        assert sim.fps == fps and set(sim.names) <= set(names) and len(sim) == res["written"] >= 1
        assert sim.provenance.config["motion"] == str(kin)  # tracked from the kinematic file
        for n in sim.names:
            r, s, g = per[n], sim.clip(n), kinematic[n]
            assert r["tokens"] == 8 and r["kinematic_seconds"] == 1.6
            assert isinstance(r["tracked_to_end"], bool) and r["seconds"] <= r["clip_seconds"] + 1e-6
            assert r["failed_at_s"] == (None if r["tracked_to_end"] else r["seconds"])
            assert np.isfinite([r["mpjpe_mm"], r["g_mpjpe_mm"]]).all() and r["g_mpjpe_mm"] > 0
            # The simulated part only, and not the kinematic joints copied: close to the error the
            # tracking measured against the (placed) kinematic motion, root-relative both.
            assert abs(s.num_frames - r["seconds"] * fps) <= 2 and s.captions[0][0] == r["text"]
            m = min(s.num_frames, g.num_frames)
            err = float(mpjpe(s.joints[:m], g.joints[:m]).mean())
            assert err > 1.0 and 0.5 * r["mpjpe_mm"] < err < 1.5 * r["mpjpe_mm"] + 10.0, (err, r["mpjpe_mm"])
    assert res["tracked_to_end"] == np.mean([per[n]["tracked_to_end"] for n in names])
    assert "video" in res and out.with_suffix(".gif").stat().st_size > 0
    assert len(res["bvh"]) == res["written"] and all(open(b).read(9) == "HIERARCHY" for b in res["bvh"])
    json.dumps(res)  # results are plain JSON


def test_both_files_round_trip_through_info_render_and_export(simulated, tmp_path):
    from motok.cli.main import app

    out, res = simulated
    runner = CliRunner()
    with MotionFile(out, "motion") as mf:
        name = mf.names[0]
    for i, path in enumerate([out, out.with_name("walk_sim.kinematic.h5")]):
        for args in (["info", str(path)],
                     ["render", "-d", str(path), "--clip", name, "-o", str(tmp_path / f"{i}.gif")],
                     ["export", "bvh", "-d", str(path), "--clip", name, "-o", str(tmp_path / f"{i}.bvh")]):
            r = runner.invoke(app, ["--quiet", *args])
            assert r.exit_code == 0, (args, r.output)
        assert (tmp_path / f"{i}.gif").stat().st_size > 0 and (tmp_path / f"{i}.bvh").stat().st_size > 1000


def test_the_command_reports_every_clip(tree, controllers, tmp_path):
    from motok.cli.main import app

    runner = CliRunner()
    base = ["--quiet", "gpt", "sample", "-g", str(tree / "gpt"), "--text", TEXTS[0], "-n", "2", "--seconds", "1.6"]
    r = runner.invoke(app, base + ["--expert", str(controllers[1]), "-o", str(tmp_path / "e.h5"), "--json"])
    assert r.exit_code == 0, r.output
    res = json.loads(r.stdout)
    assert res["controller_kind"] == "control-expert" and res["clips"] == 2 and len(res["per_clip"]) == 2
    assert (tmp_path / "e.kinematic.h5").exists() and (tmp_path / "e.h5").exists()
    r = runner.invoke(app, base + ["--prior", str(controllers[0]), "--codebooks", "2", "-o", str(tmp_path / "p.h5")])
    assert r.exit_code == 0, r.output
    with MotionFile(tmp_path / "p.kinematic.h5") as mf:
        names = list(mf.names)
    for n in names:  # one line per clip: how far it was tracked and its errors
        line = next(ln for ln in r.stdout.splitlines() if ln.startswith(f"{n}:"))
        assert ("tracked to the end" in line or "failed at" in line) and "G-MPJPE" in line
    assert f"wrote {tmp_path / 'p.h5'}" in r.stdout and "p.kinematic.h5 (the kinematic motion)" in r.stdout


@pytest.mark.parametrize("extra,message", [
    (["--prior", "{gpt}"], "--prior {gpt}: expected a control-prior bundle"),
    (["--prior", "{expert}"], "found kind 'control-expert'; pass it with --expert"),
    (["--expert", "{prior}"], "--expert {prior}: expected a control-expert bundle"),
    (["--prior", "{prior}", "--expert", "{expert}"], "not both"),
    (["--prior", "{prior}", "--codebooks", "9"], "--codebooks must be in 1..4"),
    (["--codebooks", "2"], "--codebooks goes with --prior"),
    (["--prior", "{prior}", "--render", "{tmp}/v.png"], "unknown suffix '.png'"),
])
def test_wrong_controllers_fail_in_one_line_before_any_work(tree, controllers, tmp_path, extra, message):
    from motok.cli.main import app

    paths = dict(gpt=tree / "gpt", prior=controllers[0], expert=controllers[1], tmp=tmp_path)
    args = ["gpt", "sample", "-g", str(tree / "gpt"), "--text", TEXTS[0], "-o", str(tmp_path / "x.h5"),
            *[a.format(**paths) for a in extra]]
    r = CliRunner().invoke(app, args)
    assert r.exit_code == 2, r.output
    err = r.stderr.strip()
    assert err.startswith("error:") and len(err.splitlines()) == 1 and message.format(**paths) in err, err
    assert not (tmp_path / "x.h5").exists() and not (tmp_path / "x.kinematic.h5").exists()


def test_the_library_refuses_a_missing_controller(tree, tmp_path):
    from motok.control.text_to_physics import kinematic_path, text_to_physics

    with pytest.raises(UserError, match="--prior PRIOR or --expert RUN"):
        text_to_physics(tree / "gpt", TEXTS, tmp_path / "x.h5")
    assert kinematic_path("runs/a/walk.h5").as_posix() == "runs/a/walk.kinematic.h5"
