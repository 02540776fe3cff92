"""Kinematic motion in, simulated motion out (motok.control.track, `motok control track`), with
plain PD tracking as the controller (an expert whose actions are zero: PD on the reference's
angles and velocities), so the test needs no training."""

from __future__ import annotations

import json
from dataclasses import replace

import numpy as np
import pytest
import torch
from typer.testing import CliRunner

from motok.artifacts import Provenance
from motok.control.expert.model import ExpertConfig, build_actor_critic
from motok.control.expert.train import imitation_mdp
from motok.control.priors.load import Controller
from motok.control.track import place_on_floor, report_path, track
from motok.data.dataset import MotionFile, write_motion
from motok.eval.metrics import mpjpe
from motok.sim.humanoid import from_mj, to_mj

pytestmark = pytest.mark.usefixtures("one_thread")


@pytest.fixture(scope="module")
def pd_controller(hum, lib):
    """A controller whose policy's mean action is 0 on the reference base."""
    cfg = ExpertConfig()
    cfg.action.base, cfg.task.termination, cfg.env.num_envs = "reference", "mean", 8
    cfg.net.encoder = cfg.net.decoder = cfg.net.value = [16]
    mdp = imitation_mdp(hum, lib, cfg.env, cfg.task, cfg.action, 0)
    ac = build_actor_critic(cfg.net, mdp.obs_dim, mdp.goal_dim, mdp.action_dim)
    with torch.no_grad():
        ac.policy.decoder[-1].weight.zero_()
        ac.policy.decoder[-1].bias.zero_()
    return Controller(cfg, hum, ac, {"kind": "control-expert", "model_sha256": "pd"})


def test_mj_and_data_frames_are_inverse():
    v = np.random.default_rng(0).normal(size=(5, 3))
    assert np.array_equal(from_mj(to_mj(v)), v)


def test_tracked_clips_follow_their_reference_and_round_trip(pd_controller, small_dataset, tmp_path, monkeypatch):
    out = tmp_path / "tracked.h5"
    res = track(pd_controller, small_dataset, out, clips="dataset-2_walk_normal_00[1-3]")
    assert res["clips"] == res["written"] == 3 and res["tracked_to_end"] == 0.0  # plain PD falls
    with MotionFile(out, "motion") as sim, MotionFile(small_dataset) as ref:
        assert sim.fps == ref.fps and list(sim.names) == [f"dataset-2_walk_normal_00{i}" for i in (1, 2, 3)]
        for name in sim.names:
            r, s = res["per_clip"][name], sim.clip(name)
            # the simulated part only, at the motion's rate; features recomputed (12J - 1 per frame)
            assert abs(s.num_frames - r["seconds"] * sim.fps) <= 2 and s.features.shape[1] == 12 * 21 - 1
            g = ref.clip(name)
            assert s.split == g.split and s.captions == g.captions
            # its reference's labels, and how far it was played (for `eval t2m --tracked-to-end`)
            assert s.labels == {**g.labels, "tracked_to_end": r["tracked_to_end"],
                                "tracked_seconds": pytest.approx(r["seconds"])}
            # written joints against the reference over the frames played: close to the error the
            # tracking measured at the control rate (both root-relative)
            n = min(s.num_frames, g.num_frames)
            err = float(mpjpe(s.joints[:n], g.joints[:n]).mean())
            assert 0.5 * r["mpjpe_mm"] < err < 1.5 * r["mpjpe_mm"] + 10.0, (err, r["mpjpe_mm"])
            # dataset motion already stands on the floor of the feature pipeline: not lifted (the
            # humanoid's feet reach into the floor there, and a lifted reference is not what the
            # controllers were trained on)
            assert abs(r["floor_shift_m"]) < 1e-3
    # the results beside the motion, for tables made later (strict JSON, the same numbers)
    saved = json.loads(report_path(out).read_text(), parse_constant=lambda c: pytest.fail(f"not JSON: {c}"))
    assert report_path(out).name == "tracked.track.json" and saved["kind"] == "control-track"
    assert saved["per_clip"] == res["per_clip"] and saved["tracked_to_end"] == res["tracked_to_end"]
    assert saved["provenance"]["config"]["clips"] == "dataset-2_walk_normal_00[1-3]"
    # sole slip of the simulated feet and of the reference over the same states (motok.sim.soles):
    # the reference's walks mostly plant their soles, whatever the plain PD controller does
    slip = saved["sole_slip"]
    assert set(slip) == {"simulated", "reference"} and 0 < slip["reference"]["sole_contact_fraction"] < 1
    assert slip["reference"]["sole_slip_ratio"] < 0.5 and "sole_slip_cm_s" in r
    from motok.cli.main import app

    runner = CliRunner()
    monkeypatch.setenv("MOTOK_CACHE", str(tmp_path / "cache"))
    for args in (["info", str(out)], ["render", str(out), "--clip", "dataset-2_walk_normal_002", "-o",
                                        str(tmp_path / "s.gif")],
                 ["export", "bvh", str(out), "--clip", "dataset-2_walk_normal_002", "-o", str(tmp_path / "s.bvh")]):
        r = runner.invoke(app, ["--quiet", *args])
        assert r.exit_code == 0, (args, r.output)
    assert (tmp_path / "s.gif").exists() and (tmp_path / "s.bvh").stat().st_size > 1000


