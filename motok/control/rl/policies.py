"""Policies that own their action distribution (CleanRL's agent shape), so one PPO update serves
continuous and discrete action spaces:

* ``act(x, deterministic) -> (action, logp)``: a sample (or the most likely action) and its
  log-probability, summed over action components;
* ``evaluate(x, action) -> (logp, entropy)``: both summed over components, differentiable.

Policies:

* :class:`MLPPolicy`: diagonal Gaussian with an MLP mean.
* :class:`EncoderDecoderPolicy`: the hybrid-latent paper's expert (appendix B.2): an encoder
  ``E(s, s~) -> z`` and a decoder ``D(s, z) -> a``, Gaussian around the decoder's output. The
  latent is a plain deterministic vector with no regularisation (no KL, no quantisation); the
  structure is what the distillation into the latent priors reuses.
* :class:`MultiCategoricalPolicy`: one categorical per active codebook (``M`` heads of ``K``
  codes each), the high-level policy over a discrete prior's codebook indices; actions are
  ``int64 (N, M)``.

Gaussian policies have a state-independent log standard deviation, either fixed (a buffer) or
learned (a parameter): fixed noise is what PHC and the paper's code use for imitation experts.
"""

from __future__ import annotations

import torch
from torch import nn
from torch.distributions import Normal

from motok.control.rl.networks import mlp


class GaussianPolicy(nn.Module):
    """Diagonal Gaussian over actions; subclasses define ``mean(x)``."""

    action_dtype = torch.float32

    def __init__(self, action_dim: int, log_std: float, learn_log_std: bool):
        super().__init__()
        self.action_shape = (action_dim,)
        init = torch.full((action_dim,), float(log_std))
        if learn_log_std:
            self.log_std = nn.Parameter(init)
        else:
            self.register_buffer("log_std", init)

    def mean(self, x: torch.Tensor) -> torch.Tensor:  # pragma: no cover - abstract
        raise NotImplementedError

    def dist(self, x: torch.Tensor) -> Normal:
        mu = self.mean(x)
        return Normal(mu, self.log_std.exp().expand_as(mu))

    def act(self, x: torch.Tensor, deterministic: bool = False) -> tuple[torch.Tensor, torch.Tensor]:
        d = self.dist(x)
        a = d.mean if deterministic else d.sample()
        return a, d.log_prob(a).sum(-1)

    def evaluate(self, x: torch.Tensor, a: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        d = self.dist(x)
        return d.log_prob(a).sum(-1), d.entropy().sum(-1)


class MLPPolicy(GaussianPolicy):
    def __init__(self, in_dim: int, action_dim: int, hidden=(256, 256), activation="elu", log_std=-1.0,
                 learn_log_std=True):
        super().__init__(action_dim, log_std, learn_log_std)
        self.net = mlp([in_dim, *hidden, action_dim], activation, out_gain=0.01)

    def mean(self, x):
        return self.net(x)


class EncoderDecoderPolicy(GaussianPolicy):
    """Appendix B.2 expert: ``z = E(s, s~)``, ``mu = D(s, z)``. The input is ``[s, s~]`` (normalised)."""

    def __init__(self, obs_dim: int, goal_dim: int, action_dim: int, latent_dim: int = 64,
                 encoder=(512, 256), decoder=(512, 256), activation="elu", log_std=-1.0, learn_log_std=False):
        super().__init__(action_dim, log_std, learn_log_std)
        self.obs_dim = obs_dim
        self.encoder = mlp([obs_dim + goal_dim, *encoder, latent_dim], activation)
        self.decoder = mlp([obs_dim + latent_dim, *decoder, action_dim], activation, out_gain=0.01)

    def encode(self, x: torch.Tensor) -> torch.Tensor:
        return self.encoder(x)

    def mean(self, x):
        s = x[..., :self.obs_dim]
        return self.decoder(torch.cat([s, self.encode(x)], -1))


class MultiCategoricalPolicy(nn.Module):
    """``M`` independent categoricals over ``K`` classes from one MLP: ``logits (N, M, K)``.

    ``log p(a) = sum_m log softmax(l_m)[a_m]``; entropy ``sum_m H(softmax(l_m))``. Deterministic
    actions are each head's argmax."""

    action_dtype = torch.int64

    def __init__(self, in_dim: int, heads: int, classes: int, hidden=(256, 256), activation="elu"):
        super().__init__()
        self.heads, self.classes = int(heads), int(classes)
        self.action_shape = (self.heads,)
        # out_gain 0.01: near-uniform logits at the start, so exploration begins at maximum entropy.
        self.net = mlp([in_dim, *hidden, self.heads * self.classes], activation, out_gain=0.01)

    def log_probs(self, x: torch.Tensor) -> torch.Tensor:
        """``(..., M, K)`` log-probabilities."""
        logits = self.net(x).unflatten(-1, (self.heads, self.classes))
        return torch.log_softmax(logits, -1)

    def act(self, x: torch.Tensor, deterministic: bool = False) -> tuple[torch.Tensor, torch.Tensor]:
        lp = self.log_probs(x)
        if deterministic:
            a = lp.argmax(-1)
        else:
            a = torch.multinomial(lp.exp().flatten(0, -2), 1).view(lp.shape[:-1])
        return a, lp.gather(-1, a[..., None]).squeeze(-1).sum(-1)

    @staticmethod
    def entropies(lp: torch.Tensor) -> torch.Tensor:
        """``(..., M)``: each codebook's entropy from ``log_probs``' ``(..., M, K)``."""
        return -(lp.exp() * lp).sum(-1)

    def evaluate(self, x: torch.Tensor, a: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        lp = self.log_probs(x)
        logp = lp.gather(-1, a.long()[..., None]).squeeze(-1).sum(-1)
        return logp, self.entropies(lp).sum(-1)
