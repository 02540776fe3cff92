"""The head-mounted-device tracking task (appendix C.2): the head goal in the root's heading frame,
the head reward, the 1 m termination, the task in a TaskEnv and its evaluation (Table 3 metrics)."""

from __future__ import annotations

import math

import numpy as np
import pytest

from motok.control.mdp.head import HeadRewardConfig, head_errors, head_goal, head_reward, rotation_angle
from motok.control.mdp.resets import reference_bodies
from motok.control.tasks.hmd import evaluate_hmd
from motok.control.mdp.task_env import TaskEnv
from motok.control.tasks.hmd import HMDTask, HMDTaskConfig
from motok.errors import UserError
from motok.rotations import qmul
from motok.sim.obs import Bodies
from task_helpers import place, played_to_the_end, rz, task_mdp

pytestmark = pytest.mark.usefixtures("one_thread")


def _mdp(hum, lib, n, seed=0, base="reference", **task) -> TaskEnv:
    return task_mdp(HMDTask, HMDTaskConfig(**{"episode_seconds": 0.5, **task}), hum, lib, n, seed, base)


_rz, _place = rz, place


# ----------------------------------------------------------------------------- terms

def test_head_goal_in_the_roots_heading_frame():
    """Root facing +Y (yaw 90 deg), head turned 45 deg further: the heading is the root's, so a
    reference head 1 m along world +X reads (0, -1, 0), a 2 m/s world +Y velocity difference reads
    (2, 0, 0); the second frame's head turned 30 deg more reads Rz(30)'s columns."""
    J, head = 3, 2
    pos = np.array([[[0.0, 0, 0.9], [0, 0, 1.2], [0.1, 0, 1.6]]])
    rot = np.stack([_rz(90), _rz(90), _rz(135)])[None]
    zero = np.zeros((1, J, 3))
    sim = Bodies(pos, zero, zero, rot=rot)
    rpos, rvel, rang = np.repeat(pos[:, None], 2, 1), np.zeros((1, 2, J, 3)), np.zeros((1, 2, J, 3))
    rpos[0, 0, head] += [1.0, 0, 0]
    rvel[0, 0, head] = [0, 2.0, 0]
    rang[0, 0, head] = [0, 0, 1.0]
    rrot = np.repeat(rot[:, None], 2, 1)
    rrot[0, 1, head] = _rz(165)
    g = head_goal(sim, Bodies(rpos, rvel, rang, rot=rrot), head).reshape(2, 15)
    c, s = math.cos(math.radians(30)), math.sin(math.radians(30))
    assert np.allclose(g[0], [0, -1, 0, 1, 0, 0, 0, 1, 0, 2, 0, 0, 0, 0, 1])
    assert np.allclose(g[1], [0, 0, 0, c, s, 0, -s, c, 0, 0, 0, 0, 0, 0, 0])


def test_rotation_angle_and_head_reward_hand_values():
    rng = np.random.default_rng(0)
    q = rng.normal(size=(5, 4))
    q /= np.linalg.norm(q, axis=1, keepdims=True)
    axis = rng.normal(size=(5, 3))
    axis /= np.linalg.norm(axis, axis=1, keepdims=True)
    for ang in (math.pi / 6, 1e-7, 3.0):
        d = np.concatenate([np.full((5, 1), math.cos(ang / 2)), math.sin(ang / 2) * axis], 1)
        assert np.allclose(rotation_angle(q, qmul(d, q)), ang, rtol=1e-6)
    assert np.allclose(rotation_angle(q, -q), 0)  # q and -q are one rotation
    # the head reward: 0.1 m off, 30 deg turned, velocities off by 1 m/s and 2 rad/s
    J, head = 2, 1
    zero = np.zeros((1, J, 3))
    sim = Bodies(zero.copy(), zero.copy(), zero.copy(), rot=np.broadcast_to(np.eye(3), (1, J, 3, 3)).copy())
    ref = Bodies(zero + [0, 0.1, 0], zero + [1.0, 0, 0], zero + [0, 0, 2.0], rot=np.stack([np.eye(3), _rz(30)])[None])
    err = head_errors(sim, ref, head)
    assert err["pos"][0] == pytest.approx(0.01) and err["rot"][0] == pytest.approx((math.pi / 6) ** 2)
    assert err["vel"][0] == pytest.approx(1.0) and err["angvel"][0] == pytest.approx(4.0)
    r = head_reward(err, HeadRewardConfig())["r_task"][0]
    assert r == pytest.approx(0.5 * math.exp(-1) + 0.3 * math.exp(-10 * (math.pi / 6) ** 2) + 0.1 * math.exp(-0.1)
                              + 0.1 * math.exp(-0.4))
    assert head_reward(head_errors(sim, sim, head), HeadRewardConfig())["r_task"][0] == pytest.approx(1.0)


# ----------------------------------------------------------------------------- the task

