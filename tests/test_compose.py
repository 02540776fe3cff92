"""The composed task (motok.control.tasks.compose): its hand goal and reward against hand values,
both goals' rewards and success on hand-made states of the real humanoid, its evaluation (both
goals, falls, the episodes' bodies for motion matching), and a tiny real chain: a policy over a
toy hybrid prior trained, evaluated with motion matching and rendered through `motok control eval`."""

from __future__ import annotations

import json
import math
from dataclasses import replace
from functools import partial

import numpy as np
import pytest
from typer.testing import CliRunner

from motok.control.highlevel.evaluate import evaluate_run
from motok.control.highlevel.policy import TaskTrainConfig
from motok.control.highlevel.train import train_from_prior
from motok.control.mdp.navigation import navigation_reward
from motok.control.tasks import registry
from motok.control.tasks.compose import ComposeTask, ComposeTaskConfig, evaluate_compose, hand_goal, hand_reward
from motok.control.tasks.navigation import NavigationTaskConfig
from motok.errors import UserError
from task_helpers import place, rz, task_mdp, tiny_prior_on_three_clips, tiny_task_config

pytestmark = pytest.mark.usefixtures("one_thread")


def test_hand_goal_and_reward_by_hand():
    """A root at (1, 2, 1) facing world +Y, the hand 0.3 m along +Y and 0.4 m up: in the heading
    frame the hand is 0.3 m ahead, 0.4 m up; a target 0.2 m to its right of that is (0, -0.2, 0) away."""
    g = hand_goal(np.array([[1.0, 2.0, 1.0]]), rz(90)[None], np.array([[1.0, 2.3, 1.4]]),
                  np.array([[0.3, -0.2, 0.4]]))
    assert np.allclose(g, [[0.3, -0.2, 0.4, 0.0, -0.2, 0.0]])
    cfg = ComposeTaskConfig()
    assert hand_reward(np.array([0.2]), cfg)["r_hand"][0] == pytest.approx(math.exp(-10 * 0.04))
    with pytest.raises(UserError, match="target_min"):
        ComposeTaskConfig(target_min=[0.5, 0.0, 0.0], target_max=[0.4, 0.1, 0.1])


def compose_mdp(hum, lib, n=2, nav: NavigationTaskConfig | None = None, **kw):
    return task_mdp(partial(ComposeTask, nav=nav), ComposeTaskConfig(**kw), hum, lib, n, base="current")


def test_both_goals_rewards_and_success_on_hand_made_states(hum, lib):
    mdp = compose_mdp(hum, lib)
    task = mdp.task
    obs, goal = mdp.reset()
    assert goal.shape == (2, 8) and task.goal_parts == {"lower": slice(0, 2), "upper": slice(2, 8)}
    # the same library frame in both environments; env 0's hand target is its hand, env 1's is 1 m above it
    place(mdp, [0, 1], [100, 100])
    b = mdp.env.bodies
    rel = hand_goal(b.pos[:, 0], b.rot[:, 0], b.pos[:, task.hand], np.zeros((2, 3)))[:, 3:] * -1
    task.set_hand_targets([0, 1], rel + np.array([[0.0, 0.0, 0.0], [0.0, 0.0, 1.0]]))
    task.set_targets([0, 1], b.pos[:, 0, :2] + np.array([[3.0, 0.0], [0.0, 4.0]]))
    g = mdp.task.goal()
    assert np.allclose(g[:, 5:], [[0, 0, 0], [0, 0, 1.0]], atol=1e-9)  # target minus hand
    assert np.allclose(task.hand_distance(), [0.0, 1.0], atol=1e-9)
    assert np.allclose(task.hand_target()[1] - b.pos[1, task.hand], [0.0, 0.0, 1.0])  # 1 m up, in the world too
    _, _, r, term, trunc, info = mdp.step(np.zeros((2, mdp.action_dim)))
    b = mdp.env.bodies
    d = info["hand_error"]
    assert d[0] < 0.05 and abs(d[1] - 1.0) < 0.05  # one step of a held pose moves the hand by centimetres
    nav = navigation_reward(b.pos[:, 0], b.vel[:, 0], b.rot[:, 0], task.target, task.cfg)["r_task"]
    assert np.allclose(r["r_nav"], nav) and np.allclose(r["r_hand"], np.exp(-10.0 * d ** 2))
    assert np.allclose(r["r_task"], 0.5 * nav + 0.5 * np.exp(-10.0 * d ** 2))
    assert info["hand_target_reached"].tolist() == [True, False]


