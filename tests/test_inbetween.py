"""The motion in-betweening task (appendix C.1): keyframe sampling, the time encoding, the Eq. 12
goal, the Eq. 14 reward, termination, the task in a TaskEnv and its evaluation (Table 2 metrics)."""

from __future__ import annotations

import math

import numpy as np
import pytest

from motok.control.mdp.keyframes import (InbetweenRewardConfig, pose_speed, inbetween_errors, inbetween_reward,
                                         keyframe_goal, next_keyframe, sample_keyframes, sample_still_keyframes,
                                         still_frames, time_encoding)
from motok.control.mdp.resets import reference_bodies
from motok.control.mdp.terminations import body_distances, tracking_failure
from motok.control.tasks.episodes import EpisodeErrors, summary
from motok.control.tasks.inbetween import evaluate_inbetween
from motok.control.mdp.task_env import TaskEnv
from motok.control.tasks.inbetween import InbetweenTask, InbetweenTaskConfig
from motok.errors import UserError
from motok.sim.obs import Bodies
from task_helpers import place, played_to_the_end, rz, task_mdp

pytestmark = pytest.mark.usefixtures("one_thread")

# 18-frame windows: PD tracking of the reference alone stays up that long (it drifts over 30 frames)
SHORT = dict(window_seconds=0.6, num_keyframes=3, eval_keyframes=4, min_keyframe_gap_seconds=0.1)


def _mdp(hum, lib, n, seed=0, base="reference", **task) -> TaskEnv:
    return task_mdp(InbetweenTask, InbetweenTaskConfig(**{**SHORT, **task}), hum, lib, n, seed, base)


_rz, _place = rz, place


# ----------------------------------------------------------------------------- terms

def test_keyframe_sampling_count_order_window_and_spacing():
    rng = np.random.default_rng(0)
    k = sample_keyframes(rng, 4000, 5, 120, 15)
    assert k.shape == (4000, 5) and k.dtype == np.int64
    assert (k[:, 0] == 0).all() and (k[:, -1] == 119).all()  # the start and the window's last frame
    gaps = np.diff(k, axis=1)
    assert gaps.min() == 15 and gaps.max() > 60  # never closer than the minimum, and spread out
    # three keyframes: the middle one is uniform over the frames that keep both gaps >= 15
    mid = sample_keyframes(rng, 20000, 3, 120, 15)[:, 1]
    assert mid.min() == 15 and mid.max() == 104 and abs(mid.mean() - 59.5) < 1.0
    assert np.array_equal(sample_keyframes(rng, 2, 9, 121, 15), np.tile(np.arange(9) * 15, (2, 1)))  # no slack
    for count in (1, 10):
        with pytest.raises(UserError, match="num_keyframes"):
            sample_keyframes(rng, 1, count, 121, 15)


def test_still_frames_are_the_local_minima_of_speed():
    speed = np.array([[3.0, 1.0, 2.0, 2.0, 0.5, 4.0, 1.0, 1.0, 5.0]])
    # by hand: 1 (1 <= 3, 1 <= 2), 4 (0.5 under both), 6 and 7 (a flat minimum: <= on both sides);
    # 3 is not (2 > 0.5), nor the window's ends (one neighbour only)
    assert np.flatnonzero(still_frames(speed)[0]).tolist() == [1, 4, 6, 7]
    # no still frame in a stretch: its slowest frame, the first one it allows on a rising speed
    rising = np.arange(40, dtype=float)[None] ** 2
    assert sample_still_keyframes(np.random.default_rng(0), rising, 4, 10).tolist() == [[0, 10, 20, 39]]


