"""Residual vector quantization (seed paper Eq. 5; MoMask Sec. 3.1), kind ``rvq``.

r_0 = z, q_i = Q_i(r_{i-1}), r_i = r_{i-1} - q_i, z_q = sum_{i<=M} q_i, with each Q_i a
:class:`~motok.quantize.vq.VectorQuantizer` of kind ``cfg.rvq_base``. Conventions and shapes:
:mod:`motok.quantize.base`.
"""

from __future__ import annotations

import torch
from torch import Tensor, nn

from motok.quantize.base import (QuantizeOutput, Quantizer, QuantizerConfig, batch_shape, channels_first,
                                 check_indices, fp32, straight_through, to_rows)
from motok.quantize.vq import VectorQuantizer


class ResidualVQ(Quantizer):
    """N residual codebooks; a prefix of M <= N of them quantizes each batch.

    - Quantizer dropout (MoMask): in training, with probability ``cfg.quantizer_dropout`` a batch
      uses only the first M ~ U{1..N} codebooks, so every prefix learns to reconstruct on its
      own; the rest get index -1 and are not updated. M comes from the generator shared by all
      ranks, so every rank runs the same layers and their collectives line up. An explicit
      ``num_codebooks`` overrides the draw, in training as at inference.
    - Losses: the mean over the M active layers of each layer's loss on its own residual
      (commit = mean ||r_{i-1} - sg(q_i)||^2), as MoMask.
    - Gradient: ``z_q`` is straight-through once, on the sum, so z receives the upstream
      gradient unchanged. (Summing per-layer straight-through outputs, as MoMask and
      vector-quantize-pytorch do, scales it by M.)
    - Inference: any M <= N; ``encode`` pads the unused codebooks with -1 and ``decode`` sums
      the first M codebooks' vectors, skipping -1.

    Shapes: ``z`` (B, D) -> ``z_q`` (B, D), indices (B, N); ``z`` (B, D, T) -> ``z_q``
    (B, D, T), indices (B, T, N). ``decode`` also takes fewer than N index columns.
    """

    def __init__(self, cfg: QuantizerConfig):
        super().__init__(cfg)
        self.num_codebooks, self.codebook_size = cfg.num_codebooks, cfg.codebook_size
        self.layers = nn.ModuleList(VectorQuantizer(cfg, kind=cfg.rvq_base) for _ in range(cfg.num_codebooks))

    def _active(self, requested: int | None, g: torch.Generator | None) -> int:
        if requested is not None:
            return self._check_m(requested)
        if g is None:
            return self.num_codebooks
        # Both numbers are always drawn so the shared generator advances the same way every step.
        drop = float(torch.rand(1, generator=g)) < self.cfg.quantizer_dropout
        m = int(torch.randint(1, self.num_codebooks + 1, (1,), generator=g))
        return m if drop else self.num_codebooks

    def _residual(self, x: Tensor, m: int, update: bool):
        q_sum, r = torch.zeros_like(x), x
        idx = torch.full((x.shape[0], self.num_codebooks), -1, dtype=torch.long, device=x.device)
        commit, codebook = [], []
        counts: list[Tensor | None] = [None] * self.num_codebooks
        dead = [0] * self.num_codebooks
        for i, layer in enumerate(self.layers[:m]):
            q, idx[:, i], losses, counts[i], dead[i] = layer.quantize_rows(r, update)
            r = r - q
            q_sum = q_sum + q
            commit.append(losses["commit"])
            codebook.append(losses["codebook"])
        losses = {"commit": torch.stack(commit).mean(), "codebook": torch.stack(codebook).mean()}
        return q_sum, idx, losses, counts, dead

    def forward(self, z: Tensor, num_codebooks: int | None = None) -> QuantizeOutput:
        self._sync_once()
        with fp32(z):
            x = to_rows(z, self.dim)
            m = self._active(num_codebooks, self._next_generator() if self.training else None)
            q, idx, losses, counts, dead = self._residual(x, m, self.training)
            zq = straight_through(x, q)
        return self._output(z, zq, idx, losses, counts, dead, m)

    @torch.no_grad()
    def encode(self, z: Tensor, num_codebooks: int | None = None) -> Tensor:
        m = self._check_m(num_codebooks)
        with fp32(z):
            idx = self._residual(to_rows(z, self.dim), m, update=False)[1]
        return idx.reshape(*batch_shape(z), self.num_codebooks)

    @torch.no_grad()
    def decode(self, indices: Tensor, num_codebooks: int | None = None) -> Tensor:
        """indices (B, N') or (B, T, N') with N' <= N columns (coarse token sets are accepted)."""
        check_indices(indices)
        m = self._check_m(num_codebooks if num_codebooks is not None else min(indices.shape[-1], self.num_codebooks))
        if m > indices.shape[-1]:
            raise ValueError(f"asked for {m} codebooks but indices have {indices.shape[-1]} columns")
        # Same accumulation order as forward, so decode(encode(z)) reproduces z_q bit for bit.
        out = torch.zeros(*indices.shape[:-1], self.dim, device=indices.device)
        for i, layer in enumerate(self.layers[:m]):
            out = out + layer.lookup(indices[..., i])
        return channels_first(out)

    def codebooks(self) -> Tensor:
        return torch.stack([layer.embed.detach() for layer in self.layers])
