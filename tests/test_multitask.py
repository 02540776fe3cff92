"""The multitask task (motok.control.tasks.multitask): the goal's layout against hand-derived sizes,
the assignment of environments to sub-tasks, the active sub-task's reward against the single task's
on the same states, a switch of task mid-episode, and a tiny real chain: a multitask policy over a
toy hybrid prior trained, evaluated per sub-task and rendered with a switch."""

from __future__ import annotations

import json
from dataclasses import replace
from functools import partial

import numpy as np
import pytest

from motok.control.highlevel.evaluate import evaluate_run
from motok.control.highlevel.policy import TaskTrainConfig
from motok.control.highlevel.train import train_from_prior
from motok.control.mdp.actions import ActionConfig, pd_targets
from motok.control.mdp.task_env import TaskEnv
from motok.control.tasks import registry
from motok.control.tasks.multitask import MultitaskConfig, assignment, evaluate_switch, goal_layout
from motok.control.tasks.inbetween import InbetweenTask
from motok.control.tasks.navigation import NavigationTask
from motok.control.tasks.steering import SteeringTask
from motok.errors import UserError
from motok.sim.env import HumanoidEnv, SimConfig
from task_helpers import tiny_prior_on_three_clips, tiny_task_config

pytestmark = pytest.mark.usefixtures("one_thread")

ACT = partial(pd_targets, ActionConfig("current"))


def configs(**multi) -> object:
    cfgs = registry.TaskConfigs()
    cfgs.navigation = replace(cfgs.navigation, episode_seconds=2.0, early_termination=False)
    cfgs.steering = replace(cfgs.steering, episode_seconds=2.0, early_termination=False)
    cfgs.multitask = MultitaskConfig(**multi)
    return cfgs


def multitask_mdp(hum, lib, n, seed=0, **multi) -> TaskEnv:
    env = HumanoidEnv(hum, SimConfig(num_envs=n, nthread=1))
    cfgs = configs(**multi)
    return TaskEnv(env, registry.make("multitask", cfgs, env, lib, np.random.default_rng(seed)), ACT)


def test_goal_layout_by_hand(hum, lib):
    """21 bodies: in-betweening's goal is 2 keyframes x 21 bodies x (3 position + 6 rotation) = 378,
    head tracking's 5 frames x 15 = 75, navigation's 2, steering's 3; the one-hot comes first."""
    lay = goal_layout(["navigation", "inbetween", "hmd", "steering"], [2, 378, 75, 3])
    assert lay == {"task": slice(0, 4), "navigation": slice(4, 6), "inbetween": slice(6, 384),
                   "hmd": slice(384, 459), "steering": slice(459, 462)}
    mdp = multitask_mdp(hum, lib, 4, switch=[])
    mt = mdp.task
    assert mdp.goal_dim == 462 and mt.layout == lay
    _, goal = mdp.reset()
    assert goal.shape == (4, 462)
    for i in range(4):
        k = int(mt.active[i])
        assert goal[i, :4].tolist() == [float(j == k) for j in range(4)]
        for j, name in enumerate(mt.names):
            part = goal[i, lay[name]]
            assert np.array_equal(part, mt.subtasks[j].goal()[i]) if j == k else not part.any()


def test_assignment_round_robin_weights_and_seed():
    a = assignment(8, [1, 1, 1, 1], np.random.default_rng(0))
    assert np.bincount(a, minlength=4).tolist() == [2, 2, 2, 2]
    assert np.array_equal(a, assignment(8, [1, 1, 1, 1], np.random.default_rng(0)))
    assert not all(np.array_equal(a, assignment(8, [1, 1, 1, 1], np.random.default_rng(s))) for s in range(1, 4))
    assert np.bincount(assignment(8, [3, 1], np.random.default_rng(0))).tolist() == [6, 2]
    # one environment each first, then the remaining one by weight (10 of 13: task 0)
    assert np.bincount(assignment(5, [10, 1, 1, 1], np.random.default_rng(0))).tolist() == [2, 1, 1, 1]
    with pytest.raises(UserError, match="weights"):
        MultitaskConfig(weights=[1.0, 0.0, 1.0, 1.0])
    with pytest.raises(UserError, match="switch"):
        MultitaskConfig(switch=["later steering"])


def test_every_step_of_a_rollout_holds_every_task_and_resets_go_back_to_the_assigned_one(hum, lib):
    mdp = multitask_mdp(hum, lib, 4, tasks=["navigation", "steering"], switch=["0.2s steering"])
    mt = mdp.task
    mt.switching = True
    obs, goal = mdp.reset()
    zero = np.zeros((4, mdp.action_dim))
    hz = mdp.env.control_hz
    ends = []
    # 0.2 s on the assigned task, then 2 s of steering from the switch: every episode ends at 2.2 s
    for t in range(1, int(round(2.2 * hz)) + 2):
        obs, goal, rewards, term, trunc, info = mdp.step(zero)
        own = t <= round(0.2 * hz) or t > round(2.2 * hz)  # before the switch, or in the next episodes
        assert sorted(np.asarray(info["task"]).tolist()) == ([0, 0, 1, 1] if own else [1, 1, 1, 1])
        done = term | trunc
        if done.any():
            ends.append((t, np.flatnonzero(done).tolist()))
        obs, goal = mdp.restart_done(done, obs, goal)
    assert ends == [(int(round(2.2 * hz)), [0, 1, 2, 3])]
    assert np.array_equal(mt.active, mt.assigned)  # restarted on their own tasks, two of each


