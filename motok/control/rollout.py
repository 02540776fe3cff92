"""One rollout collector for every PPO trainer of the control stage.

Per iteration, ``horizon`` steps of every environment of a :class:`~motok.control.tasks.base.TaskEnv`:
the policy input ``[s, s~]`` (Eq. 7 and the task's goal) is normalised by the running statistics
(updated first, as the policy then sees it), an action is drawn, the MDP steps, and a truncated
episode's final observation is valued *before* its reset so GAE can bootstrap it (PPO trick 4).

The reward is ``w_task r_task + sum_h w_h r_h``: ``r_task`` the task's main term
(``task.reward_key``), ``r_h`` the terms of learned reward hooks such as AMP's style reward,
computed on the stored transitions ``(s, s')`` after the rollout and then trained on them.
Episode statistics (return, main reward per step, length, share truncated rather than
terminated) are kept across iterations per environment.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Protocol

import numpy as np
import torch

from motok.control.networks import ActorCritic
from motok.control.ppo import Rollout
from motok.control.tasks.base import TaskEnv


def as_tensor(a) -> torch.Tensor:
    """float32 tensor of ``a``; a diverged env may hold non-finite rows, which become finite."""
    return torch.as_tensor(np.nan_to_num(np.asarray(a, dtype=np.float32)))


class RewardHook(Protocol):
    """A learned reward on transitions, e.g. :class:`motok.control.amp.AMPHook`."""

    name: str  # logged as this key, e.g. "r_style"
    weight: float

    def reward(self, s: torch.Tensor, s2: torch.Tensor) -> torch.Tensor: ...

    def update(self, s: torch.Tensor, s2: torch.Tensor) -> dict[str, float]: ...


@dataclass
class Episodes:
    """Running per-environment episode sums; ``add`` returns the statistics of the episodes it closed."""

    ret: np.ndarray
    main: np.ndarray
    length: np.ndarray

    @classmethod
    def empty(cls, n: int) -> "Episodes":
        return cls(np.zeros(n), np.zeros(n), np.zeros(n, dtype=np.int64))

    def add(self, ro: Rollout, main: torch.Tensor, key: str, dt: float) -> dict:
        rets, mains, lens, succ = [], [], [], []
        for t in range(len(ro.rewards)):
            self.ret += ro.rewards[t].numpy()
            self.main += main[t].numpy()
            self.length += 1
            done = (ro.terminated[t] | ro.truncated[t]).numpy()
            if done.any():
                rets += self.ret[done].tolist()
                mains += (self.main[done] / self.length[done]).tolist()
                lens += self.length[done].tolist()
                succ += ro.truncated[t].numpy()[done].tolist()  # ended without failing: clip end or time limit
                self.ret[done], self.main[done], self.length[done] = 0.0, 0.0, 0
        if not rets:
            return {}
        return {"episode_return": float(np.mean(rets)), f"episode_{key}": float(np.mean(mains)),
                "episode_seconds": float(np.mean(lens)) * dt, "success": float(np.mean(succ)), "episodes": len(rets)}


class Collector:
    """``start()`` begins fresh episodes everywhere; ``collect()`` returns ``(rollout, last_value, stats)``."""

    def __init__(self, mdp: TaskEnv, ac: ActorCritic, horizon: int, task_weight: float = 1.0,
                 hooks: tuple[RewardHook, ...] = ()):
        self.mdp, self.ac, self.horizon, self.task_weight, self.hooks = mdp, ac, horizon, task_weight, tuple(hooks)
        self.key = mdp.task.reward_key

    def start(self) -> None:
        self.obs, self.goal = self.mdp.reset()
        self.episodes = Episodes.empty(self.mdp.num_envs)

    def _input(self, obs, goal) -> torch.Tensor:
        return as_tensor(np.concatenate([obs, goal], 1))

    def collect(self) -> tuple[Rollout, torch.Tensor, dict]:
        mdp, ac, T, N = self.mdp, self.ac, self.horizon, self.mdp.num_envs
        pol = ac.policy
        ro = Rollout(T, N, mdp.obs_dim + mdp.goal_dim, pol.action_shape, pol.action_dtype)
        keep = bool(self.hooks)
        s = torch.zeros(T, N, mdp.obs_dim) if keep else None
        s2 = torch.zeros(T, N, mdp.obs_dim) if keep else None
        main = torch.zeros(T, N)
        for t in range(T):
            x = self._input(self.obs, self.goal)
            ac.norm.update(x)
            xn, a, logp, v = ac.act(x)
            obs, goal, rewards, term, trunc, _ = mdp.step(a.numpy())
            main[t] = torch.from_numpy(rewards[self.key])
            ro.x[t], ro.actions[t], ro.logp[t], ro.values[t] = xn, a, logp, v
            ro.terminated[t], ro.truncated[t] = torch.from_numpy(term), torch.from_numpy(trunc)
            if keep:
                s[t], s2[t] = as_tensor(self.obs), as_tensor(obs)
            if trunc.any():  # bootstrapping needs the value of the final observation, before the reset
                with torch.no_grad():
                    xf = ac.norm(self._input(obs[trunc], goal[trunc]))
                    ro.final_values[t, torch.from_numpy(trunc)] = ac.value(xf)
            done = term | trunc
            if done.any():
                obs, goal = mdp.reset(np.flatnonzero(done))
            self.obs, self.goal = obs, goal
        with torch.no_grad():
            last_value = ac.value(ac.norm(self._input(self.obs, self.goal)))
        terms = {h.name: h.reward(s.flatten(0, 1), s2.flatten(0, 1)).view(T, N) for h in self.hooks}
        ro.rewards = self.task_weight * main
        for h in self.hooks:
            ro.rewards = ro.rewards + h.weight * terms[h.name]
        stats = self.episodes.add(ro, main, self.key, mdp.dt)
        stats.update({self.key: float(main.mean()), **{k: float(v.mean()) for k, v in terms.items()},
                      "reward": float(ro.rewards.mean())})
        for h in self.hooks:
            stats.update(h.update(s.flatten(0, 1), s2.flatten(0, 1)))
        return ro, last_value, stats