def test_reward_maximal_on_the_reference_and_termination_at_1m(hum, lib):
    mdp = _mdp(hum, lib, 3)
    task = mdp.task
    mdp.reset(clips=[0, 2, 4], frames=[10, 10, 10])
    g = lib.starts[[0, 2, 4]] + 11
    _place(mdp, [0, 1, 2], g)
    r, term, trunc, info = task.update(np.zeros(3, bool), np.zeros(3, bool))
    assert np.allclose(r["r_task"], 1.0, atol=1e-9) and not term.any() and not trunc.any()
    for i, d in enumerate((0.1, 0.8, 1.2)):  # the whole body moved: the head as much
        _place(mdp, [i], g[i:i + 1] + 1, shift=(d, 0.0, 0.0))
    r, term, _, info = task.update(np.zeros(3, bool), np.zeros(3, bool))
    assert np.allclose(info["head_error"], [0.1, 0.8, 1.2]) and term.tolist() == [False, False, True]
    assert r["r_task"][0] == pytest.approx(0.5 * math.exp(-100 * 0.01) + 0.5, abs=1e-6)
    loose = _mdp(hum, lib, 1, termination_distance=1.5)  # the fork's recipe
    loose.reset(clips=[0], frames=[10])
    _place(loose, [0], g[:1], shift=(1.2, 0.0, 0.0))
    assert not loose.task.update(np.zeros(1, bool), np.zeros(1, bool))[1].any()
    r, term, _, _ = task.update(np.array([True, False, False]), np.zeros(3, bool))  # env 0 diverged
    assert r["r_task"][0] == 0.0 and term[0]


def test_task_env_tracks_the_reference_head(hum, lib):
    mdp = _mdp(hum, lib, 2)
    task = mdp.task
    obs, goal = mdp.reset(clips=[1, 6], frames=[0, 30])
    assert goal.shape == (2, 75) == (2, task.goal_dim) and task.limit.tolist() == [15, 15]
    ref = lib.body_pos[lib.starts[[1, 6]] + np.array([0, 30])]
    assert np.allclose(task.markers()[:, 0], ref[:, task.head])
    zero = np.zeros((2, mdp.action_dim))
    for step in range(1, 16):
        obs, goal, r, term, trunc, info = mdp.step(zero)
        assert np.isfinite(obs).all() and np.isfinite(goal).all() and not term.any()
        # PD on the reference alone drifts (the head 0.15-0.4 m off after 0.5 s), but starts on it
        assert ((r["r_task"] > 0.9) | (step > 3)).all() and ((r["r_task"] >= 0) & (r["r_task"] <= 1 + 1e-9)).all()
        assert ((info["head_error"] < 0.02) | (step > 3)).all()
        assert trunc.all() == (step == 15)
    # the goal reads the next 5 reference frames (t + 1 .. t + 5), after a step as after a reset
    ahead = reference_bodies(lib, task.clip[:, None], task.frame[:, None] + np.arange(1, 6))
    assert np.allclose(goal, head_goal(mdp.env.bodies, ahead, task.head))
    _, goal = mdp.reset(clips=[1, 6], frames=[0, 30])
    ahead = reference_bodies(lib, np.array([[1], [6]]), np.array([[0], [30]]) + np.arange(1, 6))
    assert np.allclose(goal, head_goal(mdp.env.bodies, ahead, task.head))
    near = ahead.pos[:, 0, task.head] - mdp.env.bodies.pos[:, task.head]  # one frame ahead: a few cm
    assert np.allclose(np.linalg.norm(goal[:, :3], axis=1), np.linalg.norm(near, axis=1))
    cur = _mdp(hum, lib, 2, base="current")
    cur.reset()
    for _ in range(3):
        _, goal, r, _, _, _ = cur.step(np.zeros((2, cur.action_dim)))
        assert np.isfinite(goal).all() and np.isfinite(r["r_task"]).all()
    with pytest.raises(UserError, match="goal_frames"):
        HMDTaskConfig(goal_frames=0)


def test_random_starts_leave_a_whole_episode(hum, lib):
    mdp = _mdp(hum, lib, 64, seed=2, episode_seconds=5.0)
    mdp.reset()
    t = mdp.task
    assert (t.limit == 150).all() and (t.start + 150 + 5 <= lib.lengths[t.clip] - 1).all()
    with pytest.raises(UserError, match="start frames"):
        mdp.reset([0], clips=[0], frames=[lib.lengths[0] - 3])


# ----------------------------------------------------------------------------- evaluation

def test_evaluate_hmd_on_pd_tracking(hum, lib):
    mdp = _mdp(hum, lib, 2, seed=4)
    res = evaluate_hmd(mdp, lambda obs, goal: np.zeros((len(obs), mdp.action_dim)), 3)
    assert res["episodes"] == 3 and len(res["per_episode"]["head_error_mm"]) == 3
    assert res["success_rate"] == 1.0 and res["seconds_mean"] == pytest.approx(0.5)
    for m in ("mpjpe_mm", "g_mpjpe_mm", "vel_err_mm", "acc_err_mm", "head_error_mm"):
        # the summary over episodes is the population mean and std of the per-episode values
        v = np.asarray(res["per_episode"][m])
        assert res[f"{m}_mean"] == pytest.approx(v.mean()) and res[f"{m}_std"] == pytest.approx(v.std())
    assert 0 < res["head_error_mm_mean"] < 200 and res["head_within_share_mean"] == 1.0
    assert not any(k.startswith("keyframe_") for k in res)
    with pytest.raises(UserError, match="HMDTask"):
        evaluate_hmd(TaskEnv(mdp.env, object(), mdp.action_map), None, 1)


def test_evaluation_plays_lost_heads_to_the_end(hum, lib):
    """Table 3's errors are over whole trajectories: with a head test that fires at once (2 mm),
    the same trajectories give the same errors, no episode succeeds, and the head is within the
    distance for a share of the frames only."""
    ok, bad, _ = played_to_the_end(evaluate_hmd, lambda **kw: _mdp(hum, lib, 2, seed=4, **kw), 0.002,
                                   ("mpjpe_mm", "g_mpjpe_mm", "vel_err_mm", "acc_err_mm", "head_error_mm"), 0.5)
    assert bad["head_within_share_mean"] < 1.0 == ok["head_within_share_mean"]