def test_zero_velocity_keyframes_on_a_real_clip(lib):
    """C.1's keyframes are zero-velocity poses: on a real 4 s window, each interior keyframe is a
    frame where the pose's speed (each body's speed relative to the root, averaged over the
    bodies; computed here body by body) is a local minimum; every such frame the spacing allows is
    drawn, and no other."""
    c = int(np.argmax(lib.lengths))
    g = lib.starts[c] + 10 + np.arange(120)
    J = lib.body_vel.shape[1]
    speed = np.array([np.mean([math.sqrt(sum((lib.body_vel[i, j, a] - lib.body_vel[i, 0, a]) ** 2 for a in range(3)))
                               for j in range(1, J)]) for i in g])
    assert np.allclose(pose_speed(lib.body_vel[g]), speed)
    hand = [t for t in range(1, 119) if speed[t] <= speed[t - 1] and speed[t] <= speed[t + 1]]
    assert len(hand) >= 6  # a walk comes to rest about twice a second
    k = sample_still_keyframes(np.random.default_rng(0), np.tile(speed, (3000, 1)), 4, 15)
    assert (k[:, 0] == 0).all() and (k[:, -1] == 119).all() and (np.diff(k, axis=1) >= 15).all()
    assert set(k[:, 1:3].ravel().tolist()) <= set(hand)
    # the first interior keyframe: uniform over the still frames from 15 to 119 - 2 * 15
    first = [t for t in hand if 15 <= t <= 89]
    assert sorted(set(k[:, 1].tolist())) == first
    share = np.bincount(k[:, 1], minlength=120)[first] / len(k)
    assert np.abs(share - 1 / len(first)).max() < 0.03


def test_time_encoding_hand_values():
    e = time_encoding(np.array([0, 1, 7, 96, 500]), 4, cap=96)
    assert np.allclose(e[0], [0, 1, 0, 1])
    assert np.allclose(e[1], [math.sin(1), math.cos(1), math.sin(0.01), math.cos(0.01)])  # w_1 = 10000^(-2/4)
    assert np.allclose(e[2], [math.sin(7), math.cos(7), math.sin(0.07), math.cos(0.07)])
    assert np.array_equal(e[4], e[3])  # constant from the cap on
    odd = time_encoding(np.array([2]), 3, cap=50)[0]
    assert np.allclose(odd, [math.sin(2), math.cos(2), math.sin(2 * 10000 ** (-2 / 3))])


def test_next_keyframe_moves_on_at_arrival():
    keys = np.array([[0, 10, 25, 40]] * 6)
    t = np.array([0, 9, 10, 24, 25, 40])
    assert next_keyframe(keys, t).tolist() == [1, 1, 2, 2, 3, 3]  # the last one stays once reached


def test_keyframe_goal_in_the_heading_frame():
    """A character facing +Y (yaw 90 deg): a keyframe 1 m along world +X is 1 m to its right
    (heading frame -Y); a keyframe turned 30 deg more about the vertical reads Rz(30)'s columns."""
    root, arm = np.array([1.0, 2.0, 0.9]), np.array([0.0, 0.3, 0.4])
    pos = np.stack([root, root + arm])[None]
    rot = np.broadcast_to(_rz(90), (1, 2, 3, 3)).copy()
    zero = np.zeros((1, 2, 3))
    sim = Bodies(pos, zero, zero, rot=rot)
    kpos = np.stack([pos[0] + [1.0, 0, 0], pos[0]])[None]  # (1, K=2, J=2, 3)
    krot = np.stack([rot[0], np.broadcast_to(_rz(120), (2, 3, 3))])[None]
    keys = Bodies(kpos, np.zeros((1, 2, 2, 3)), np.zeros((1, 2, 2, 3)), rot=krot)
    g = keyframe_goal(sim, keys).reshape(1, 2, 2, 9)
    c, s = math.cos(math.radians(30)), math.sin(math.radians(30))
    assert np.allclose(g[0, 0, :, :3], [0, -1, 0]) and np.allclose(g[0, 0, :, 3:], [1, 0, 0, 0, 1, 0])
    assert np.allclose(g[0, 1, :, :3], 0) and np.allclose(g[0, 1, :, 3:], [c, s, 0, -s, c, 0])


