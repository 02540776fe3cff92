"""Text to physics in a closed loop (motok.control.closed_loop, `motok gpt sample --prior PRIOR
--closed-loop`), on the tiny GPT of tiny_runs.py (0.2-s tokens, 23 positions) and an untrained
hybrid prior: what is checked is the loop (what the GPT is conditioned on, where a plan starts,
when the prompt changes, that nothing changes without re-plans, the files and their readers,
the one-line refusals), not how well an untrained prior walks."""

from __future__ import annotations

import copy
import json
import math

import numpy as np
import pytest
import torch
from typer.testing import CliRunner

from motok.data.dataset import MotionFile
import tiny_runs

tree, cache, controllers = tiny_runs.tree, tiny_runs.cache, tiny_runs.controllers

pytestmark = pytest.mark.usefixtures("one_thread")

TEXTS = ["a person walks forward", "someone waves"]
SAMPLING = dict(num_samples=1, seed=3, seconds=1.6)  # 8 tokens at rate 4: 32 frames at 20 fps


@pytest.fixture(scope="module")
def steady(tree, controllers):
    """``(planner, controller)``: the tiny GPT ready to plan and the prior with its failure test off,
    so the character plays every re-plan however badly it tracks."""
    from motok.control.closed_loop.loop import clock_of, load_planner
    from motok.control.text_to_physics import load_physics_controller

    ctrl = load_physics_controller(controllers[0])
    ctrl.cfg = copy.deepcopy(ctrl.cfg)
    ctrl.cfg.task.early_termination = False
    clock = clock_of(tree / "gpt")
    planner = load_planner(tree / "gpt", TEXTS, clock)
    return planner, ctrl


def encode_window(planner, pos_mj: np.ndarray) -> np.ndarray:
    """The tokenizer's encoding of simulated positions (MuJoCo frame, 30 Hz), written out here as
    the data's pipeline: to the data frame, to 20 fps, features, tokens."""
    from motok.features.humanml3d import extract_features
    from motok.features.resample import resample_positions

    pos = resample_positions(pos_mj[..., [1, 2, 0]], 30.0, 20.0)
    f = extract_features(pos, planner.skeleton, target_offsets=planner.offsets, fps=20.0, legacy=planner.legacy)
    return planner.tokenizer.encode_features(torch.from_numpy(f.features)[None], 1)[0, :, 0].numpy()


def test_without_replans_the_loop_is_the_open_loop_to_the_bit(tree, controllers, small_dataset, tmp_path, script):
    """No --replan-every, no --then, a motion the GPT holds whole: the closed loop's first plans are
    `gpt sample`'s samples and their tracking is `gpt sample --prior`'s, to the bit; and made again
    from the open loop's kinematic file (--data: texts, lengths and seeds from its labels) too."""
    from motok.control.closed_loop.loop import closed_loop
    from motok.control.text_to_physics import text_to_physics

    text_to_physics(tree / "gpt", TEXTS, tmp_path / "open.h5", prior=controllers[0], **SAMPLING)
    rep = closed_loop(tree / "gpt", tmp_path / "closed.h5", texts=TEXTS, prior=controllers[0], replan_every=None,
                      **SAMPLING)
    again = closed_loop(tree / "gpt", tmp_path / "again.h5", data=tmp_path / "open.kinematic.h5",
                        prior=controllers[0], replan_every=None)
    assert rep["replans"] == again["replans"] == 0 and rep["replans_changed"] is None
    with MotionFile(tmp_path / "open.h5") as o, MotionFile(tmp_path / "open.kinematic.h5") as k:
        names = list(o.names)
        opened = {n: o.clip(n) for n in names}
        codes = {n: k.clip(n).labels["codes"] for n in k.names}
    for path in ("closed.h5", "again.h5"):
        with MotionFile(tmp_path / path) as c, MotionFile(tmp_path / path.replace(".h5", ".plans.h5")) as p:
            assert list(c.names) == names
            for n in names:
                a, b = opened[n], c.clip(n)
                for key in ("features", "joints", "local_quats", "root_translation"):
                    assert np.array_equal(getattr(a, key), getattr(b, key)), (path, n, key)
                assert b.labels["tracked_to_end"] == a.labels["tracked_to_end"] and b.labels["replans_s"] == []
                assert p.clip(f"{n}.plan00").labels["codes"] == codes[n]  # the first plan is the sample
    for n in names:
        assert rep["per_clip"][n]["mpjpe_mm"] == again["per_clip"][n]["mpjpe_mm"]
    # scripts/track_failures.py reads the report of a generated set made again (none of these has a source clip)
    report = json.loads((tmp_path / "again.closed-loop.json").read_text())
    assert report["provenance"]["config"]["data"] == str(tmp_path / "open.kinematic.h5")
    assert script("track_failures").content_of(report, small_dataset, "train") == {}


