"""The steering task (motok.control.tasks.steering): its goal and reward against hand values, the
task on the real humanoid (commands that change within their range, truncation, a fall), its
evaluation, and a tiny real chain: a toy expert and hybrid prior, a steering policy trained over
the prior through `motok control train`, resumed exactly, evaluated and rendered through
`motok control eval`."""

from __future__ import annotations

import json
import math
from dataclasses import replace

import numpy as np
import pytest
import torch
from typer.testing import CliRunner

from motok.control.highlevel.evaluate import evaluate_run
from motok.control.highlevel.policy import TaskTrainConfig, load_task_run
from motok.control.highlevel.train import train_from_prior
from motok.control.tasks.steering import (SteeringTask, SteeringTaskConfig, angle_between, command_goal,
                                          evaluate_steering, steering_reward)
from motok.errors import UserError
from motok.sim.reference import load_library
from task_helpers import task_mdp
from tiny_runs import tiny_prior_bundle

pytestmark = pytest.mark.usefixtures("one_thread")


# ----------------------------------------------------------------------------- pure terms

def test_goal_is_the_command_in_the_heading_frame():
    """A root facing world +Y (heading 90 deg) commanded to walk along world +X sees the command
    on its right, (0, -1), with the speed as the third number."""
    g = command_goal(np.array([0.0]), np.array([1.0]), np.array([0.0]), np.array([1.2]))
    assert np.allclose(g, [[0.0, -1.0, 1.2]])
    g = command_goal(np.array([1.0]), np.array([0.0]), np.array([math.pi / 2]), np.array([0.5]))  # facing +X
    assert np.allclose(g, [[0.0, 1.0, 0.5]])


def test_reward_against_hand_values():
    cfg = SteeringTaskConfig()
    # on command: walking along +X at 1 m/s, facing +X, commanded +X at 1 m/s -> r = w_vel + w_face
    r = steering_reward(np.array([[1.0, 0.0, 0.0]]), np.array([1.0]), np.array([0.0]), np.array([0.0]),
                        np.array([1.0]), cfg)
    assert r["r_task"][0] == pytest.approx(cfg.w_vel + cfg.w_face)
    # standing, facing +Y, commanded +X at 1 m/s: |v* - v|^2 = 1, the facing term 0
    r = steering_reward(np.zeros((1, 3)), np.array([0.0]), np.array([1.0]), np.array([0.0]), np.array([1.0]), cfg)
    assert r["r_vel"][0] == pytest.approx(math.exp(-cfg.k_vel)) and r["r_face"][0] == pytest.approx(0.0)
    assert angle_between(np.array([0.0]), np.array([-1.0]), np.array([math.pi / 2]))[0] == pytest.approx(180.0)


def test_config_errors_name_the_field():
    with pytest.raises(UserError, match="min_command_seconds <= max_command_seconds"):
        SteeringTaskConfig(min_command_seconds=3.0, max_command_seconds=2.0)
    with pytest.raises(UserError, match="episode_seconds"):
        SteeringTaskConfig(episode_seconds=0.0)


# ----------------------------------------------------------------------------- the task

def test_commands_change_within_their_range_and_episodes_truncate(hum, lib):
    cfg = SteeringTaskConfig(episode_seconds=4.0, min_command_seconds=0.5, max_command_seconds=1.0,
                             early_termination=False)
    mdp = task_mdp(SteeringTask, cfg, hum, lib, 3, base="current")
    obs, goal = mdp.reset()
    task, hz = mdp.task, mdp.env.control_hz
    assert goal.shape == (3, 3) and np.allclose(np.hypot(goal[:, 0], goal[:, 1]), 1.0)
    assert ((cfg.min_speed <= goal[:, 2]) & (goal[:, 2] <= cfg.max_speed)).all()
    changes, last, since = [], task.heading.copy(), np.zeros(3, dtype=int)
    zero = np.zeros((3, mdp.action_dim))
    for t in range(task.max_steps):
        obs, goal, rewards, term, trunc, info = mdp.step(zero)
        since += 1
        new = task.heading != last
        changes += since[new].tolist()
        since[new], last = 0, task.heading.copy()
        assert (rewards["r_task"] >= 0).all() and (rewards["r_task"] <= cfg.w_vel + cfg.w_face + 1e-9).all()
        if t < task.max_steps - 1:
            assert not (term | trunc).any()
    assert trunc.all() and (info["episode_steps"] == round(4.0 * hz)).all()
    assert changes and min(changes) >= round(0.5 * hz) and max(changes) <= round(1.0 * hz)
    m = task.markers()
    assert m.shape == (3, 10, 3) and np.allclose(m[:, :, 2], 0.1)


