"""Online distillation's data (hybrid-latent paper section 4.3.1): the student acts, the frozen
expert labels every state it visits (DAgger, Ross et al. 2011).

**Label conversion.** The student acts without a reference motion, so its action is a residual
on the *current* pose, ``q_hat = q + scale a`` (the paper's action map, ``ActionConfig("current")``).
The expert's action is a residual on its own base (in the recipes the next reference frame with
a velocity lead, ``q_hat_e = q*_{t+1} + (kv / kp) qd*_{t+1} + a_e``). The label is the expert's
PD target, as the simulation would apply it (clipped to the actuator range), expressed on the
student's base: ``a_label = (clip(q_hat_e) - q) / scale``, so a student that outputs the label
drives exactly the targets the expert would have (tested).

The collector keeps the rollout's ``(T, N)`` layout: step ``t + 1`` of column ``n`` continues the
episode of step ``t`` unless ``done[t, n]``, which is what the latent regulariser ``L_reg`` needs.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch

from motok.arrays import xp
from motok.control.mdp.actions import ActionConfig, pd_targets
from motok.control.mdp.task_env import TaskEnv
from motok.control.priors.model import LatentPrior, squared_norm
from motok.control.rl.networks import ActorCritic
from motok.control.rl.rollout import Episodes, as_tensor
from motok.quantize.base import code_stats


def expert_labels(expert_action: ActionConfig, a_e, env, task, scale: float = 1.0):
    """The student's label ``(N, nu)`` for expert actions ``a_e``: the expert's PD target
    (``pd_targets`` with the expert's action map, clipped as the simulation clips it) minus the
    current hinge angles, over the student's action scale. Call it before the step. Host arrays
    or, for an on-device environment, device tensors."""
    target = xp(a_e).clip(pd_targets(expert_action, a_e, env, task), env.ctrl_low, env.ctrl_high)
    return (target - env.qpos[:, env.hinge_adr]) / scale


@dataclass
class DaggerBatch:
    """One iteration's ``(T, N, .)`` data; the reward and end masks also feed the episode statistics."""

    x: torch.Tensor  # raw [s, s~] (normalised at update time, with the statistics the student keeps)
    labels: torch.Tensor  # a_label on the student's base
    rewards: torch.Tensor  # the task's main reward (r_im), for episode statistics only
    terminated: torch.Tensor
    truncated: torch.Tensor

    @property
    def done(self) -> torch.Tensor:
        return self.terminated | self.truncated


def code_usage(indices: torch.Tensor, codebook_size: int) -> dict[str, float]:
    """Per codebook ``m``: ``code_usage_m`` (share of codes used) and ``code_perplexity_m`` of
    indices ``(B, N)`` (entries -1 not counted), plus their means over codebooks."""
    out: dict[str, float] = {}
    for m in range(indices.shape[-1]):
        col = indices[..., m].reshape(-1)
        used, ppl = code_stats(torch.bincount(col[col >= 0], minlength=codebook_size).float())
        out[f"code_usage_{m}"], out[f"code_perplexity_{m}"] = float(used), float(ppl)
    n = indices.shape[-1]
    out["code_usage"] = sum(out[f"code_usage_{m}"] for m in range(n)) / n
    out["code_perplexity"] = sum(out[f"code_perplexity_{m}"] for m in range(n)) / n
    return out


class DaggerCollector:
    """``start()`` begins fresh episodes everywhere; ``collect()`` returns ``(batch, stats)``.

    Per step: the student's normaliser is updated with ``[s, s~]`` (as the PPO collector does),
    the student acts (eval mode: all codebooks, no codebook updates; the continuous posterior is
    sampled) plus optional Gaussian noise of std ``action_noise`` (the authors' code samples
    its fixed-std policy), the expert labels the same state with its most likely action, the
    MDP steps, and finished environments restart (the task's termination and truncation)."""

    def __init__(self, mdp: TaskEnv, model: LatentPrior, expert: ActorCritic, expert_action: ActionConfig,
                 horizon: int, action_noise: float = 0.0, scale: float = 1.0):
        self.mdp, self.model, self.expert, self.expert_action = mdp, model, expert, expert_action
        self.horizon, self.action_noise, self.scale = horizon, action_noise, scale
        self.key = mdp.task.reward_key
        self.on_device = mdp.env.on_device  # env.on_device: the batch and every step stay on the physics device
        self.device = mdp.env.torch_device if self.on_device else None

    def start(self) -> None:
        self.obs, self.goal = self.mdp.reset()
        self.episodes = Episodes.empty(self.mdp.num_envs, self.device)

    def collect(self) -> tuple[DaggerBatch, dict]:
        mdp, model, T, N, dev = self.mdp, self.model, self.horizon, self.mdp.num_envs, self.device
        env = mdp.env
        z = lambda *shape, dtype=torch.float32: torch.zeros(*shape, dtype=dtype, device=dev)  # noqa: E731
        b = DaggerBatch(z(T, N, mdp.obs_dim + mdp.goal_dim), z(T, N, mdp.action_dim), z(T, N),
                        z(T, N, dtype=torch.bool), z(T, N, dtype=torch.bool))
        err = z(T, N)
        idx = torch.full((T, N, max(model.columns(), 1)), -1, dtype=torch.long, device=dev)
        host = (lambda a_: a_) if self.on_device else (lambda a_: a_.numpy())  # noqa: E731  (what the MDP takes)
        model.eval()
        for t in range(T):
            x = as_tensor(xp(self.obs).concatenate([self.obs, self.goal], 1))
            model.norm.update(x)
            with torch.no_grad():
                out = model(model.norm(x))
                a = out.action
                if self.action_noise > 0:
                    a = a + self.action_noise * torch.randn_like(a)
                a_e = self.expert.policy.act(self.expert.norm(x), True)[0]  # its mean action; no critic
            label = as_tensor(expert_labels(self.expert_action, host(a_e), env, mdp.task, self.scale))
            b.x[t], b.labels[t], err[t] = x, label, squared_norm(out.action - label)
            if out.indices is not None:
                idx[t] = out.indices
            obs, goal, rewards, term, trunc, _ = mdp.step(host(a))
            b.rewards[t] = torch.as_tensor(rewards[self.key])
            b.terminated[t], b.truncated[t] = torch.as_tensor(term), torch.as_tensor(trunc)
            self.obs, self.goal = mdp.restart_done(term | trunc, obs, goal)
        stats = self.episodes.add(b, b.rewards, self.key, mdp.dt)
        # The student's error on states it has not been trained on yet: the honest DAgger curve.
        stats.update({self.key: float(b.rewards.mean()), "rollout_action_err": float(err.mean())})
        if model.quantizer is not None:
            stats.update(code_usage(idx, model.quantizer.codebook_size))
        return b, stats
