"""The high-level policy's categorical heads for grouped priors.

A part-wise prior (``hybrid-parts``) has one group of code columns per body part. Its high-level
policy has one network per part, each with one categorical per active codebook of its part, so
that a task with one goal per part (a composition task: walk somewhere, wave) can give each part's
network its own inputs later without touching the prior or the action map. The actions are laid
out in the prior's column order (``quantizer.column_groups``), which is what
``LatentPrior.codes_to_latent`` reads.
"""

from __future__ import annotations

import torch
from torch import nn

from motok.control.rl.policies import MultiCategoricalPolicy


class PartCategoricalPolicy(nn.Module):
    """One :class:`MultiCategoricalPolicy` per group of columns (``groups[c]`` is column c's
    group, ``names[g]`` group g's name); ``log p`` and the entropy are sums over every head, as
    for one policy with all the heads (the groups are independent given the input)."""

    action_dtype = torch.int64

    def __init__(self, in_dim: int, groups: torch.Tensor, classes: int, names: tuple[str, ...], hidden=(256, 256),
                 activation="elu"):
        super().__init__()
        groups = torch.as_tensor(groups, dtype=torch.long)
        self.names = tuple(names)
        self.action_shape = (len(groups),)
        for g in range(len(self.names)):
            self.register_buffer(f"columns_{g}", torch.nonzero(groups == g).flatten(), persistent=False)
        self.parts = nn.ModuleDict({n: MultiCategoricalPolicy(in_dim, len(self.columns(g)), classes, hidden, activation)
                                    for g, n in enumerate(self.names)})

    def columns(self, g: int) -> torch.Tensor:
        """The action columns part ``g`` chooses."""
        return getattr(self, f"columns_{g}")

    def act(self, x: torch.Tensor, deterministic: bool = False) -> tuple[torch.Tensor, torch.Tensor]:
        a = torch.empty(*x.shape[:-1], *self.action_shape, dtype=torch.long, device=x.device)
        logp = x.new_zeros(x.shape[:-1])
        for g, n in enumerate(self.names):
            a_g, lp = self.parts[n].act(x, deterministic)
            a[..., self.columns(g)] = a_g
            logp = logp + lp
        return a, logp

    def evaluate(self, x: torch.Tensor, a: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        logp, ent = x.new_zeros(x.shape[:-1]), x.new_zeros(x.shape[:-1])
        for g, n in enumerate(self.names):
            lp, h = self.parts[n].evaluate(x, a[..., self.columns(g)])
            logp, ent = logp + lp, ent + h
        return logp, ent
