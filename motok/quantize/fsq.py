"""Finite scalar quantization (Mentzer et al. 2023), kind ``fsq``: a codebook-free alternative
to the VQ kinds. Conventions and shapes: :mod:`motok.quantize.base`."""

from __future__ import annotations

import math

import torch
from torch import Tensor, nn

from motok.quantize.base import (QuantizeOutput, Quantizer, QuantizerConfig, all_reduce_sum, batch_shape,
                                 channels_first, check_indices, fp32, straight_through, to_rows)


class FSQuantizer(Quantizer):
    """Finite scalar quantization (Mentzer et al. 2023): project to d = len(levels) channels,
    bound each channel with tanh to L_i levels, round with a straight-through gradient, and
    project back. The implicit codebook is the grid of prod(levels) points; there are no
    codebook parameters, no auxiliary loss (both losses are zero) and nothing to reset.

    Channel i takes L_i values evenly spaced in [-1, 1]. For even L_i the grid is the symmetric
    half-integer one (round(b - 1/2) + 1/2) rather than the reference code's shifted grid, which
    keeps z = 0 at the centre and makes L_i = 2 valid. Unlike the VQ kinds, the gradient to z
    is not the identity: the straight-through estimator sits on the rounding only, so the
    gradient passes through tanh and the projections, as in the paper.

    Shapes: ``z`` (B, D) -> ``z_q`` (B, D), indices (B, 1); ``z`` (B, D, T) -> ``z_q``
    (B, D, T), indices (B, T, 1); an index is the mixed-radix number of the grid point.
    """

    def __init__(self, cfg: QuantizerConfig):
        super().__init__(cfg)
        levels = [int(v) for v in cfg.fsq_levels]
        self.num_codebooks, self.codebook_size = 1, math.prod(levels)
        basis = [math.prod(levels[:i]) for i in range(len(levels))]
        self.register_buffer("levels", torch.tensor(levels, dtype=torch.long), persistent=False)
        self.register_buffer("basis", torch.tensor(basis, dtype=torch.long), persistent=False)
        self.register_buffer("half_width", (self.levels.float() - 1) / 2, persistent=False)
        self.register_buffer("shift", (1 - self.levels % 2).float() / 2, persistent=False)  # 1/2 for even L
        d = len(levels)
        self.project_in = nn.Linear(cfg.dim, d) if cfg.dim != d else nn.Identity()
        self.project_out = nn.Linear(d, cfg.dim) if cfg.dim != d else nn.Identity()

    def _grid_codes(self, h: Tensor) -> Tensor:
        bounded = torch.tanh(h) * self.half_width
        grid = torch.round(bounded.detach() - self.shift) + self.shift
        return straight_through(bounded, grid) / self.half_width

    def _to_indices(self, codes: Tensor) -> Tensor:
        return ((codes * self.half_width + self.half_width).round().long() * self.basis).sum(-1)

    def _to_codes(self, idx: Tensor) -> Tensor:
        return ((idx[..., None] // self.basis) % self.levels - self.half_width) / self.half_width

    def forward(self, z: Tensor, num_codebooks: int | None = None) -> QuantizeOutput:
        self._check_m(num_codebooks)
        self._sync_once()
        with fp32(z):
            codes = self._grid_codes(self.project_in(to_rows(z, self.dim)))
            idx = self._to_indices(codes.detach())
            out = self.project_out(codes)
            counts = torch.bincount(idx, minlength=self.codebook_size).float()
            if self.training:
                counts = all_reduce_sum(counts)
            zero = out.new_zeros(())
        return self._output(z, out, idx[:, None], {"commit": zero, "codebook": zero.clone()}, [counts], [0], 1)

    @torch.no_grad()
    def encode(self, z: Tensor, num_codebooks: int | None = None) -> Tensor:
        self._check_m(num_codebooks)
        with fp32(z):
            codes = self._grid_codes(self.project_in(to_rows(z, self.dim)))
            return self._to_indices(codes).reshape(*batch_shape(z), 1)

    @torch.no_grad()
    def decode(self, indices: Tensor, num_codebooks: int | None = None) -> Tensor:
        self._check_m(num_codebooks)
        check_indices(indices)
        with fp32(indices):
            return channels_first(self.project_out(self._to_codes(indices[..., 0])))

    @torch.no_grad()
    def codebooks(self) -> Tensor:
        idx = torch.arange(self.codebook_size, device=self.levels.device)
        return self.project_out(self._to_codes(idx))[None]