def test_inbetween_reward_hand_values():
    pos = np.zeros((1, 3, 3))
    ref = pos + [0.1, 0.0, 0.0]  # every body 0.1 m off: root and (global) end effectors
    err = inbetween_errors(pos, ref, np.zeros((1, 2)), np.array([[0.1, 0.3]]), np.zeros((1, 2)),
                           np.array([[1.0, 3.0]]), [1, 2])
    assert err["root"][0] == pytest.approx(0.01) and err["ee"][0] == pytest.approx(0.01)
    assert err["q"][0] == pytest.approx(0.05) and err["qd"][0] == pytest.approx(5.0)  # means over hinges
    r = inbetween_reward(err, InbetweenRewardConfig())
    want = 0.65 * math.exp(-0.1) + 0.1 * math.exp(-0.5) + 0.15 * math.exp(-0.4) + 0.1 * math.exp(-0.1)
    assert r["r_task"][0] == pytest.approx(want)
    same = inbetween_errors(pos, pos, np.zeros((1, 2)), np.zeros((1, 2)), np.zeros((1, 2)), np.zeros((1, 2)), [1])
    assert inbetween_reward(same, InbetweenRewardConfig())["r_task"][0] == pytest.approx(1.0)
    with pytest.raises(UserError, match="w_q"):
        InbetweenRewardConfig(w_q=-1)


# ----------------------------------------------------------------------------- the task

def test_reward_is_maximal_on_the_reference_and_lower_off_it(hum, lib):
    mdp = _mdp(hum, lib, 2)
    mdp.reset(clips=[0, 3], frames=[10, 20], keyframes=[0, 8, 17])
    task, g = mdp.task, lib.starts[[0, 3]] + np.array([10, 20])
    _place(mdp, [0, 1], g + 1)  # exactly the reference frame the step reaches
    r, term, trunc, info = task.update(np.zeros(2, bool), np.zeros(2, bool))
    assert np.allclose(r["r_task"], 1.0, atol=1e-9) and not term.any() and not trunc.any()
    assert info["max_body_error"].max() < 1e-9
    _place(mdp, [0, 1], g + 2, shift=(0.1, 0.0, 0.0))  # the whole body 0.1 m off, same pose
    r, term, _, _ = task.update(np.zeros(2, bool), np.zeros(2, bool))
    want = 0.65 + 0.1 + 0.15 * math.exp(-40 * 0.01) + 0.1 * math.exp(-10 * 0.01)
    assert np.allclose(r["r_task"], want, atol=1e-6) and not term.any()
    _place(mdp, [0, 1], g + 3)
    r, term, _, info = task.update(np.array([False, True]), np.zeros(2, bool))  # env 1 diverged
    assert r["r_task"][1] == 0.0 and r["r_task"][0] == pytest.approx(1.0) and term.tolist() == [False, True]


def test_one_body_far_fails_the_maximum_test_and_not_the_mean(lib):
    """B.1 / C.1: a body more than 0.5 m from its reference fails; on a real reference pose with one
    body 0.6 m off and the others exact, the maximum is 0.6 m and the mean 0.6 / J."""
    ref = reference_bodies(lib, np.array([0, 0]), np.array([5, 5]))
    pos = ref.pos.copy()
    pos[1, 7, 1] += 0.6  # environment 1: body 7 moved 0.6 m along y
    dist = body_distances(Bodies(pos, ref.vel, ref.angvel, quat=ref.quat), ref)
    assert dist[0].max() == 0.0 and dist[1, 7] == pytest.approx(0.6) and dist[1].mean() == pytest.approx(0.6 / 21)
    assert tracking_failure(dist, "any", 0.5).tolist() == [False, True]
    assert tracking_failure(dist, "mean", 0.5).tolist() == [False, False]
    assert InbetweenTaskConfig().termination == "any" and InbetweenTaskConfig().termination_distance == 0.5


def test_termination_at_the_body_distance(hum, lib):
    """The whole body 0.45 / 0.55 m off ends only the second episode; a flung arm (one body far,
    the mean small) ends it on the "any" test (the default: B.1 and C.1's maximum distance) and not
    on the fork's "mean" one."""
    strict, mdp = _mdp(hum, lib, 3), _mdp(hum, lib, 3, termination="mean")
    g = lib.starts[1] + 6
    arm = hum.qpos_adr[list(hum.skeleton.joints).index("UpperArm_R")]
    for m in (mdp, strict):
        m.reset(clips=[1, 1, 1], frames=[5, 5, 5])
        for i, d in enumerate((0.45, 0.55)):
            _place(m, [i], [g], shift=(0.0, d, 0.0))
        q, v = lib.qpos[[g]].copy(), lib.qvel[[g]].copy()
        q[0, arm[0]] += 3.0  # a swing hinge of the shoulder (the middle one is the twist)
        m.env.set_state(np.array([2]), q, v)
    _, term, trunc, info = mdp.task.update(np.zeros(3, bool), np.zeros(3, bool))
    assert np.allclose(info["mean_body_error"][:2], [0.45, 0.55]) and not trunc.any()
    assert info["max_body_error"][2] > 0.5 > info["mean_body_error"][2]
    assert term.tolist() == [False, True, False]
    assert strict.task.update(np.zeros(3, bool), np.zeros(3, bool))[1].tolist() == [False, True, True]
    off = _mdp(hum, lib, 2, early_termination=False)
    off.reset(clips=[1, 1], frames=[5, 5])
    _place(off, [0, 1], [g, g], shift=(0.0, 2.0, 0.0))
    assert not off.task.update(np.zeros(2, bool), np.zeros(2, bool))[1].any()


