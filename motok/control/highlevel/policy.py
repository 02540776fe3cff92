"""The high-level policy of task learning over a frozen latent prior (hybrid-latent paper section
5 / 6.3, appendix C, Tables 6-8).

The prior's decoder ``pi_low(s, z_bar)`` is frozen; a new policy ``pi_high(s, g)`` reads the
proprioception ``s`` (Eq. 7) and the task goal ``g`` and chooses the latent:

* ``discrete``, ``hybrid-vq``: one categorical over the codebook;
* ``discrete+``, ``hybrid``: one categorical per active codebook (the first ``M``), independent
  given the input; ``z_bar`` is the sum of the chosen codes, plus ``z_p(s)`` for the hybrid
  (section 4.1: the codes are codes of the margin to the prior);
* ``continuous``: a Gaussian offset ``u`` with a fixed exploration std (a recipe value; the
  paper's Fig. 4 right shows the result depends on it), ``z = mu_p(s) + u`` (Eq. 2's prior mean).

The environment sees the decoder's action: :class:`LatentActionMap` is the action map of
``motok.control.mdp.task_env.TaskEnv`` that turns the high-level action into PD targets on the
current pose (``q_hat = q + scale pi_low(s, z_bar)``, how the prior was distilled). PPO optimises
the high-level policy only; the prior's weights never receive a gradient (they are not in the
optimiser, and the map runs under ``no_grad``).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np
import torch

from motok.control.priors.generate import check_codebooks
from motok.control.mdp.actions import residual_targets
from motok.control.rl.networks import ActorCritic, RunningNorm, ValueNet
from motok.control.rl.policies import MLPPolicy, MultiCategoricalPolicy
from motok.control.priors.model import LatentPrior
from motok.errors import UserError


@dataclass
class HighLevelNetConfig:
    policy: list[int] = field(default_factory=lambda: [256, 256])
    value: list[int] = field(default_factory=lambda: [256, 256])
    activation: str = "elu"
    std: float = 0.2  # continuous prior: exploration std of the offset u (fixed, as in the paper)


class LatentActionMap:
    """``(actions, env, task) -> PD targets``: high-level actions decoded by the frozen prior.

    ``actions`` are code indices ``(N, M)`` (int) for the quantized kinds or offsets ``(N, D)``
    for the continuous prior. ``scale`` is the prior's action scale (its distillation recipe's
    ``action.scale``)."""

    def __init__(self, model: LatentPrior, codebooks: int, scale: float):
        self.model, self.codebooks, self.scale = model.eval().requires_grad_(False), codebooks, float(scale)

    @torch.no_grad()
    def latent(self, sn: torch.Tensor, actions) -> torch.Tensor:
        """``z_bar`` for normalised observations ``sn`` and high-level actions."""
        m = self.model
        if m.quantizer is None:
            return m.offset_to_latent(sn, torch.as_tensor(actions, dtype=torch.float32, device=sn.device))
        return m.codes_to_latent(sn, torch.as_tensor(actions, dtype=torch.int64, device=sn.device), self.codebooks)

    @torch.no_grad()
    def __call__(self, actions, env, task):
        m = self.model
        device = next(m.parameters()).device  # the prior's; the environment's arrays may be host or device
        sn = m.norm_obs(torch.as_tensor(env.observation(), dtype=torch.float32, device=device))
        a = m.decode(sn, self.latent(sn, actions))
        return residual_targets(a if env.on_device else a.cpu().numpy(), env.qpos[:, env.hinge_adr], self.scale)


def action_space(model: LatentPrior, codebooks: int | None) -> dict:
    """What the high-level policy chooses: ``{"kind", "codebooks", "codes"|"latent_dim"}``."""
    m = check_codebooks(model, codebooks)
    if model.quantizer is None:
        return {"kind": "gaussian offset u, z = mu_p(s) + u", "codebooks": 0, "latent_dim": model.cfg.latent_dim}
    return {"kind": "code indices, one categorical per codebook", "codebooks": m,
            "codes": model.quantizer.codebook_size}


def build_high_level(net: HighLevelNetConfig, model: LatentPrior, obs_dim: int, goal_dim: int,
                     codebooks: int | None) -> ActorCritic:
    """Normaliser + policy + value on ``[s, g]``; the policy's action space follows the prior."""
    if goal_dim < 1:
        raise UserError("a task for the high-level policy needs a goal (goal_dim >= 1)")
    if model.obs_dim != obs_dim:
        raise UserError(f"the prior reads {model.obs_dim} observation entries, the task's humanoid gives {obs_dim}")
    space = action_space(model, codebooks)
    d = obs_dim + goal_dim
    if model.quantizer is None:
        if net.std <= 0:
            raise UserError(f"net.std must be positive, not {net.std}")
        pol = MLPPolicy(d, model.cfg.latent_dim, tuple(net.policy), net.activation, math.log(net.std), False)
    else:
        pol = MultiCategoricalPolicy(d, space["codebooks"], space["codes"], tuple(net.policy), net.activation)
    return ActorCritic(RunningNorm(d), pol, ValueNet(d, tuple(net.value), net.activation))