def same_episodes(single: TaskEnv, sub, ids) -> None:
    """The single task's episodes of ``ids`` made the multitask sub-task's ``sub``: its targets,
    commands, reference windows or head trajectories."""
    task = single.task
    if isinstance(task, NavigationTask):
        task.set_targets(ids, sub.target)
    elif isinstance(task, SteeringTask):
        task.set_commands(ids, sub.heading, sub.speed)
    elif isinstance(task, InbetweenTask):
        task.reset(ids, clips=sub.clip, frames=sub.start, keyframes=sub.keyframes - sub.start[:, None])
    else:
        task.reset(ids, clips=sub.clip, frames=sub.start)


def test_the_active_task_s_reward_is_the_single_task_s(hum, lib):
    """Same states and episodes (targets, commands, reference windows, head trajectories): each
    environment's multitask reward and episode end are those of its task alone on it."""
    mdp = multitask_mdp(hum, lib, 4, switch=[])
    mt = mdp.task
    mdp.reset()
    cfgs = configs()
    singles = []
    for name, sub in zip(mt.names, mt.subtasks):
        env = HumanoidEnv(hum, SimConfig(num_envs=4, nthread=1))
        single = TaskEnv(env, type(sub)(getattr(cfgs, name), env, lib, np.random.default_rng(5)), ACT)
        single.reset()
        same_episodes(single, sub, np.arange(4))
        env.set_state(np.arange(4), mdp.env.qpos.copy(), mdp.env.qvel.copy())
        singles.append(single)
    assert sorted(np.asarray(mt.active).tolist()) == [0, 1, 2, 3]
    rng = np.random.default_rng(1)
    for _ in range(5):
        a = 0.05 * rng.standard_normal((4, mdp.action_dim))
        _, _, r, term, trunc, _ = mdp.step(a)
        own = [s.step(a)[2:5] for s in singles]
        for i in range(4):
            k = int(mt.active[i])
            assert r["r_task"][i] == pytest.approx(own[k][0]["r_task"][i], rel=1e-12)
            assert (term[i], trunc[i]) == (own[k][1][i], own[k][2][i])
            # and not another task's reward on the same state
            assert all(r["r_task"][i] != pytest.approx(own[j][0]["r_task"][i]) for j in range(4) if j != k)


def test_a_switch_changes_the_one_hot_and_the_goal_at_its_step(hum, lib):
    mdp = multitask_mdp(hum, lib, 2, tasks=["navigation", "steering"], switch=["0.5s steering"])
    mt = mdp.task
    mt.for_evaluation()
    _, goal = mdp.reset()
    nav_env = int(np.flatnonzero(np.asarray(mt.assigned) == 0)[0])
    at = int(round(0.5 * mdp.env.control_hz))
    lay = mt.layout
    zero = np.zeros((2, mdp.action_dim))
    for t in range(1, at + 3):
        _, goal, *_ = mdp.step(zero)
        g = goal[nav_env]
        if t < at:
            assert g[lay["task"]].tolist() == [1.0, 0.0] and not g[lay["steering"]].any()
            assert mt.caption()[nav_env] == "navigation"
        else:
            assert g[lay["task"]].tolist() == [0.0, 1.0] and not g[lay["navigation"]].any()
            assert np.array_equal(g[lay["steering"]], mt.subtasks[1].goal()[nav_env])
            assert mt.caption()[nav_env] == "steering"
    # the steering clock restarted at the switch: its episode runs its own length from there
    assert mt.subtasks[1].steps[nav_env] == 2 and mt.step_limit()[nav_env] == mt.subtasks[1].max_steps
    m = mt.markers()
    assert m.shape == (2, 1 + 10, 3) and np.isnan(m[nav_env, 0]).all() and np.isfinite(m[nav_env, 1:]).all()
    with pytest.raises(UserError, match="cannot switch to hmd"):
        multitask_mdp(hum, lib, 2, tasks=["navigation", "hmd"], switch=["1s hmd"])


def test_the_switch_evaluation_counts_what_follows_the_switch(hum, lib):
    """No fall ends an episode here: every episode is switched at 0.2 s and then plays steering's
    whole 2 s; the rewards before and after are the per-step means of the task under way."""
    mdp = multitask_mdp(hum, lib, 2, tasks=["navigation", "steering"], switch=["0.2s steering"])
    seen = {"before": [], "after": []}  # both environments switch at the same step

    def hold(obs, goal):
        return np.zeros((len(obs), mdp.action_dim))

    step = mdp.step

    def watched(a):
        out = step(a)
        seen["after" if out[5]["switched"][0] else "before"].append(out[2]["r_task"])
        return out

    mdp.step = watched
    res = evaluate_switch(mdp, hold, 2)
    assert res["switched_share"] == 1.0 and res["failed_after_share"] == 0.0
    assert res["seconds_after_mean"] == pytest.approx(2.0)
    assert res["reward_before"] == pytest.approx(np.mean(seen["before"]))
    assert res["reward_after"] == pytest.approx(np.mean(seen["after"]))
    assert not mdp.task.switching  # switching is on only while the switch evaluation plays