def test_task_env_tracks_the_reference_through_the_keyframes(hum, lib):
    """Zero actions on the reference base (PD on the reference) pass every keyframe: high reward,
    no termination (the fork's mean test: PD tracking alone drifts a hand past 0.5 m within the
    window), the keyframes flagged at their frames, truncation at the last one, and the goal is the
    Eq. 12 differences to the interval's start and goal keyframes plus the encoded frames left
    (Eq. 13)."""
    mdp = _mdp(hum, lib, 2, termination="mean")
    task = mdp.task
    obs, goal = mdp.reset(clips=[0, 5], frames=[0, 40], keyframes=[0, 8, 17])
    assert goal.shape == (2, task.goal_dim) == (2, 2 * 21 * 9) and obs.shape == (2, mdp.obs_dim)
    keys = task.keyframe_bodies()
    expect = keyframe_goal(mdp.env.bodies, keys.take((slice(None), slice(0, 2))))
    assert np.allclose(goal - expect, time_encoding(np.array([8, 8]), task.goal_dim, task.window - 4))
    assert task.markers().shape == (2, 21, 3) and np.allclose(task.markers(), keys.pos[:, 1])
    zero = np.zeros((2, mdp.action_dim))
    for step in range(1, 18):
        obs, goal, r, term, trunc, info = mdp.step(zero)
        assert np.isfinite(obs).all() and np.isfinite(goal).all()
        assert (r["r_task"] > 0.6).all() and (r["r_task"] <= 1.0 + 1e-9).all() and not term.any()
        assert info["at_keyframe"].all() == (step in (8, 17)) and trunc.all() == (step == 17)
        assert (task.target == (1 if step < 8 else 2)).all()
        if step == 8:  # the next interval: keyframes 1 (its start) and 2 (its goal), 9 frames ahead
            enc = time_encoding(np.array([9, 9]), task.goal_dim, task.window - 4)
            assert np.allclose(goal, keyframe_goal(mdp.env.bodies, keys.take((slice(None), slice(1, 3)))) + enc)
    assert info["keyframe_index"].tolist() == [2, 2]
    # the other pair (the goal keyframe and the one after it), concatenated encoding, current-pose base
    nxt = _mdp(hum, lib, 2, base="current", goal_keyframes="next", time_encoding="concat", time_encoding_dim=6)
    _, goal = nxt.reset(clips=[0, 5], frames=[0, 40], keyframes=[0, 8, 17])
    assert goal.shape == (2, 2 * 21 * 9 + 6) and nxt.task.goal_dim == goal.shape[1]
    pair = nxt.task.keyframe_bodies().take((slice(None), slice(1, 3)))
    assert np.allclose(goal[:, :-6], keyframe_goal(nxt.env.bodies, pair))
    assert np.allclose(goal[:, -6:], time_encoding(np.array([8, 8]), 6, 14))
    for _ in range(3):
        _, goal, r, term, _, _ = nxt.step(np.zeros((2, nxt.action_dim)))
        assert np.isfinite(goal).all() and np.isfinite(r["r_task"]).all()


