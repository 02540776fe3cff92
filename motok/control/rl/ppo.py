"""Proximal Policy Optimisation (Schulman et al. 2017), written so every trick is a named line.

The tricks, in the order a rollout meets them (the names follow CleanRL's
``ppo_continuous_action.py`` and "The 37 implementation details of PPO"):

1. **Vectorised rollouts**: ``horizon`` steps of N environments per iteration (:class:`Rollout`).
2. **Running observation normalisation** (``networks.RunningNorm``), updated during rollouts and
   stored in the buffer as the policy saw it, so old and new log-probabilities agree.
3. **The policy owns its distribution** (``policies``): Gaussian actions with a fixed or learned
   state-independent log-std, or categoricals over codebook indices; PPO only asks for
   ``evaluate(x, a) -> (log-probability, entropy)``.
4. **GAE** (:func:`gae`, gamma 0.99, lambda 0.95) that **bootstraps on time-limit truncation but
   not on termination**: a truncated step's target uses ``V(final observation)``, a terminated
   step's uses 0, and the advantage recursion stops at both (the next state is a reset).
5. **Advantage normalisation** per minibatch.
6. **Clipped surrogate objective** (:func:`policy_loss`, clip 0.2).
7. **Value loss**, optionally clipped around the old values (:func:`value_loss`).
8. **Entropy bonus** (often 0 with a fixed std, where it is a constant).
9. **Minibatches and epochs** over the flattened rollout, reshuffled each epoch.
10. **Global gradient-norm clipping**.
11. **Learning-rate schedule** (:func:`learning_rate`: constant, linear or cosine decay).
12. **Optional early stop** of the epochs when the approximate KL exceeds ``target_kl``.

Under ``torchrun`` every rank collects its own environments and the gradients are averaged
across ranks before clipping (as DDP would), and so is the KL the early stop reads, so all ranks
take the same steps and keep identical weights.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch
import torch.distributed as dist

from motok.control.rl.networks import ActorCritic
from motok.errors import UserError
from motok.ranges import In


@dataclass
class PPOConfig:
    horizon: In[int, ">= 1"] = 32  # steps per environment per iteration
    epochs: In[int, ">= 1"] = 5
    minibatch_size: In[int, ">= 1"] = 512  # samples per gradient step (a ragged last minibatch is dropped)
    gamma: In[float, "[0, 1]"] = 0.99  # discount
    lam: In[float, "[0, 1]"] = 0.95  # GAE lambda
    clip: In[float, "> 0"] = 0.2  # epsilon of the clipped surrogate
    clip_value: bool = False  # clip the value loss around the old values
    value_clip: In[float, "> 0"] = 0.2  # only with clip_value; in return units, so tight for large returns
    value_coef: In[float, ">= 0"] = 0.5
    entropy_coef: In[float, ">= 0"] = 0.0  # entropy bonus (a constant for a fixed-std Gaussian)
    max_grad_norm: In[float, "> 0"] = 1.0  # global gradient-norm clip
    lr: In[float, "> 0"] = 3e-4  # Adam learning rate (the schedule's start)
    lr_schedule: str = "constant"  # constant | linear | cosine (to lr_min at the last iteration)
    lr_min: In[float, ">= 0"] = 0.0
    adam_eps: In[float, "> 0"] = 1e-5  # Adam epsilon (CleanRL's)
    norm_adv: bool = True  # normalise advantages per minibatch
    # stop an update's epochs once the approximate KL exceeds this (None: never)
    target_kl: In[float | None, "> 0"] = None


def gae(rewards, values, next_values, terminated, truncated, gamma: float, lam: float):
    """Generalised advantage estimation over ``(T, N)`` tensors.

    ``next_values[t]`` is the value of the state reached by step t: ``V(s_{t+1})`` mid-episode,
    ``V(final observation)`` when step t was truncated (the episode did not really end, so its
    future is bootstrapped), anything when it was terminated (masked out: no future). The
    recursion ``A_t = delta_t + gamma lam A_{t+1}`` is cut at every episode end either way,
    because step t+1 then belongs to a new episode. Returns ``(advantages, returns)``.
    """
    term = terminated.to(rewards.dtype)
    done = (terminated | truncated).to(rewards.dtype)
    delta = rewards + gamma * next_values * (1.0 - term) - values
    adv = torch.zeros_like(rewards)
    acc = torch.zeros_like(rewards[0])
    for t in range(len(rewards) - 1, -1, -1):
        acc = delta[t] + gamma * lam * (1.0 - done[t]) * acc
        adv[t] = acc
    return adv, adv + values


def policy_loss(logp, old_logp, adv, clip: float):
    """Clipped surrogate ``-E[min(rho A, clip(rho, 1 - eps, 1 + eps) A)]``; once the ratio has left
    the trust region in the direction the advantage favours, its gradient is exactly zero.
    Returns ``(loss, approx_kl, clip_fraction)``; the KL is the low-variance ``(rho - 1) - log rho``."""
    log_ratio = logp - old_logp
    ratio = log_ratio.exp()
    loss = -torch.min(ratio * adv, ratio.clamp(1.0 - clip, 1.0 + clip) * adv).mean()
    with torch.no_grad():
        kl = ((ratio - 1.0) - log_ratio).mean()
        frac = ((ratio - 1.0).abs() > clip).float().mean()
    return loss, kl, frac


def value_loss(v, old_v, returns, clip: float | None):
    """``0.5 (V - R)^2``; clipped: the larger of that and the loss of ``old_v + clip(V - old_v)``."""
    unclipped = (v - returns) ** 2
    if clip is None:
        return 0.5 * unclipped.mean()
    v_clipped = old_v + (v - old_v).clamp(-clip, clip)
    return 0.5 * torch.max(unclipped, (v_clipped - returns) ** 2).mean()


# A median approximate KL per update (nats) over KL_WINDOW iterations above which the updates have
# left the clipped objective's trust region: policies that learn here stay at 0.02-0.07 (the
# expert, the categorical task policies), while the continuous prior's Gaussian at lr 3e-4 moved
# 0.2-11 and its in-betweening diverged (docs/results.md).
KL_WARN, KL_WINDOW = 0.3, 50


def kl_warning(recent, threshold: float = KL_WARN) -> str | None:
    """The warning a training prints once when the median of its ``recent`` iterations' ``approx_kl``
    exceeds ``threshold``, else None: the clip no longer bounds the steps, and the lr should fall."""
    if not recent:
        return None
    kl = float(sorted(recent)[len(recent) // 2])
    if not kl > threshold:
        return None
    return (f"[bold red]warning:[/] PPO's updates move a median {kl:.2g} nats of approximate KL over the last "
            f"{len(recent)} iterations (policies that learn: < {threshold:g}): they have left the trust region "
            f"and training may diverge; lower ppo.lr (--set ppo.lr=...)")


def learning_rate(cfg: PPOConfig, iteration: int, total: int) -> float:
    """LR for 0-based ``iteration`` of ``total``."""
    frac = min(max(iteration / max(total, 1), 0.0), 1.0)
    if cfg.lr_schedule == "constant":
        return cfg.lr
    if cfg.lr_schedule == "linear":
        return cfg.lr_min + (cfg.lr - cfg.lr_min) * (1.0 - frac)
    if cfg.lr_schedule == "cosine":
        return cfg.lr_min + 0.5 * (cfg.lr - cfg.lr_min) * (1.0 + math.cos(math.pi * frac))
    raise UserError(f"unknown lr_schedule {cfg.lr_schedule!r}: use constant, linear or cosine")


class Rollout:
    """``(T, N, .)`` storage for one iteration. ``x`` is the normalised policy input; actions keep
    the policy's shape and dtype (``(A,)`` float for a Gaussian, ``(M,)`` int64 for codebook indices)."""

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