def test_tracking_in_chunks_changes_nothing(pd_controller, small_dataset, tmp_path):
    """The reference library is built a chunk of clips at a time (memory); chunks of one clip and
    batches of two give the clips, frames and per-clip results of one library and one batch."""
    glob = "dataset-2_walk_normal_00[1-4]"
    whole = track(pd_controller, small_dataset, tmp_path / "whole.h5", clips=glob)
    parts = track(pd_controller, small_dataset, tmp_path / "parts.h5", clips=glob, chunk=1, batch=2)
    assert parts["per_clip"] == whole["per_clip"] and len(whole["per_clip"]) == 4
    with MotionFile(tmp_path / "whole.h5", "motion") as a, MotionFile(tmp_path / "parts.h5", "motion") as b:
        assert list(a.names) == list(b.names)
        for n in a.names:
            assert np.array_equal(a.clip(n).joints, b.clip(n).joints) and np.array_equal(a.clip(n).features,
                                                                                     b.clip(n).features)


def test_a_split_of_a_dataset_is_tracked(pd_controller, small_dataset, tmp_path):
    """``split``: the clips of that split only (the real-test-motion row of the text-to-physics evaluation),
    alone or with a glob; a split the data lacks is named."""
    from motok.errors import UserError

    with MotionFile(small_dataset) as mf:
        test = [mf.names[i] for i in mf.split_indices("test")]
    res = track(pd_controller, small_dataset, tmp_path / "test.h5", split="test")
    with MotionFile(tmp_path / "test.h5", "motion") as sim:
        assert sorted(sim.names) == sorted(test) and res["clips"] == len(test) >= 1
        assert {sim.clip(n).split for n in sim.names} == {"test"}
    with pytest.raises(UserError, match="split 'nope'"):
        track(pd_controller, small_dataset, tmp_path / "x.h5", split="nope")


def test_floating_motion_is_placed_on_the_floor_and_short_clips_fail_alone(pd_controller, small_dataset, tmp_path,
                                                                          lib):
    """A motion 1 m above the floor is tracked from the floor; a clip too short to track is
    reported by name and the others are written."""
    with MotionFile(small_dataset) as mf:
        a, b = mf.clip("dataset-2_walk_normal_001"), mf.clip("dataset-2_walk_normal_002")
        skeleton, offsets, fps = mf.skeleton, mf.offsets, mf.fps
    up = replace(a, name="floating", joints=a.joints + np.array([0.0, 1.0, 0.0], np.float32))
    tiny = replace(b, name="tiny", features=b.features[:2], joints=b.joints[:2], local_quats=b.local_quats[:2],
                   root_translation=b.root_translation[:2])
    src = tmp_path / "gen.h5"
    write_motion(src, "motion", Provenance(command="test", config={}), [up, tiny, b], skeleton, offsets, fps, False)
    res = track(pd_controller, src, tmp_path / "out.h5")
    per = res["per_clip"]
    assert per["floating"]["floor_shift_m"] == pytest.approx(-1.0, abs=1e-3)
    assert "too short" in per["tiny"]["error"] and res["written"] == 2 and not per["tiny"]["tracked_to_end"]
    base = track(pd_controller, small_dataset, tmp_path / "ref.h5", clips="dataset-2_walk_normal_001")
    assert per["floating"]["seconds"] == pytest.approx(base["per_clip"]["dataset-2_walk_normal_001"]["seconds"], abs=0.1)
    with MotionFile(tmp_path / "out.h5", "motion") as mf:
        assert list(mf.names) == ["floating", "dataset-2_walk_normal_002"]
    placed, shift = place_on_floor(lib)
    assert np.allclose([placed.joints[s:e, :, 2].min() for s, e in zip(placed.starts[:-1], placed.starts[1:])], 0.0)
    assert np.abs(shift).max() < 1e-3  # the dataset's own clips: on the floor already
    assert np.allclose(placed.qpos[:, 2] - lib.qpos[:, 2], np.repeat(shift, lib.lengths))
    with pytest.raises(ValueError, match="no clip is long enough"):
        write_motion(tmp_path / "t.h5", "motion", Provenance(command="test", config={}), [tiny], skeleton, offsets, fps, False)
        track(pd_controller, tmp_path / "t.h5", tmp_path / "none.h5")
    assert not (tmp_path / "none.h5").exists()
    json.dumps(res)  # results are plain JSON


def test_track_failures_groups_the_report_and_replays_the_failures(pd_controller, small_dataset, tmp_path, script):
    """scripts/track_failures.py: per content label, the shares and errors of a track report, and
    the failed clips played again to the same step (the tracking is deterministic); plain PD falls:
    its head ends below the reference's."""
    tf = script("track_failures")
    with MotionFile(small_dataset) as mf:
        split = next(s for s in ("test", "val", "train") if mf.split_indices(s))
    res = track(pd_controller, small_dataset, tmp_path / "sim.h5", split=split, clips="dataset-2_walk*")
    rep = json.loads(report_path(tmp_path / "sim.h5").read_text())
    content = tf.content_of(rep, str(small_dataset), split)
    assert set(content) == set(res["per_clip"]) and set(content.values()) <= {"walk", "walk-turn-left",
                                                                           "walk-turn-right"}
    groups = tf.summary(rep, content)
    assert sum(g["clips"] for g in groups.values()) == len(content)
    failed = sorted(n for g in groups.values() for n in g["failed"])
    assert failed == sorted(n for n, v in res["per_clip"].items() if not v["tracked_to_end"]) and failed
    for c, g in groups.items():
        clips = [res["per_clip"][n] for n, cc in content.items() if cc == c]
        assert g["tracked_to_end"] == pytest.approx(np.mean([v["tracked_to_end"] for v in clips]))
        assert g["mpjpe_mm"] == pytest.approx(np.median([v["mpjpe_mm"] for v in clips]))
    f = tf.how_they_failed(pd_controller, str(small_dataset), failed)
    assert f["clips"] == len(failed) and f["head_m"] < f["ref_head_m"]
    assert f["seconds"] == pytest.approx({n: res["per_clip"][n]["seconds"] for n in failed})