def test_a_dropped_humanoid_falls_and_the_evaluation_counts_it(hum, lib):
    mdp = task_mdp(SteeringTask, SteeringTaskConfig(episode_seconds=2.0), hum, lib, 2, base="current")
    limp = lambda obs, goal: np.full((len(obs), mdp.action_dim), 3.0)  # noqa: E731  (PD targets far off: it collapses)
    res = evaluate_steering(mdp, limp, 4)
    assert res["episodes"] == 4 and res["falls_per_episode"] > 0
    assert set(res) >= {f"{k}_{s}" for k in ("heading_error_deg", "speed_error", "velocity_error") for s in ("mean", "median")}
    hold = lambda obs, goal: np.zeros((len(obs), mdp.action_dim))  # noqa: E731
    res = evaluate_steering(task_mdp(SteeringTask, SteeringTaskConfig(episode_seconds=2.0, settle_seconds=0.5),
                                     hum, lib, 2, base="current"), hold, 2)
    assert res["steps_measured"] > 0 and 0.0 <= res["heading_error_deg_mean"] <= 180.0
    assert res["speed_error_mean"] >= 0.0 and res["mean_reward"] > 0.0


def test_given_starts_lie_inside_their_clips(hum, lib):
    mdp = task_mdp(SteeringTask, SteeringTaskConfig(), hum, lib, 2, base="current")
    mdp.reset(clips=[0, 1], frames=[0, 2])
    assert mdp.task.steps.tolist() == [0, 0]
    with pytest.raises(UserError, match=r"^steering task: start frames \[\d+\] are outside their clips"):
        mdp.reset(clips=[0, 1], frames=[0, int(lib.lengths[1])])


# ----------------------------------------------------------------------------- a tiny real chain

@pytest.fixture(scope="module")
def tiny_prior(hum, small_dataset, tmp_path_factory):
    lib = load_library(hum, small_dataset, clips=[0, 1, 2], cache_dir=tmp_path_factory.mktemp("steer-ref"))
    return tiny_prior_bundle(tmp_path_factory.mktemp("steer-runs"), hum, lib, small_dataset)


def test_steering_over_a_prior_trains_resumes_evaluates_and_renders(tiny_prior, tmp_path):
    cfg = TaskTrainConfig(task="steering", iterations=4, save_every=2, eval_every=2, eval_episodes=2)
    cfg.env.num_envs, cfg.env.nthread = 4, 1
    cfg.net.policy = cfg.net.value = [16]
    cfg.ppo = replace(cfg.ppo, horizon=8, minibatch_size=16, epochs=1)
    cfg.tasks.steering = replace(cfg.tasks.steering, episode_seconds=1.0, min_command_seconds=0.3,
                                 max_command_seconds=0.6, settle_seconds=0.1)
    train_from_prior(replace(cfg), tiny_prior, tmp_path / "straight", codebooks=2)
    train_from_prior(replace(cfg), tiny_prior, tmp_path / "split", codebooks=2, until=2)
    train_from_prior(replace(cfg), tiny_prior, tmp_path / "split", codebooks=2, resume=True)
    a, b = load_task_run(tmp_path / "straight"), load_task_run(tmp_path / "split")
    assert all(torch.equal(v, b[2].state_dict()[k]) for k, v in a[2].state_dict().items())
    rows = [json.loads(x) for x in (tmp_path / "split" / "metrics.jsonl").read_text().splitlines()]
    assert [r["iteration"] for r in rows] == [1, 2, 3, 4] and "eval_heading_error_deg_mean" in rows[1]
    assert a[-1]["extra"]["task"] == "steering" and a[-1]["extra"]["goal_dim"] == 3
    res = evaluate_run(tmp_path / "straight", episodes=3, render=tmp_path / "steer.gif")
    assert res["written"].endswith("eval_steering.json") and res["episodes"] == 3
    assert 0.0 <= res["heading_error_deg_mean"] <= 180.0 and res["falls_per_episode"] >= 0
    assert (tmp_path / "steer.gif").stat().st_size > 0
    from motok.cli.main import app
    r = CliRunner().invoke(app, ["-q", "control", "eval", "--task", "steering", "--run", str(tmp_path / "split"),
                                 "-n", "2", "--json"])
    assert r.exit_code == 0, r.output
    assert json.loads(r.output)["task"] == "steering"
    r = CliRunner().invoke(app, ["control", "train", "--help"])
    assert "steering" in r.output


def test_the_recipe_loads_and_trains_in_navigation_s_world():
    from pathlib import Path

    from motok.config import load_config
    root = Path(__file__).resolve().parent.parent / "recipes" / "control"
    steer, nav = (load_config(TaskTrainConfig, root / f"task_{n}.yaml") for n in ("steering", "navigation"))
    assert steer.task == "steering" and steer.tasks.steering == SteeringTaskConfig()
    assert steer.env == nav.env and steer.ppo == nav.ppo and steer.net == nav.net
    assert steer.continuous_lr == nav.continuous_lr
