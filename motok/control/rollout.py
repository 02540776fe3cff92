"""One rollout collector for every PPO trainer of the control stage.

Per iteration, ``horizon`` steps of every environment of a :class:`~motok.control.tasks.base.TaskEnv`:
the policy input ``[s, s~]`` (Eq. 7 and the task's goal) is normalised by the running statistics
(updated first, as the policy then sees it), an action is drawn, the MDP steps, and a truncated
episode's final observation is valued *before* its reset so GAE can bootstrap it (PPO trick 4).

The reward is ``w_task r_task + sum_h w_h r_h``: ``r_task`` the task's main term
(``task.reward_key``), ``r_h`` the terms of learned reward hooks such as AMP's style reward,
computed on the stored transitions ``(s, s')`` after the rollout and then trained on them.
Episode statistics (return, main reward per step, length, share truncated rather than
terminated) are kept across iterations per environment. ``update_hooks`` then trains the hooks
on the stored transitions.
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
    """``start()`` begins fresh episodes everywhere; ``collect()`` returns ``(rollout, last_value, stats)``.

    ``mdps`` are groups of environments, stored side by side in the rollout (group ``g`` holds
    columns ``offsets[g]:offsets[g + 1]``). One group steps as any MDP: act, step, record. With
    several, the groups take turns: group g's policy runs, its physics is launched on a worker
    thread, and while it steps the previous group's step is finished and recorded (EnvPool's
    idea, for a Python main thread that would otherwise wait on MuJoCo). The order of every
    policy call, normaliser update and random draw is fixed by the schedule, not by thread
    timing, so ``threaded=False`` gives exactly the same transitions (tested)."""

    def __init__(self, mdps: TaskEnv | list[TaskEnv], ac: ActorCritic, horizon: int, task_weight: float = 1.0,
                 hooks: tuple[RewardHook, ...] = (), threaded: bool = True):
        self.mdps = [mdps] if isinstance(mdps, TaskEnv) else list(mdps)
        self.ac, self.horizon, self.task_weight, self.hooks = ac, horizon, task_weight, tuple(hooks)
        self.threaded = threaded and len(self.mdps) > 1
        first = self.mdps[0]
        self.key, self.dt = first.task.reward_key, first.dt
        self.obs_dim, self.goal_dim = first.obs_dim, first.goal_dim
        self.offsets = np.cumsum([0] + [m.num_envs for m in self.mdps])
        self.num_envs = int(self.offsets[-1])

    def start(self) -> None:
        self.obs, self.goal = [], []
        for m in self.mdps:
            o, g = m.reset()
            self.obs.append(o)
            self.goal.append(g)
        self.episodes = Episodes.empty(self.num_envs)

    def _input(self, obs, goal) -> torch.Tensor:
        return as_tensor(np.concatenate([obs, goal], 1))

    def _act(self, g: int, t: int, ro: Rollout) -> None:
        cols = slice(self.offsets[g], self.offsets[g + 1])
        x = self._input(self.obs[g], self.goal[g])
        self.ac.norm.update(x)
        xn, a, logp, v = self.ac.act(x)
        ro.x[t, cols], ro.actions[t, cols], ro.logp[t, cols], ro.values[t, cols] = xn, a, logp, v
        self.mdps[g].launch(a.numpy(), self.threaded)

    def _record(self, g: int, t: int, ro: Rollout, main, s, s2) -> None:
        mdp, cols = self.mdps[g], slice(self.offsets[g], self.offsets[g + 1])
        obs, goal, rewards, term, trunc, _ = mdp.finish()
        main[t, cols] = torch.from_numpy(rewards[self.key])
        ro.terminated[t, cols], ro.truncated[t, cols] = torch.from_numpy(term), torch.from_numpy(trunc)
        if s is not None:
            s[t, cols], s2[t, cols] = as_tensor(self.obs[g]), as_tensor(obs)
        if trunc.any():  # bootstrapping needs the value of the final observation, before the reset
            with torch.no_grad():
                xf = self.ac.norm(self._input(obs[trunc], goal[trunc]))
                ro.final_values[t, torch.from_numpy(np.flatnonzero(trunc) + self.offsets[g])] = self.ac.value(xf)
        done = term | trunc
        if done.any():
            obs, goal = mdp.reset(np.flatnonzero(done))
        self.obs[g], self.goal[g] = obs, goal

    def collect(self) -> tuple[Rollout, torch.Tensor, dict]:
        ac, T, N, G = self.ac, self.horizon, self.num_envs, len(self.mdps)
        pol = ac.policy
        ro = Rollout(T, N, self.obs_dim + self.goal_dim, pol.action_shape, pol.action_dtype)
        keep = bool(self.hooks)
        s = torch.zeros(T, N, self.obs_dim) if keep else None
        s2 = torch.zeros(T, N, self.obs_dim) if keep else None
        main = torch.zeros(T, N)
        in_flight: list[tuple[int, int]] = []  # (group, step) launched and not yet recorded
        for t in range(T):
            for g in range(G):
                self._act(g, t, ro)
                in_flight.append((g, t))
                if len(in_flight) == min(G, 2):  # one group steps while the one before it is recorded
                    self._record(*in_flight.pop(0), ro, main, s, s2)
        while in_flight:
            self._record(*in_flight.pop(0), ro, main, s, s2)
        with torch.no_grad():
            last_value = ac.value(ac.norm(self._input(np.concatenate(self.obs), np.concatenate(self.goal))))
        terms = {h.name: h.reward(s.flatten(0, 1), s2.flatten(0, 1)).view(T, N) for h in self.hooks}
        ro.rewards = self.task_weight * main
        for h in self.hooks:
            ro.rewards = ro.rewards + h.weight * terms[h.name]
        stats = self.episodes.add(ro, main, self.key, self.dt)
        stats.update({self.key: float(main.mean()), **{k: float(v.mean()) for k, v in terms.items()},
                      "reward": float(ro.rewards.mean())})
        self._transitions = (s.flatten(0, 1), s2.flatten(0, 1)) if keep else None
        return ro, last_value, stats

    def update_hooks(self) -> dict[str, float]:
        """Train the reward hooks (AMP's discriminator) on the last rollout's transitions; separate
        from :meth:`collect` so a trainer can give the learning steps more threads than the rollout."""
        stats: dict[str, float] = {}
        if self._transitions is not None:
            for h in self.hooks:
                stats.update(h.update(*self._transitions))
            self._transitions = None
        return stats