def test_hand_targets_change_every_target_seconds_inside_their_box(hum, lib):
    nav = NavigationTaskConfig(episode_seconds=1.0, early_termination=False)
    mdp = compose_mdp(hum, lib, nav=nav, target_seconds=0.2)
    mdp.reset()
    task, seen = mdp.task, []
    for t in range(1, 31):
        before = task.offset.copy()
        _, _, _, term, trunc, info = mdp.step(np.zeros((2, mdp.action_dim)))
        assert info["hand_target_ends"].all() == (t % 6 == 0)  # 0.2 s at 30 Hz: 6 steps
        seen.append(before)
        if t % 6 == 0 and t < 30:
            assert not np.allclose(before, task.offset)
    seen = np.concatenate(seen)
    assert (seen >= np.array(task.compose.target_min) - 1e-12).all()
    assert (seen <= np.array(task.compose.target_max) + 1e-12).all()


def test_joining_mid_episode_draws_both_goals_from_where_the_character_is(hum, lib):
    mdp = compose_mdp(hum, lib)
    mdp.reset()
    zero = np.zeros((2, mdp.action_dim))
    for _ in range(3):
        mdp.step(zero)
    task = mdp.task
    before = (task.offset.copy(), task.target.copy(), mdp.env.qpos.copy())
    task.join([1])
    assert np.array_equal(mdp.env.qpos, before[2])  # the character is not moved
    assert task.steps.tolist() == [3, 0] and task.hand_steps.tolist() == [3, 0]
    assert np.array_equal(task.offset[0], before[0][0]) and not np.allclose(task.offset[1], before[0][1])
    d = np.hypot(*(task.target[1] - mdp.env.bodies.pos[1, 0, :2]))
    assert task.cfg.min_distance <= d <= task.cfg.max_distance and not np.allclose(task.target[1], before[1][1])


def test_the_evaluation_counts_both_goals_and_keeps_every_episode_s_bodies(hum, lib):
    mdp = compose_mdp(hum, lib, nav=NavigationTaskConfig(episode_seconds=1.0, early_termination=False),
                      target_seconds=0.5)
    hold = lambda obs, goal: np.zeros((len(obs), mdp.action_dim))  # noqa: E731
    res = evaluate_compose(mdp, hold, 3)
    assert res["episodes"] == 3 and res["targets"] == 3  # one 4 s navigation target per 1 s episode
    assert res["hand_targets"] == 6  # two 0.5 s hand targets per episode
    assert len(res["motion_bodies"]) == 3 and all(b.shape == (31, 21, 3) for b in res["motion_bodies"])
    assert 0.0 <= res["hand_reached_share"] <= 1.0 and res["hand_error_mean_m"] > 0.0


# ----------------------------------------------------------------------------- a tiny real chain

@pytest.fixture(scope="module")
def tiny_prior(hum, small_dataset, tmp_path_factory):
    return tiny_prior_on_three_clips(hum, small_dataset, tmp_path_factory, "compose")


def test_compose_over_a_prior_trains_evaluates_with_motion_matching_and_renders(tiny_prior, tmp_path):
    cfg = tiny_task_config("compose")
    cfg.tasks.navigation = replace(cfg.tasks.navigation, episode_seconds=1.0, retarget_seconds=0.5)
    cfg.tasks.compose = replace(cfg.tasks.compose, target_seconds=0.5)
    train_from_prior(cfg, tiny_prior, tmp_path / "compose", codebooks=2)
    res = evaluate_run(tmp_path / "compose", episodes=2, render=tmp_path / "compose.mp4")
    assert res["written"].endswith("eval_compose.json") and res["episodes"] == 2
    assert res["motion_transitions"] > 0 and "motion_bodies" not in res
    assert {"reached_share", "hand_reached_share", "hand_error_mean_m", "falls_per_episode",
            "motion_filtered_rate"} <= set(res)
    assert (tmp_path / "compose.mp4").stat().st_size > 0
    assert json.loads((tmp_path / "compose" / "eval_compose.json").read_text())["task"] == "compose"
    from motok.cli.main import app
    r = CliRunner().invoke(app, ["control", "train", "--help"])
    assert "compose" in r.output and "multitask" in r.output
    assert {"compose", "multitask"} <= set(registry.names())


def test_the_recipe_is_navigation_s_with_the_hand_goal():
    from pathlib import Path

    from motok.config import load_config
    root = Path(__file__).resolve().parent.parent / "recipes" / "control"
    comp, nav = (load_config(TaskTrainConfig, root / f"task_{n}.yaml") for n in ("compose", "navigation"))
    assert comp.task == "compose" and comp.tasks.compose == ComposeTaskConfig()
    assert comp.tasks.navigation == nav.tasks.navigation
    assert (comp.env, comp.ppo, comp.net, comp.iterations) == (nav.env, nav.ppo, nav.net, nav.iterations)
