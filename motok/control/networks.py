"""Policy and value networks for PPO, and the running observation normaliser they carry.

* :class:`RunningNorm`: per-feature running mean and variance (Chan et al.'s parallel update),
  held as buffers so the statistics are saved in the policy's state dict and travel with it.
* :class:`MLPPolicy`: a Gaussian policy with an MLP mean.
* :class:`EncoderDecoderPolicy`: the hybrid-latent paper's expert (appendix B.2): an encoder
  ``E(s, s~) -> z`` and a decoder ``D(s, z) -> a``. The latent is a plain deterministic vector
  with no regularisation (no KL, no quantisation); the structure is what the later distillation
  into the hybrid latent prior reuses.
* :class:`ValueNet`: an MLP critic on the same (normalised) input.

Both policies have a state-independent log standard deviation, either fixed (a buffer) or
learned (a parameter): fixed noise is what PHC and the paper's code use for imitation experts.
"""

from __future__ import annotations

import math

import torch
from torch import nn
from torch.distributions import Normal

ACTIVATIONS = {"relu": nn.ReLU, "elu": nn.ELU, "tanh": nn.Tanh, "silu": nn.SiLU}


def mlp(sizes: list[int], activation: str = "elu", out_gain: float = 1.0) -> nn.Sequential:
    """Linear layers with ``activation`` between them (not after the last).

    Orthogonal initialisation (CleanRL's choice); a small ``out_gain`` on the last layer starts
    a policy near its mean action and a critic near zero.
    """
    act = ACTIVATIONS[activation]
    layers: list[nn.Module] = []
    for i in range(len(sizes) - 1):
        lin = nn.Linear(sizes[i], sizes[i + 1])
        last = i == len(sizes) - 2
        nn.init.orthogonal_(lin.weight, out_gain if last else math.sqrt(2))
        nn.init.zeros_(lin.bias)
        layers.append(lin)
        if not last:
            layers.append(act())
    return nn.Sequential(*layers)


class RunningNorm(nn.Module):
    """``(x - mean) / sqrt(var + eps)`` clipped to ``[-clip, clip]``, statistics updated by batches."""

    def __init__(self, dim: int, clip: float = 5.0, eps: float = 1e-5):
        super().__init__()
        self.clip, self.eps = clip, eps
        self.register_buffer("mean", torch.zeros(dim, dtype=torch.float64))
        self.register_buffer("var", torch.ones(dim, dtype=torch.float64))
        self.register_buffer("count", torch.tensor(0.0, dtype=torch.float64))

    @torch.no_grad()
    def update(self, x: torch.Tensor) -> None:
        x = x.reshape(-1, x.shape[-1]).to(torch.float64)
        n = float(len(x))
        if n == 0:
            return
        m, v = x.mean(0), x.var(0, unbiased=False)
        total = self.count + n
        delta = m - self.mean
        # Merge two (mean, M2) summaries exactly, so the order of batches barely matters.
        m2 = self.var * self.count + v * n + delta**2 * self.count * n / total
        self.mean.add_(delta * n / total)
        self.var.copy_(m2 / total)
        self.count.fill_(total)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        y = (x - self.mean.to(x.dtype)) / torch.sqrt(self.var.to(x.dtype) + self.eps)
        return y.clamp(-self.clip, self.clip)


class GaussianPolicy(nn.Module):
    """Diagonal Gaussian over actions; subclasses define ``mean(x)``."""

    def __init__(self, action_dim: int, log_std: float, learn_log_std: bool):
        super().__init__()
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


class ValueNet(nn.Module):
    def __init__(self, in_dim: int, hidden=(512, 256), activation="elu"):
        super().__init__()
        self.net = mlp([in_dim, *hidden, 1], activation, out_gain=1.0)

    def forward(self, x):
        return self.net(x).squeeze(-1)


class ActorCritic(nn.Module):
    """What PPO optimises and a checkpoint stores: normaliser + policy + value."""

    def __init__(self, norm: RunningNorm, policy: GaussianPolicy, value: ValueNet):
        super().__init__()
        self.norm, self.policy, self.value = norm, policy, value

    @torch.no_grad()
    def act(self, x_raw: torch.Tensor, deterministic: bool = False):
        """Normalised input, sampled (or mean) action, its log-probability and the state value."""
        xn = self.norm(x_raw)
        d = self.policy.dist(xn)
        a = d.mean if deterministic else d.sample()
        return xn, a, d.log_prob(a).sum(-1), self.value(xn)
