"""One rollout collector for every PPO trainer of the control stage, and the buffer it fills.

Per iteration, ``horizon`` steps of every environment of a :class:`~motok.control.mdp.task_env.TaskEnv`:
the policy input ``[s, s~]`` (Eq. 7 and the task's goal) is normalised by the running statistics
(updated first, as the policy then sees it), an action is drawn, the MDP steps, and a truncated
episode's final observation is valued *before* its reset so GAE can bootstrap it (PPO trick 4).

The reward is ``w_task r_task + sum_h w_h r_h``: ``r_task`` the task's main term
(``task.reward_key``), ``r_h`` the terms of learned reward hooks such as AMP's style reward,
computed on the stored transitions ``(s, s')`` after the rollout and then trained on them, plus,
with ``action_rate`` (its weight) > 0, ``action_rate * r_action_rate``, the change of the
action between consecutive steps of an episode (``motok.control.mdp.rewards.action_rate``).
The hooks' transitions are the Eq. 7 observations unless ``hook_obs(mdp, obs)`` extends them
(AMP's discriminator seeing the soles, ``motok.control.rl.amp.SoleObservation``).
Episode statistics (return, main reward per step, length, share truncated rather than
terminated) are kept across iterations per environment. ``update_hooks`` then trains the hooks
on the stored transitions.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Protocol

import numpy as np
import torch

from motok.arrays import xp
from motok.control.rl.networks import ActorCritic
from motok.control.mdp.rewards import action_rate
from motok.control.mdp.task_env import TaskEnv
from motok.errors import UserError


def as_tensor(a) -> torch.Tensor:
    """float32 tensor of ``a`` (where a tensor already is); a diverged env may hold non-finite rows,
    which become finite."""
    if isinstance(a, torch.Tensor):
        return torch.nan_to_num(a.to(torch.float32))
    return torch.as_tensor(np.nan_to_num(np.asarray(a, dtype=np.float32)))


class Rollout:
    """``(T, N, .)`` storage for one iteration, what :meth:`motok.control.rl.ppo.PPO.update` reads.
    ``x`` is the normalised policy input; actions keep the policy's shape and dtype (``(A,)`` float
    for a Gaussian, ``(M,)`` int64 for codebook indices)."""

    def __init__(self, horizon: int, num_envs: int, in_dim: int, action_shape: tuple[int, ...],
                 action_dtype: torch.dtype = torch.float32, device=None):
        T, N = horizon, num_envs
        z = lambda *shape, dtype=torch.float32: torch.zeros(*shape, dtype=dtype, device=device)  # noqa: E731
        self.x = z(T, N, in_dim)
        self.actions = z(T, N, *action_shape, dtype=action_dtype)
        self.logp = z(T, N)
        self.values = z(T, N)
        self.rewards = z(T, N)
        self.final_values = z(T, N)  # V(final observation) of truncated steps
        self.terminated = z(T, N, dtype=torch.bool)
        self.truncated = z(T, N, dtype=torch.bool)

    def next_values(self, last_value: torch.Tensor) -> torch.Tensor:
        """``V`` of the state each step reached: the following step's value inside an episode,
        the stored final value after a truncation, ``last_value`` after the last step."""
        nv = torch.cat([self.values[1:], last_value[None]], 0)
        return torch.where(self.truncated, self.final_values, nv)


class RewardHook(Protocol):
    """A learned reward on transitions, e.g. :class:`motok.control.rl.amp.AMPHook`."""

    name: str  # logged as this key, e.g. "r_style"
    weight: float

    def reward(self, s: torch.Tensor, s2: torch.Tensor) -> torch.Tensor: ...

    def update(self, s: torch.Tensor, s2: torch.Tensor) -> dict[str, float]: ...


@dataclass
class Episodes:
    """Running per-environment episode sums (float64 tensors where the rollout is); ``add`` returns
    the statistics of the episodes it closed. The closed episodes are summed, not listed, so a
    rollout on a device is read on the host once per iteration, not once per step."""

    ret: torch.Tensor
    main: torch.Tensor
    length: torch.Tensor

    @classmethod
    def empty(cls, n: int, device=None) -> "Episodes":
        z = torch.zeros(n, dtype=torch.float64, device=device)
        return cls(z, z.clone(), z.clone())

    def add(self, ro: Rollout, main: torch.Tensor, key: str, dt: float) -> dict:
        # Sums over closed episodes of: return, main reward per step, length, ended without failing.
        sums = torch.zeros(5, dtype=torch.float64, device=self.ret.device)
        for t in range(len(ro.rewards)):
            self.ret += ro.rewards[t]
            self.main += main[t]
            self.length += 1
            done = (ro.terminated[t] | ro.truncated[t]).to(torch.float64)
            ok = ro.truncated[t].to(torch.float64)  # clip end or time limit
            sums += torch.stack([(self.ret * done).sum(), (self.main / self.length * done).sum(),
                                 (self.length * done).sum(), (ok * done).sum(), done.sum()])
            keep = 1.0 - done
            self.ret *= keep
            self.main *= keep
            self.length *= keep
        ret, per_step, length, ok, n = sums.tolist()
        if n == 0:
            return {}
        return {"episode_return": ret / n, f"episode_{key}": per_step / n, "episode_seconds": length / n * dt,
                "success": ok / n, "episodes": int(n)}


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
                 hooks: tuple[RewardHook, ...] = (), threaded: bool = True, action_rate: float = 0.0,
                 hook_obs=None):
        self.mdps = [mdps] if isinstance(mdps, TaskEnv) else list(mdps)
        self.ac, self.horizon, self.task_weight, self.hooks = ac, horizon, task_weight, tuple(hooks)
        self.w_rate, self.hook_obs = action_rate, hook_obs
        if action_rate and not ac.policy.action_dtype.is_floating_point:
            raise UserError("action_rate penalises the change of continuous actions; this policy's are indices")
        self.threaded = threaded and len(self.mdps) > 1
        first = self.mdps[0]
        # On the device (env.on_device): observations, actions, rewards and buffers stay there.
        self.on_device = first.env.on_device
        self.device = first.env.torch_device if self.on_device else None
        if self.on_device and len(self.mdps) > 1:
            raise UserError("env.groups > 1 overlaps host physics with the policy; on the device use one group")
        self.key, self.dt = first.task.reward_key, first.dt
        self.obs_dim, self.goal_dim = first.obs_dim, first.goal_dim
        self.offsets = np.cumsum([0] + [m.num_envs for m in self.mdps])
        self.num_envs = int(self.offsets[-1])

    def _hook_state(self, g: int, obs):
        """What the reward hooks see of group ``g``'s current state: the Eq. 7 ``obs`` or its extension."""
        return obs if self.hook_obs is None else self.hook_obs(self.mdps[g], obs)

    def start(self) -> None:
        self.obs, self.goal = [], []
        for m in self.mdps:
            o, g = m.reset()
            self.obs.append(o)
            self.goal.append(g)
        self.hobs = [self._hook_state(g, o) for g, o in enumerate(self.obs)]
        self.episodes = Episodes.empty(self.num_envs, self.device)
        if self.w_rate:  # the last action of every environment, and whether its episode has none yet
            self.last_action = torch.zeros(self.num_envs, *self.ac.policy.action_shape, device=self.device)
            self.fresh = torch.ones(self.num_envs, dtype=torch.bool, device=self.device)

    def _input(self, obs, goal) -> torch.Tensor:
        return as_tensor(xp(obs).concatenate([obs, goal], 1))

    def _act(self, g: int, t: int, ro: Rollout) -> None:
        cols = slice(self.offsets[g], self.offsets[g + 1])
        x = self._input(self.obs[g], self.goal[g])
        self.ac.norm.update(x)
        xn, a, logp, v = self.ac.act(x)
        ro.x[t, cols], ro.actions[t, cols], ro.logp[t, cols], ro.values[t, cols] = xn, a, logp, v
        if self.w_rate:
            self.rate[t, cols] = action_rate(a, self.last_action[cols], self.fresh[cols])
            self.last_action[cols], self.fresh[cols] = a, False
        self.mdps[g].launch(a if self.on_device else a.numpy(), self.threaded)

    def _record(self, g: int, t: int, ro: Rollout, main, s, s2) -> None:
        mdp, cols = self.mdps[g], slice(self.offsets[g], self.offsets[g + 1])
        obs, goal, rewards, term, trunc, _ = mdp.finish()
        main[t, cols] = torch.as_tensor(rewards[self.key])
        ro.terminated[t, cols], ro.truncated[t, cols] = torch.as_tensor(term), torch.as_tensor(trunc)
        if s is not None:
            s[t, cols], s2[t, cols] = as_tensor(self.hobs[g]), as_tensor(self._hook_state(g, obs))
        if self.w_rate:  # a finished episode restarts below: its next action has no predecessor
            self.fresh[cols] |= torch.as_tensor(term | trunc, device=self.fresh.device)
        # Bootstrapping needs the value of a truncated episode's final observation, before the reset.
        if self.on_device:  # every row's value, kept where truncated: no host read of the mask
            with torch.no_grad():
                v = self.ac.value(self.ac.norm(self._input(obs, goal)))
            ro.final_values[t, cols] = torch.where(trunc, v, ro.final_values[t, cols])
        elif trunc.any():
            with torch.no_grad():
                xf = self.ac.norm(self._input(obs[trunc], goal[trunc]))
                ro.final_values[t, torch.from_numpy(np.flatnonzero(trunc) + self.offsets[g])] = self.ac.value(xf)
        self.obs[g], self.goal[g] = mdp.restart_done(term | trunc, obs, goal)
        if s is not None:
            self.hobs[g] = self._hook_state(g, self.obs[g])

    def collect(self) -> tuple[Rollout, torch.Tensor, dict]:
        ac, T, N, G = self.ac, self.horizon, self.num_envs, len(self.mdps)
        pol = ac.policy
        ro = Rollout(T, N, self.obs_dim + self.goal_dim, pol.action_shape, pol.action_dtype, self.device)
        keep = bool(self.hooks)
        h_dim = self.hobs[0].shape[1]  # obs_dim, or more when hook_obs extends it
        s = torch.zeros(T, N, h_dim, device=self.device) if keep else None
        s2 = torch.zeros(T, N, h_dim, device=self.device) if keep else None
        main = torch.zeros(T, N, device=self.device)
        self.rate = torch.zeros(T, N, device=self.device) if self.w_rate else None
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
            cat = xp(self.obs[0]).concatenate
            last_value = ac.value(ac.norm(self._input(cat(self.obs), cat(self.goal))))
        terms = {h.name: h.reward(s.flatten(0, 1), s2.flatten(0, 1)).view(T, N) for h in self.hooks}
        ro.rewards = self.task_weight * main
        for h in self.hooks:
            ro.rewards = ro.rewards + h.weight * terms[h.name]
        if self.w_rate:
            terms["r_action_rate"] = -self.rate
            ro.rewards = ro.rewards + self.w_rate * terms["r_action_rate"]
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