def test_clips_of_a_generated_set_keep_their_seeds(tree, controllers, tmp_path):
    """--clips makes a chosen part of a generated set again: the second clip alone, without re-plans,
    draws the open loop's plan (its seed is its index in the file, not in the subset) and is
    simulated as there (to float rounding); a glob matching nothing, and --clips without --data, are
    refused before any work."""
    from motok.control.closed_loop.loop import check_options, closed_loop
    from motok.control.text_to_physics import text_to_physics
    from motok.errors import UserError

    text_to_physics(tree / "gpt", TEXTS, tmp_path / "open.h5", prior=controllers[0], **SAMPLING)
    with MotionFile(tmp_path / "open.kinematic.h5") as k:
        names = list(k.names)
    assert len(names) == 2
    closed_loop(tree / "gpt", tmp_path / "one.h5", data=tmp_path / "open.kinematic.h5", clips=names[1],
                prior=controllers[0], replan_every=None)
    with MotionFile(tmp_path / "open.kinematic.h5") as k, MotionFile(tmp_path / "one.plans.h5") as p, \
            MotionFile(tmp_path / "open.h5") as o, MotionFile(tmp_path / "one.h5") as c:
        assert list(c.names) == [names[1]]
        assert p.clip(f"{names[1]}.plan00").labels["codes"] == k.clip(names[1]).labels["codes"]  # the same draw
        a, b = o.clip(names[1]), c.clip(names[1])
        # simulated alone rather than beside another clip: the policy's batched matmuls may round otherwise
        assert a.labels["tracked_to_end"] == b.labels["tracked_to_end"]
        assert np.allclose(a.joints, b.joints, atol=1e-5)
    with pytest.raises(UserError, match="matches 'nothing-\\*'"):
        closed_loop(tree / "gpt", tmp_path / "none.h5", data=tmp_path / "open.kinematic.h5", clips="nothing-*",
                    prior=controllers[0], replan_every=None)
    assert not (tmp_path / "none.h5").exists()
    with pytest.raises(UserError, match="--clips chooses clips of --data"):
        check_options(texts=TEXTS, then=[], data=None, replan_every=None, closed_loop=True, simulated=True,
                      clips="gen-*")


def test_a_pushed_character_is_where_the_next_plan_starts(steady):
    """The character is displaced 0.8 m and turned 90 degrees half a second in; the re-plan at 0.8 s
    conditions the GPT on the tokenizer's encoding of the simulated window (the push in it), and
    the new plan starts at the pushed root and heading, far from where the old plan had got to;
    the physics goes on from its state (no reset at the re-plan)."""
    from motok.control.closed_loop.loop import run
    from motok.control.closed_loop.timeline import timeline_rows
    from motok.sim.humanoid import from_mj
    from motok.control.closed_loop.replan import heading

    planner, ctrl = steady
    clock = replace_hz(planner.clock, ctrl)
    rows = timeline_rows([TEXTS[0]], [], clock, 1.6, 1, 3)
    turn = np.array([math.cos(math.pi / 4), 0.0, 0.0, math.sin(math.pi / 4)])  # 90 degrees about +z (up)

    def push(steps, env):
        if steps == 15:
            q, v = env.qpos.copy(), env.qvel.copy()
            q[0, 0] += 0.8
            w, x, y, z = q[0, 3:7]
            a, b, c, d = turn
            q[0, 3:7] = [a * w - d * z, a * x - d * y, a * y + d * x, a * z + d * w]  # turn * root
            env.set_state(np.array([0]), q, v)

    (loop, res, _), = run(planner, ctrl, rows, every=4, push=push)
    plans = loop.plans[0]
    assert [p.start for p in plans] == [0, 4] and [p.reason for p in plans] == ["start", "every"]
    old, new = plans
    pos = np.stack(loop.pos)[:, 0]  # (steps + 1, J, 3), MuJoCo frame
    s = 4 * clock.steps_per_token
    assert new.context == encode_window(planner, pos[:s + 1]).tolist() and len(new.context) == 4
    sk = planner.skeleton
    now = from_mj(pos[s])
    assert np.allclose(new.joints[0, 0, [0, 2]], now[0, [0, 2]], atol=1e-6)
    assert abs(math.remainder(heading(new.joints[0], sk) - heading(now, sk), 2 * math.pi)) < 1e-6
    was = old.joints[4 * clock.rate]  # where the old plan had the character at 0.8 s
    assert np.linalg.norm(was[0, [0, 2]] - now[0, [0, 2]]) > 0.5 and new.info["root_shift_mm"] > 500
    assert new.info["change_mm"] > 100
    steps = np.linalg.norm(np.diff(pos[:, 0], axis=0), axis=-1)  # root motion per control step
    assert steps[s] < 0.1 and steps[15] > 0.5  # the push moved it; the re-plan did not


