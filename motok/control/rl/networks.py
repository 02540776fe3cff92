"""Policy and value networks for PPO, and the running observation normaliser they carry.

* :class:`RunningNorm`: per-feature running mean and variance (Chan et al.'s parallel update),
  held as buffers so the statistics are saved in the policy's state dict and travel with it.
* :class:`ValueNet`: an MLP critic on the (normalised) policy input.
* :class:`ActorCritic`: normaliser + policy (``motok.control.rl.policies``, which own their action
  distributions) + value, the unit PPO optimises and a checkpoint stores.
"""

from __future__ import annotations

import math

import torch
import torch.distributed as dist
from torch import nn

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
        """Merge a batch; under ``torchrun`` the batch is every rank's, so all ranks keep one normaliser."""
        x = x.reshape(-1, x.shape[-1]).to(torch.float64)
        if dist.is_available() and dist.is_initialized() and dist.get_world_size() > 1:
            n, m, v = self._global_moments(x)
        else:
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

    @staticmethod
    def _global_moments(x: torch.Tensor) -> tuple[float, torch.Tensor, torch.Tensor]:
        sums = torch.cat([torch.tensor([float(len(x))], dtype=torch.float64, device=x.device), x.sum(0),
                          (x * x).sum(0)])
        dist.all_reduce(sums)
        d = x.shape[1]
        n = float(sums[0])
        m = sums[1:1 + d] / n
        return n, m, (sums[1 + d:] / n - m * m).clamp_min(0.0)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        y = (x - self.mean.to(x.dtype)) / torch.sqrt(self.var.to(x.dtype) + self.eps)
        return y.clamp(-self.clip, self.clip)


class ValueNet(nn.Module):
    def __init__(self, in_dim: int, hidden=(512, 256), activation="elu"):
        super().__init__()
        self.net = mlp([in_dim, *hidden, 1], activation, out_gain=1.0)

    def forward(self, x):
        return self.net(x).squeeze(-1)


class ActorCritic(nn.Module):
    """What PPO optimises and a checkpoint stores: normaliser + policy + value."""

    def __init__(self, norm: RunningNorm, policy: nn.Module, value: ValueNet):
        super().__init__()
        self.norm, self.policy, self.value = norm, policy, value

    @torch.no_grad()
    def act(self, x_raw: torch.Tensor, deterministic: bool = False):
        """Normalised input, sampled (or most likely) action, its log-probability and the state value."""
        xn = self.norm(x_raw)
        a, logp = self.policy.act(xn, deterministic)
        return xn, a, logp, self.value(xn)