def test_the_goal_is_the_intervals_start_and_goal_keyframes_on_a_hand_pose(hum, lib):
    """Eq. 12-13: the goal reads the current interval's start keyframe and its goal keyframe. Reset
    on the start keyframe, its part is zero position and the identity rotation; with the root moved
    0.3 m along world x, every body's difference to it is -0.3 m along x turned into the heading
    frame; the goal keyframe's part is Eq. 12 to keyframe 1 alone."""
    mdp = _mdp(hum, lib, 1, time_encoding="none")
    task = mdp.task
    mdp.reset(clips=[2], frames=[4], keyframes=[0, 9, 17])
    J, g = len(hum.skeleton.joints), lib.starts[2] + 4
    _place(mdp, [0], [g])  # exactly the start keyframe (a reset's start state is lifted clear of the floor)
    task._refresh_goal(np.arange(1))
    parts = task.goal().reshape(2, J, 9)
    assert np.allclose(parts[0, :, :3], 0.0, atol=1e-9) and np.allclose(parts[0, :, 3:], [1, 0, 0, 0, 1, 0], atol=1e-9)
    _place(mdp, [0], [g], shift=(0.3, 0.0, 0.0))
    task._refresh_goal(np.arange(1))
    parts = task.goal().reshape(2, J, 9)
    r = mdp.env.bodies.rot[0, 0]
    yaw = math.atan2(r[1, 0], r[0, 0])  # the root's heading, from its rotation matrix by hand
    assert np.allclose(parts[0, :, :3], [-0.3 * math.cos(yaw), 0.3 * math.sin(yaw), 0.0], atol=1e-9)
    one = keyframe_goal(mdp.env.bodies, task.keyframe_bodies().take((slice(None), slice(1, 2))))
    assert np.allclose(parts[1].ravel(), one[0])


def test_random_windows_fit_their_clips_and_bad_inputs_are_named(hum, lib):
    mdp = _mdp(hum, lib, 64, seed=3, window_seconds=4.0, num_keyframes=4, eval_keyframes=5,
               min_keyframe_gap_seconds=0.5)
    mdp.reset()
    t = mdp.task
    assert (t.keyframes[:, 0] == t.start).all() and (t.keyframes[:, -1] == t.start + 119).all()
    assert (t.keyframes[:, -1] <= lib.lengths[t.clip] - 1).all() and (np.diff(t.keyframes, axis=1) >= 15).all()
    assert len(np.unique(t.keyframes[:, 1] - t.start)) > 10  # the keyframes differ between windows
    # the interior ones are zero-velocity poses: local minima of their clip's pose speed, or
    # the slowest frame of a stretch the spacing allows that has none
    speed, still = pose_speed(lib.body_vel), 0
    for i in range(64):
        s = speed[lib.frame_index(t.clip[i], t.start[i] + np.arange(120))]
        k = t.keyframes[i] - t.start[i]
        for j in (1, 2):
            allowed = np.arange(k[j - 1] + 15, 119 - (3 - j) * 15 + 1)
            minima = [u for u in allowed if s[u] <= s[u - 1] and s[u] <= s[u + 1]]
            assert k[j] in minima if minima else k[j] == allowed[np.argmin(s[allowed])]
            still += bool(minima)
    assert still > 100  # most stretches hold a still frame
    with pytest.raises(UserError, match="keyframe_selection"):
        InbetweenTaskConfig(keyframe_selection="random")
    with pytest.raises(UserError, match="run past"):
        mdp.reset([0], clips=[0], frames=[lib.lengths[0] - 50])
    with pytest.raises(UserError, match="keyframes must be"):
        mdp.reset([0], clips=[0], frames=[0], keyframes=[0, 30, 20, 60])
    with pytest.raises(UserError, match="num_keyframes"):
        _mdp(hum, lib, 1, num_keyframes=8)  # 8 keyframes 3 frames apart need 22 of the 18 frames
    with pytest.raises(UserError, match="goal_keyframes"):
        InbetweenTaskConfig(goal_keyframes="all")


# ----------------------------------------------------------------------------- evaluation

