"""Helpers the task tests share: a task MDP on the real humanoid, yaw rotations, placing
environments exactly in library frames, an evaluation played to the end."""

from __future__ import annotations

import math
from functools import partial

import numpy as np
import pytest

from motok.control.mdp.actions import ActionConfig, pd_targets
from motok.control.mdp.task_env import TaskEnv
from motok.sim.env import HumanoidEnv, SimConfig


def task_mdp(task_cls, cfg, hum, lib, n, seed=0, base="reference") -> TaskEnv:
    """``n`` environments of ``task_cls(cfg)`` with residual PD targets on ``base``."""
    env = HumanoidEnv(hum, SimConfig(num_envs=n, nthread=1))
    return TaskEnv(env, task_cls(cfg, env, lib, np.random.default_rng(seed)), partial(pd_targets, ActionConfig(base)))


def rz(deg: float) -> np.ndarray:
    c, s = math.cos(math.radians(deg)), math.sin(math.radians(deg))
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


def place(mdp, ids, g, shift=(0.0, 0.0, 0.0)):
    """Put environments ``ids`` exactly in library rows ``g``, the root moved by ``shift`` (m)."""
    q, v = mdp.task.lib.qpos[g].copy(), mdp.task.lib.qvel[g].copy()
    q[:, :3] += shift
    mdp.env.set_state(np.asarray(ids), q, v)


def played_to_the_end(evaluate, make_mdp, tight: float, metrics, seconds: float, episodes: int = 3):
    """Whole-episode evaluation (Tables 2-3): ``make_mdp()`` and ``make_mdp(termination_distance=tight)``
    (a failure test that fires within a few frames) evaluated with a zero policy on the same episodes
    give the same ``metrics`` (``*_mean`` keys); none of the tight ones succeeds and their seconds stop
    where the test first fired. Returns both results and the tight MDP."""
    def zero(obs, goal):
        return np.zeros((len(obs), mdp.action_dim))
    mdp = make_mdp()
    ok = evaluate(mdp, zero, episodes)
    mdp = make_mdp(termination_distance=tight)
    bad = evaluate(mdp, zero, episodes)
    assert ok["success_rate"] == 1.0 and bad["success_rate"] == 0.0
    assert 0 < bad["seconds_mean"] < ok["seconds_mean"] == pytest.approx(seconds)
    for m in metrics:
        assert bad[f"{m}_mean"] == pytest.approx(ok[f"{m}_mean"], rel=1e-9)
    assert mdp.task.cfg.early_termination  # training still ends an episode at the failure
    return ok, bad, mdp


def tiny_task_config(task: str):
    """A 2-iteration policy of 16-unit networks on 4 environments, evaluated on 2 episodes at the end."""
    from dataclasses import replace

    from motok.control.highlevel.policy import TaskTrainConfig

    cfg = TaskTrainConfig(task=task, iterations=2, save_every=2, eval_every=2, eval_episodes=2)
    cfg.env.num_envs, cfg.env.nthread = 4, 1
    cfg.net.policy = cfg.net.value = [16]
    cfg.ppo = replace(cfg.ppo, horizon=8, minibatch_size=16, epochs=1)
    return cfg


def tiny_prior_on_three_clips(hum, data, tmp_path_factory, name: str):
    """``tiny_prior_bundle`` on the first three clips of ``data``, in fresh folders named ``name``."""
    from motok.sim.reference import load_library
    from tiny_runs import tiny_prior_bundle

    lib = load_library(hum, data, clips=[0, 1, 2], cache_dir=tmp_path_factory.mktemp(f"{name}-ref"))
    return tiny_prior_bundle(tmp_path_factory.mktemp(f"{name}-runs"), hum, lib, data)