def replace_hz(clock, ctrl):
    from dataclasses import replace

    return replace(clock, control_hz=float(ctrl.cfg.env.control_hz or ctrl.humanoid.control_hz))


def test_a_timeline_switches_the_condition_at_its_time(steady, monkeypatch):
    """Two prompts, the second at 0.8 s: the first plan is conditioned on the first text alone, the
    plan made at 0.8 s on the second text's embedding and on the simulated motion's 4 tokens."""
    import motok.gpt.sample as gs
    from motok.control.closed_loop.loop import run
    from motok.control.closed_loop.timeline import timeline_rows

    planner, ctrl = steady
    clock = replace_hz(planner.clock, ctrl)
    rows = timeline_rows([TEXTS[0]], [(0.8, TEXTS[1])], clock, 1.6, 1, 3)
    assert rows[0].prompts == [(0, TEXTS[0]), (4, TEXTS[1])]
    assert rows[0].captions == [(TEXTS[0], "", 0.0, 0.8), (TEXTS[1], "", 0.8, 1.6)]
    calls, generate = [], gs.generate

    def spy(model, text, **kw):
        calls.append((text.clone(), None if kw.get("prefix") is None else kw["prefix"].clone()))
        return generate(model, text, **kw)

    monkeypatch.setattr(gs, "generate", spy)
    (loop, _, _), = run(planner, ctrl, rows, every=None)
    plans = loop.plans[0]
    assert [(p.start, p.text, p.reason) for p in plans] == [(0, TEXTS[0], "start"), (4, TEXTS[1], "prompt")]
    assert len(calls) == 2
    (t0, p0), (t1, p1) = calls
    assert torch.equal(t0[0], planner.embeddings[TEXTS[0]]) and p0 is None
    assert torch.equal(t1[0], planner.embeddings[TEXTS[1]]) and p1[0].tolist() == plans[1].context
    assert not torch.equal(planner.embeddings[TEXTS[0]], planner.embeddings[TEXTS[1]])
    assert plans[1].end == 8 and len(plans[1].codes) == 4  # continued to the motion's length


def test_the_command_writes_the_loop_and_eval_reads_it(tree, controllers, tmp_path):
    """`gpt sample --closed-loop` with a timeline: the simulated motion, the reference it was given,
    every plan, the report with each re-plan, the video; the simulated file reads as an
    evaluation row (`eval t2m --motions`), with its labels."""
    from motok.cli.main import app
    from motok.eval.sets import motion_set

    out = tmp_path / "walk_sim.h5"
    r = CliRunner().invoke(app, ["--quiet", "gpt", "sample", "-g", str(tree / "gpt"), "--text", TEXTS[0],
                                 "--then", f"0.4s {TEXTS[1]}", "--seconds", "1.6", "--prior", str(controllers[0]),
                                 "--closed-loop", "--replan-every", "0.2", "-o", str(out),
                                 "--render", str(tmp_path / "walk_sim.gif"), "--json"])
    assert r.exit_code == 0, r.output
    res = json.loads(r.stdout)
    report = json.loads((tmp_path / "walk_sim.closed-loop.json").read_text())
    assert report["kind"] == "closed-loop" and report["replan_every_s"] == 0.2 and res["clips"] == 1
    (name, clip), = report["per_clip"].items()
    reasons = [(x["at_s"], x["reason"], x["text"]) for x in clip["replans"]]
    played = clip["seconds"]  # the untrained prior falls within a second; it gets past the switch
    want = [(round(0.2 * k, 4), "prompt" if k == 2 else "every", TEXTS[0] if k < 2 else TEXTS[1]) for k in range(1, 8)]
    assert played > 0.5 and reasons == [w for w in want if w[0] < played - 1e-9]  # a fallen character re-plans no more
    for x in clip["replans"]:
        assert len(x["context"]) == round(x["at_s"] / 0.2) and len(x["codes"]) == 8 - len(x["context"])
        assert {"change_mm", "pose_change_mm", "root_shift_mm", "sim_root_m", "sim_heading_deg"} <= set(x)
    assert report["replans"] == len(reasons) and "video" in report and (tmp_path / "walk_sim.gif").stat().st_size
    with MotionFile(out) as sim, MotionFile(tmp_path / "walk_sim.kinematic.h5") as kin, \
            MotionFile(tmp_path / "walk_sim.plans.h5") as plans:
        lab = sim.clip(name).labels
        assert lab["replans_s"] == [w[0] for w in reasons] and lab["prompts"] == [[0.0, TEXTS[0]], [0.4, TEXTS[1]]]
        assert sim.clip(name).captions == [(TEXTS[0], "", 0.0, 0.4), (TEXTS[1], "", 0.4, 1.6)]
        assert list(kin.names) == [name] and kin.clip(name).num_frames == 31  # 1.6 s of reference, per transition
        assert list(plans.names) == [f"{name}.plan{k:02d}" for k in range(len(reasons) + 1)]
    ms = motion_set(out, tracked_to_end=False)
    assert ms.names == [name] and ms.captions[0] == [TEXTS[0], TEXTS[1]]


