"""The MDP a policy acts in: physics (``HumanoidEnv``) + a task + an action map.

A task (:class:`Task`, the base of the tasks in ``motok.control.tasks``) has

* ``goal_dim`` and ``reward_key`` (the name of its main reward term, e.g. ``"r_im"``);
* ``reset(ids, **where)``: put environments ``ids`` in start states (through ``env.set_state``);
* ``goal() -> (N, goal_dim)``: the task part of the policy input, after a reset or step;
* ``update(diverged, invalid) -> (rewards, terminated, truncated, info)`` after a physics step,
  ``rewards`` a dict of ``(N,)`` terms that holds ``reward_key``;

and, where it differs from the base's, what generic code asks of it: ``markers()`` and
``caption()`` for videos, ``step_limit()`` for tests that need an episode's length,
``for_evaluation()`` for a video of the episodes its evaluation plays, ``build()`` for a task
made of other tasks (it reads their settings), ``join()`` for a task that can take over an episode
in progress (a switch of task mid-episode).

There is no auto-reset: the caller reads the final observation (for bootstrapping truncated
episodes) and then calls ``reset(ids)`` for the finished environments.

With an ``on_device`` environment everything crossing this interface (ids, actions, observations,
goals, rewards, masks) is a torch tensor on the physics device.
"""

from __future__ import annotations

from typing import Callable

import numpy as np

from motok.arrays import is_tensor, like
from motok.sim.env import HumanoidEnv

ActionMap = Callable[[np.ndarray, HumanoidEnv, "Task"], np.ndarray]  # (actions, env, task) -> PD targets


class Task:
    """What a policy is asked to do, with its episode state and its random generator."""

    goal_dim: int
    reward_key: str = "r_task"
    marker_radius: float = 0.12  # m, the dots :meth:`markers` draws in videos (one, or one per marker)
    marker_rgba: tuple = (0.9, 0.2, 0.2, 0.8)  # their colour (one, or one per marker)
    # The task can start in an episode under way (:meth:`join`): its goal is drawn from the
    # character's current state. Tasks whose goal is a reference motion cannot: their reference
    # starts where their own start state was set.
    joins_mid_episode: bool = False

    @classmethod
    def build(cls, cfg, env, lib, rng, cfgs=None) -> "Task":
        """The task with its settings ``cfg``; ``cfgs`` holds every task's settings (a
        ``TaskConfigs``), which a task made of other tasks reads theirs from."""
        return cls(cfg, env, lib, rng)

    def reset(self, ids: np.ndarray, **where) -> None:  # pragma: no cover - every task defines it
        raise NotImplementedError

    def goal(self) -> np.ndarray:  # pragma: no cover - every task defines it
        raise NotImplementedError

    def update(self, diverged: np.ndarray, invalid: np.ndarray) -> tuple[dict, np.ndarray, np.ndarray, dict]:
        raise NotImplementedError  # pragma: no cover - every task defines it

    def markers(self) -> np.ndarray | None:
        """``(N, K, 3)`` world points a video draws (targets, keyframes, a head); None: nothing."""
        return None

    def caption(self) -> list[str] | None:
        """Per environment, a word a video writes on each frame (the task under way); None: nothing."""
        return None

    def join(self, ids) -> None:
        """Take over environments ``ids`` in an episode under way without moving the character:
        a new goal from its current state, the task's episode clock restarted."""
        raise NotImplementedError(f"{type(self).__name__} cannot start in an episode under way")

    def step_limit(self):
        """Each environment's episode length in control steps (``(N,)`` or one number)."""
        return np.iinfo(np.int64).max

    def for_evaluation(self) -> None:
        """Switch to the settings the task's evaluation plays with, for a video of such an episode
        (every environment must be reset afterwards)."""


class TaskEnv:
    """``reset`` / ``step`` over physics, task and action map; see the module docstring."""

    def __init__(self, env: HumanoidEnv, task: Task, action_map: ActionMap):
        self.env, self.task, self.action_map = env, task, action_map
        self.num_envs, self.dt = env.num_envs, env.dt
        self._started = False

    @property
    def obs_dim(self) -> int:
        return self.env.obs_dim

    @property
    def goal_dim(self) -> int:
        return self.task.goal_dim

    @property
    def action_dim(self) -> int:
        return self.env.action_dim

    def reset(self, ids=None, **where) -> tuple[np.ndarray, np.ndarray]:
        """Start new episodes in ``ids`` (all by default); returns the full ``(obs, goal)`` arrays."""
        N = self.num_envs
        if self.env.on_device:  # ids from the rollout itself (device tensors): not checked on the host
            q = self.env.qpos
            ids = like(q, np.arange(N)) if ids is None else ids if is_tensor(ids) else like(q, np.atleast_1d(ids))
        else:
            ids = np.arange(N) if ids is None else np.atleast_1d(np.asarray(ids, dtype=np.int64))
            if ids.size and (ids.min() < 0 or ids.max() >= N):
                raise IndexError(f"environment ids must be in 0..{N - 1}, got {ids.tolist()}")
        if not self._started and len(ids) != N:
            self.reset()  # every environment needs an episode before a subset can be restarted
        self._started = True
        self.task.reset(ids, **where)
        return self.env.observation(), self.task.goal()

    def restart_done(self, done, obs, goal):
        """Reset the environments whose episode ended (``done`` mask) and return the full
        ``(obs, goal)``; unchanged when none did. On the device the ids come from ``nonzero``, whose
        size is the one number read on the host per step."""
        ids = done.nonzero().flatten() if self.env.on_device else np.flatnonzero(done)
        return self.reset(ids) if len(ids) else (obs, goal)

    def launch(self, actions: np.ndarray, threaded: bool = True) -> None:
        """Start a control step (physics on a worker thread when ``threaded``); :meth:`finish` ends it."""
        if not self._started:
            raise RuntimeError("call reset() before step()")
        a = actions if is_tensor(actions) else np.asarray(actions)
        if a.ndim < 1 or len(a) != self.num_envs:
            raise ValueError(f"actions must have {self.num_envs} rows, got shape {tuple(a.shape)}")
        self.env.launch(self.action_map(a, self.env, self.task), threaded)

    def finish(self):
        """``(obs, goal, rewards, terminated, truncated, info)`` of the step in flight."""
        diverged, invalid = self.env.finish()
        rewards, terminated, truncated, info = self.task.update(diverged, invalid)
        return self.env.observation(), self.task.goal(), rewards, terminated, truncated, info

    def step(self, actions: np.ndarray):
        """``(obs, goal, rewards, terminated, truncated, info)`` after one control step."""
        self.launch(actions, threaded=False)
        return self.finish()
