"""Helpers the task tests share: a task MDP on the real humanoid, yaw rotations, placing
environments exactly in library frames."""

from __future__ import annotations

import math
from functools import partial

import numpy as np

from motok.control.mdp.actions import ActionConfig, pd_targets
from motok.control.tasks.base import TaskEnv
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