def test_episode_errors_hand_values():
    """The accumulator behind the evaluations: zero on the reference itself; a constant 10 mm
    offset is only global error; a drift of 1 mm per frame is 1 mm/frame of velocity error and no
    acceleration error; keyframe columns count only the flagged frames."""
    rng = np.random.default_rng(0)
    T, N, J = 8, 3, 4
    ref = rng.normal(0, 0.3, (T, N, J, 3))
    drift = np.arange(T)[:, None, None, None] * np.array([0.001, 0, 0])
    sims = {"same": ref, "offset": ref + [0.01, 0, 0], "drift": ref + drift}
    key = np.zeros((T, N), bool)
    key[[3, 6]] = True
    out = {}
    for name, sim in sims.items():
        acc = EpisodeErrors(N)
        live = np.ones(N, bool)
        for t in range(T):
            acc.record(sim[t], ref[t], live, key[t])
        out[name] = dict(zip(acc.names, acc.means(np.arange(N)).T))
    assert all(np.allclose(v, 0) for v in out["same"].values())
    assert np.allclose(out["offset"]["g_mpjpe_mm"], 10) and np.allclose(out["offset"]["mpjpe_mm"], 0)
    assert np.allclose(out["offset"]["vel_err_mm"], 0) and np.allclose(out["offset"]["acc_err_mm"], 0)
    assert np.allclose(out["drift"]["vel_err_mm"], 1) and np.allclose(out["drift"]["acc_err_mm"], 0, atol=1e-9)
    assert np.allclose(out["drift"]["g_mpjpe_mm"], np.arange(T).mean())
    assert np.allclose(out["drift"]["keyframe_g_mpjpe_mm"], (3 + 6) / 2)


def test_the_episode_summary_on_hand_values():
    # Per metric: mean and population std over the episodes where it was measured (NaN: no frame).
    rows = np.array([[1.0, np.nan], [3.0, 2.0], [np.nan, 2.0]])
    res = summary(["a", "b"], rows, np.array([True, False, True]), np.array([1.0, 2.0, 3.0]))
    assert res["episodes"] == 3 and res["success_rate"] == pytest.approx(2 / 3) and res["seconds_mean"] == 2.0
    assert (res["a_mean"], res["a_std"], res["b_mean"], res["b_std"]) == (2.0, 1.0, 2.0, 0.0)
    assert res["per_episode"]["success"] == [True, False, True] and res["per_episode"]["a"][:2] == [1.0, 3.0]


def test_evaluate_inbetween_on_pd_tracking(hum, lib):
    mdp = _mdp(hum, lib, 2, seed=1, termination="mean")  # PD tracking drifts a hand past 0.5 m, not the mean
    res = evaluate_inbetween(mdp, lambda obs, goal: np.zeros((len(obs), mdp.action_dim)), 3)
    assert res["episodes"] == 3 and res["keyframes_per_window"] == 4 and len(res["per_episode"]["success"]) == 3
    assert res["success_rate"] == 1.0 and res["seconds_mean"] == pytest.approx(17 / 30)
    for m in ("mpjpe_mm", "g_mpjpe_mm", "vel_err_mm", "acc_err_mm"):
        for pre in ("", "keyframe_"):
            # the summary over episodes is the population mean and std of the per-episode values
            v = np.asarray(res["per_episode"][f"{pre}{m}"])
            assert res[f"{pre}{m}_mean"] == pytest.approx(v.mean()) and res[f"{pre}{m}_std"] == pytest.approx(v.std())
    assert 0 < res["mpjpe_mm_mean"] < 150 and res["g_mpjpe_mm_mean"] >= res["mpjpe_mm_mean"] * 0.5
    assert mdp.task.num_keyframes == 3  # restored after evaluating with eval_keyframes
    with pytest.raises(UserError, match="episodes"):
        evaluate_inbetween(mdp, lambda o, g: np.zeros((2, mdp.action_dim)), 0)


def test_evaluation_plays_failed_windows_to_their_end(hum, lib):
    """Table 2's errors are over whole windows: with a failure test that fires within a few frames
    (1 cm mean body distance), the same windows give the same errors as when nothing fails, every
    episode is a failure, and its seconds stop where the test first fired."""
    _, _, mdp = played_to_the_end(evaluate_inbetween,
                                  lambda **kw: _mdp(hum, lib, 2, seed=1, termination="mean", **kw), 0.01,
                                  [pre + m for m in ("mpjpe_mm", "g_mpjpe_mm", "vel_err_mm", "acc_err_mm")
                                   for pre in ("", "keyframe_")], 17 / 30)
    mdp.reset()
    for _ in range(3):
        _, _, _, term, _, info = mdp.step(np.zeros((2, mdp.action_dim)))
        if term.any():
            break
    assert term.any() and np.array_equal(term, info["off_track"])