# ----------------------------------------------------------------------------- a tiny real chain

@pytest.fixture(scope="module")
def tiny_prior(hum, small_dataset, tmp_path_factory):
    return tiny_prior_on_three_clips(hum, small_dataset, tmp_path_factory, "multi")


def test_multitask_over_a_prior_trains_evaluates_each_task_and_renders_a_switch(tiny_prior, tmp_path):
    cfg = tiny_task_config("multitask")
    t = cfg.tasks
    # no fall ends an episode: the video's length is the schedule's (the untrained policy falls)
    t.navigation = replace(t.navigation, episode_seconds=1.0, retarget_seconds=0.5, early_termination=False)
    t.steering = replace(t.steering, episode_seconds=1.0, min_command_seconds=0.3, max_command_seconds=0.6,
                         settle_seconds=0.1, early_termination=False)
    t.inbetween = replace(t.inbetween, window_seconds=1.0, num_keyframes=3, eval_keyframes=3, min_keyframe_gap_seconds=0.1)
    t.hmd = replace(t.hmd, episode_seconds=1.0)
    t.multitask = MultitaskConfig(switch=["0.5s steering"])
    train_from_prior(cfg, tiny_prior, tmp_path / "multi", codebooks=2)
    res = evaluate_run(tmp_path / "multi", episodes=2, render=tmp_path / "multi.mp4")
    assert res["tasks"] == ["navigation", "inbetween", "hmd", "steering"]
    for key in ("navigation.reached_share", "navigation.idle_transitions", "inbetween.success_rate",
                "inbetween.keyframe_mpjpe_mm_mean", "hmd.head_error_mm_mean", "steering.heading_error_deg_mean",
                "switch.switched_share"):
        assert key in res, key
    assert res["navigation.episodes"] == res["inbetween.episodes"] == res["steering.episodes"] == 2
    assert res["switch.switched_share"] + res["switch.failed_after_share"] >= 0
    # the command line evaluates it under another switching schedule (task settings only)
    from typer.testing import CliRunner

    from motok.cli.main import app
    r = CliRunner().invoke(app, ["-q", "control", "eval", "--task", "multitask", "--policy", str(tmp_path / "multi"),
                                 "-n", "1", "--set", 'tasks.multitask.switch=["0.2s navigation"]', "--json"])
    assert r.exit_code == 0, r.output
    out = json.loads(r.output)
    assert out["switch.episodes"] == 1 and out["task"] == "multitask"
    r = CliRunner().invoke(app, ["control", "eval", "--task", "multitask", "--policy", str(tmp_path / "multi"),
                                 "--set", "ppo.lr=1"])
    assert r.exit_code != 0 and "task settings only" in r.output

    import imageio.v3 as iio

    frames = iio.imread(tmp_path / "multi.mp4")
    iio.imwrite(tmp_path / "switched.png", frames[25])
    # one environment: navigation (the first task) for 0.5 s, then 1 s of steering from the switch
    assert len(frames) == 1 + round(0.5 * 30) + round(1.0 * 30)


def test_markers_are_drawn_at_their_own_radius_and_not_at_all_when_not_finite(hum, tmp_path):
    import imageio.v3 as iio

    from motok.sim.render import render_trajectory
    from test_sim_render import GREEN, green_pixels

    qpos = np.repeat(hum.model.qpos0[None], 2, 0)
    marks = np.array([[[3.0, 0.0, 0.1], [np.nan, np.nan, np.nan]]] * 2)
    px = {}
    for r in (0.1, 0.3):
        out, _ = render_trajectory(hum, qpos, tmp_path / f"r{r}.mp4", 30.0, markers=marks, marker_rgba=GREEN,
                                   marker_radius=np.array([r, 5.0]))
        px[r] = green_pixels(iio.imread(out)[0])
    assert px[0.3] > 4 * px[0.1] > 0  # the area grows with the square of the radius; the NaN one is nowhere


def test_the_recipe_is_the_four_task_recipes_at_their_total_samples():
    from pathlib import Path

    from motok.config import load_config
    root = Path(__file__).resolve().parent.parent / "recipes" / "control"
    multi = load_config(TaskTrainConfig, root / "task_multitask.yaml")
    assert multi.task == "multitask" and multi.tasks.multitask.tasks == ["navigation", "inbetween", "hmd", "steering"]
    for name in multi.tasks.multitask.tasks:
        own = load_config(TaskTrainConfig, root / f"task_{name}.yaml")
        assert getattr(multi.tasks, name) == getattr(own.tasks, name), name
        assert multi.env == own.env and multi.ppo == own.ppo and multi.net == own.net
        # a quarter of the environments over four times the iterations: each task's own samples
        assert multi.iterations * multi.env.num_envs // 4 == own.iterations * own.env.num_envs