@pytest.mark.parametrize("extra,message", [
    (["--then", "0.8s b", "--then", "0.4s c"], "--then '0.4s c': expected times that increase"),
    (["--then", "2s b"], "--then 2s: expected a time before the end of the motion (1.6 s"),
    (["--then", "0.5s b"], "--then 0.5: expected a positive multiple of the token duration 0.2 s"),
    (["--then", "soon b"], "--then 'soon b': expected a time in seconds, then the text"),
    (["--replan-every", "0.3"], "--replan-every 0.3: expected a positive multiple of the token duration 0.2 s"),
    (["--replan-every", "0"], "--replan-every 0.0 must be > 0"),  # the option's range, at parse time
    (["--replan-every", "-0.4"], "--replan-every -0.4 must be > 0"),
    (["--text", "two", "--then", "0.8s b"], "--then continues one --text; 2 texts were given"),
])
def test_bad_closed_loop_options_fail_in_one_line_before_any_work(tree, controllers, tmp_path, extra, message):
    from motok.cli.main import app

    args = ["gpt", "sample", "-g", str(tree / "gpt"), "--text", TEXTS[0], "--seconds", "1.6", "--closed-loop",
            "--prior", str(controllers[0]), "-o", str(tmp_path / "x.h5"), *extra]
    r = CliRunner().invoke(app, args)
    assert r.exit_code == 2, r.output
    err = r.stderr.strip()
    assert err.startswith("error:") and len(err.splitlines()) == 1 and message in err, err
    assert not list(tmp_path.iterdir())


@pytest.mark.parametrize("args,message", [
    (["--replan-every", "0.4"], "--replan-every goes with --closed-loop"),
    (["--closed-loop"], "--closed-loop re-plans from the simulated character: add --prior PRIOR"),
    (["--then", "0.8s b"], "--then re-plans from the simulated character: add --prior PRIOR"),
])
def test_closed_loop_options_need_their_partners(tree, tmp_path, args, message):
    from motok.cli.main import app

    r = CliRunner().invoke(app, ["gpt", "sample", "-g", str(tree / "gpt"), "--text", TEXTS[0], "-o",
                                 str(tmp_path / "x.h5"), *args])
    assert r.exit_code == 2 and message in r.stderr and len(r.stderr.strip().splitlines()) == 1, r.output
    assert not list(tmp_path.iterdir())


def test_the_schedule_and_the_window():
    """Re-plans fall on multiples of --replan-every, on switches and before a plan runs out; a motion
    the GPT holds whole is continued from all of it, a longer one from the last half of the positions."""
    from motok.control.closed_loop.timeline import Clock, Row, next_replan, plan_window

    assert plan_window(4, 8, 23) == (4, 4) and plan_window(0, 40, 23) == (0, 23)
    assert plan_window(22, 40, 23) == (11, 12) and plan_window(35, 40, 23) == (11, 5)
    row = Row("r", [(0, "a"), (7, "b")], 40, 0)
    assert next_replan(0, 23, row, 5) == 5 and next_replan(5, 28, row, 5) == 7 and next_replan(7, 30, row, None) == 29
    assert next_replan(35, 40, row, None) is None and next_replan(35, 40, row, 5) is None
    clock = Clock(20.0, 4, 30.0, 23)
    assert clock.steps_per_token == 6 and clock.tokens(1.0, "--replan-every") == 5 and clock.length(None) == 23
