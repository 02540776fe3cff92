"""Proximal Policy Optimisation (Schulman et al. 2017): its configuration and its update, which
reads top to bottom in :meth:`PPO.update`.

One iteration of every PPO trainer is two calls: ``Collector.collect()`` (``rollout.py``) runs
``horizon`` steps of every environment into a :class:`~motok.control.rl.rollout.Rollout`, and
``PPO.update(rollout, last_value, iteration)`` here learns from it. The networks it optimises
(``networks.ActorCritic``: the running normaliser, a policy of ``policies``, the critic) are the
model, and the runner (``runner.py``) is the loop around the iterations (checkpoints, metrics).

The tricks, in the order a rollout meets them (the names follow CleanRL's
``ppo_continuous_action.py`` and "The 37 implementation details of PPO"):

1. **Vectorised rollouts**: ``horizon`` steps of N environments per iteration (the collector).
2. **Running observation normalisation** (``networks.RunningNorm``), updated during rollouts and
   stored in the buffer as the policy saw it, so old and new log-probabilities agree.
3. **The policy owns its distribution** (``policies``): Gaussian actions with a fixed or learned
   state-independent log-std, or categoricals over codebook indices; PPO only asks for
   ``evaluate(x, a) -> (log-probability, entropy)``.
4. **GAE** (:func:`gae`) that **bootstraps on time-limit truncation but not on termination**.
5. **Learning-rate schedule** (:func:`learning_rate`: constant, linear or cosine decay).
6. **Minibatches and epochs** over the flattened rollout, reshuffled each epoch.
7. **Advantage normalisation** per minibatch.
8. **Clipped surrogate objective**.
9. **Value loss**, optionally clipped around the old values.
10. **Entropy bonus** (often 0 with a fixed std, where it is a constant).
11. **Global gradient-norm clipping**.
12. **Optional early stop** of the epochs when the approximate KL exceeds ``target_kl``.

Under ``torchrun`` every rank collects its own environments and the gradients are averaged
across ranks before clipping (as DDP would), and so is the KL the early stop reads, so all ranks
take the same steps and keep identical weights.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch

from motok.control.rl.networks import ActorCritic
from motok.control.rl.rollout import Rollout
from motok.distributed import average_gradients, average_scalar, world_size
from motok.errors import UserError
from motok.ranges import In


@dataclass
class PPOConfig:
    horizon: In[int, ">= 1"] = 32  # steps per environment per iteration: the rollout's length T
    epochs: In[int, ">= 1"] = 5  # passes over the rollout per update, each in a new minibatch order
    minibatch_size: In[int, ">= 1"] = 512  # samples per gradient step (a ragged last minibatch is dropped)
    gamma: In[float, "[0, 1]"] = 0.99  # discount per control step
    lam: In[float, "[0, 1]"] = 0.95  # GAE lambda: 0 is the one-step TD error, 1 the Monte-Carlo return
    clip: In[float, "> 0"] = 0.2  # epsilon of the clipped surrogate: the ratio's trust region 1 +- clip
    clip_value: bool = False  # clip the value loss around the old values
    value_clip: In[float, "> 0"] = 0.2  # only with clip_value; in return units, so tight for large returns
    value_coef: In[float, ">= 0"] = 0.5  # weight of the value loss beside the surrogate
    entropy_coef: In[float, ">= 0"] = 0.0  # entropy bonus (a constant for a fixed-std Gaussian)
    max_grad_norm: In[float, "> 0"] = 1.0  # global gradient-norm clip
    lr: In[float, "> 0"] = 3e-4  # Adam learning rate (the schedule's start)
    lr_schedule: str = "constant"  # constant | linear | cosine (to lr_min at the last iteration)
    lr_min: In[float, ">= 0"] = 0.0  # where the linear and cosine schedules end
    adam_eps: In[float, "> 0"] = 1e-5  # Adam epsilon (CleanRL's)
    norm_adv: bool = True  # normalise advantages per minibatch
    # stop an update's epochs once the approximate KL exceeds this (None: never)
    target_kl: In[float | None, "> 0"] = None


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


class PPO:
    """The update half of PPO: ``update(rollout, last_value, iteration)`` does epochs x minibatches."""

    def __init__(self, ac: ActorCritic, cfg: PPOConfig, total_iterations: int):
        self.ac, self.cfg, self.total = ac, cfg, total_iterations
        # The normaliser's statistics are buffers the rollout updates, never a gradient's business.
        self.params = [p for n, p in ac.named_parameters() if not n.startswith("norm.")]
        self.opt = torch.optim.Adam(self.params, lr=cfg.lr, eps=cfg.adam_eps)

    def update(self, ro: Rollout, last_value: torch.Tensor, iteration: int,
               generator: torch.Generator | None = None) -> dict[str, float]:
        """Learn from the rollout ``ro`` (``last_value``: V of the state after its last step);
        returns the means over the minibatches of the losses, the entropy, the approximate KL and
        the share of clipped ratios, and the explained variance and learning rate."""
        c, ac = self.cfg, self.ac
        lr = learning_rate(c, iteration, self.total)
        for g in self.opt.param_groups:
            g["lr"] = lr
        adv, ret = gae(ro.rewards, ro.values, ro.next_values(last_value), ro.terminated, ro.truncated, c.gamma, c.lam)
        # The batch: T x N samples, each as the policy saw it when it acted.
        x, a, old_logp = ro.x.flatten(0, 1), ro.actions.flatten(0, 1), ro.logp.flatten(0, 1)
        old_v, adv, ret = ro.values.flatten(), adv.flatten(), ret.flatten()
        synced = world_size() > 1
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
                # Clipped surrogate -E[min(rho A, clip(rho, 1 - eps, 1 + eps) A)]: once the ratio has
                # left the trust region in the direction the advantage favours, its gradient is zero.
                log_ratio = logp - old_logp[idx]
                ratio = log_ratio.exp()
                pl = -torch.min(ratio * A, ratio.clamp(1.0 - c.clip, 1.0 + c.clip) * A).mean()
                with torch.no_grad():
                    kl = ((ratio - 1.0) - log_ratio).mean()  # the low-variance estimator (rho - 1) - log rho
                    frac = ((ratio - 1.0).abs() > c.clip).float().mean()
                # Value loss 0.5 (V - R)^2; clipped: the larger of that and the loss of old_v + clip(V - old_v).
                v = ac.value(x[idx])
                v_err = (v - ret[idx]) ** 2
                if c.clip_value:
                    v_clipped = old_v[idx] + (v - old_v[idx]).clamp(-c.value_clip, c.value_clip)
                    v_err = torch.max(v_err, (v_clipped - ret[idx]) ** 2)
                vl = 0.5 * v_err.mean()
                loss = pl + c.value_coef * vl - c.entropy_coef * ent
                self.opt.zero_grad(set_to_none=True)
                loss.backward()
                if synced:
                    average_gradients(self.params)
                torch.nn.utils.clip_grad_norm_(self.opt.param_groups[0]["params"], c.max_grad_norm)
                self.opt.step()
                for k, val in zip(stats, (pl, vl, ent, kl, frac)):
                    stats[k] += float(val.detach())
                n += 1
            if c.target_kl is not None and float(average_scalar(kl) if synced else kl) > c.target_kl:
                break
        out = {k: val / max(n, 1) for k, val in stats.items()}
        var = float(ret.var())
        out["explained_var"] = float("nan") if var == 0 else 1.0 - float((ret - old_v).var()) / var
        out["lr"] = lr
        return out