def world_size() -> int:
    return dist.get_world_size() if dist.is_available() and dist.is_initialized() else 1


def average_gradients(params: list[torch.Tensor]) -> None:
    """All-reduce mean of the gradients over ranks, flattened into one collective."""
    grads = [p.grad for p in params if p.grad is not None]
    if not grads:
        return
    flat = torch.cat([g.reshape(-1) for g in grads])
    dist.all_reduce(flat)
    flat /= world_size()
    o = 0
    for g in grads:
        g.copy_(flat[o:o + g.numel()].view_as(g))
        o += g.numel()


def average_scalar(x: torch.Tensor) -> torch.Tensor:
    y = x.detach().clone().reshape(1)
    dist.all_reduce(y)
    return y[0] / world_size()


class PPO:
    """The update half of PPO: ``update(rollout, last_value, iteration)`` does epochs x minibatches."""

    def __init__(self, ac: ActorCritic, cfg: PPOConfig, total_iterations: int):
        self.ac, self.cfg, self.total = ac, cfg, total_iterations
        self.params = [p for n, p in ac.named_parameters() if not n.startswith("norm.")]
        self.opt = torch.optim.Adam(self.params, lr=cfg.lr, eps=cfg.adam_eps)

    def update(self, ro: Rollout, last_value: torch.Tensor, iteration: int,
               generator: torch.Generator | None = None) -> dict[str, float]:
        c, ac = self.cfg, self.ac
        lr = learning_rate(c, iteration, self.total)
        for g in self.opt.param_groups:
            g["lr"] = lr
        adv, ret = gae(ro.rewards, ro.values, ro.next_values(last_value), ro.terminated, ro.truncated, c.gamma, c.lam)
        x, a, old_logp = ro.x.flatten(0, 1), ro.actions.flatten(0, 1), ro.logp.flatten(0, 1)
        synced = world_size() > 1
        old_v, adv, ret = ro.values.flatten(), adv.flatten(), ret.flatten()
        B = len(x)
        mb = min(c.minibatch_size, B)
        stats = {"policy_loss": 0.0, "value_loss": 0.0, "entropy": 0.0, "approx_kl": 0.0, "clip_frac": 0.0}
        n = 0
        for _ in range(c.epochs):
            perm = torch.randperm(B, generator=generator)
            for i in range(0, B - mb + 1, mb):  # a ragged last minibatch would be noisier: dropped
                idx = perm[i:i + mb]
                logp, ent = ac.policy.evaluate(x[idx], a[idx])
                ent = ent.mean()
                A = adv[idx]
                if c.norm_adv:
                    A = (A - A.mean()) / (A.std() + 1e-8)
                pl, kl, frac = policy_loss(logp, old_logp[idx], A, c.clip)
                vl = value_loss(ac.value(x[idx]), old_v[idx], ret[idx], c.value_clip if c.clip_value else None)
                loss = pl + c.value_coef * vl - c.entropy_coef * ent
                self.opt.zero_grad(set_to_none=True)
                loss.backward()
                if synced:
                    average_gradients(self.params)
                torch.nn.utils.clip_grad_norm_(self.opt.param_groups[0]["params"], c.max_grad_norm)
                self.opt.step()
                for k, v in zip(stats, (pl, vl, ent, kl, frac)):
                    stats[k] += float(v.detach())
                n += 1
            if c.target_kl is not None and float(average_scalar(kl) if synced else kl) > c.target_kl:
                break
        out = {k: v / max(n, 1) for k, v in stats.items()}
        var = float(ret.var())
        out["explained_var"] = float("nan") if var == 0 else 1.0 - float((ret - old_v).var()) / var
        out["lr"] = lr
        return out
