"""Grouped quantizers for the latent priors' margins: group residual VQ (HiFi-Codec, Yang et al.
2023) and finite scalar quantization whose channels form groups (Mentzer et al. 2023).

Both keep the shared conventions (:mod:`motok.quantize.base`) and add one notion the residual
kind did not need: an index *column* is not a codebook. ``num_codebooks`` is still what M counts
(the prefix a batch or a task policy uses); ``columns(m)`` is how many index columns the first M
fill, always a prefix of the columns, so ``indices[..., :columns(m)]`` is what ``decode`` reads;
``codebook_size`` is the number of classes of every column; ``column_groups(m)`` says which group
each column belongs to (what a policy with one head per group reads).

* :class:`GroupedRVQ`: the D dimensions split into G contiguous groups of D / G, each quantized by
  its own :class:`~motok.quantize.rvq.ResidualVQ` of N codebooks; M is the depth used in every
  group (one draw of quantizer dropout for all groups, so a prefix of depth M decodes on its own
  in every group). Columns are level-major, ``column = level * G + group``, so the first M levels
  of every group are the first ``M * G`` columns.
* :class:`GroupedFSQ`: FSQ with ``G * C`` channels of L levels each (one projection in and out, as
  the paper's); column ``c`` is channel ``c``'s level (0..L-1), group ``c // C``. M is the number of
  leading channel groups in use: the others sit at level zero, which needs an odd L. The codes of
  one group are the L^C points of its channels' grid, its levels read as a mixed-radix number.
"""

from __future__ import annotations

from dataclasses import replace

import torch
from torch import Tensor, nn

from motok.quantize.base import (QuantizeOutput, Quantizer, QuantizerConfig, all_reduce_sum, batch_shape,
                                 channels_first, check_indices, code_stats, fp32, from_rows, to_rows)
from motok.quantize.fsq import FSQuantizer
from motok.quantize.rvq import ResidualVQ


def interleave(per_group: list[list], m: int) -> list:
    """Per-group lists of per-level values -> one list in column order (level-major)."""
    return [values[level] for level in range(m) for values in per_group]


class GroupedRVQ(Quantizer):
    """Group residual VQ: see the module docstring. ``cfg.num_codebooks`` is the depth N of every
    group, ``cfg.codebook_size`` the codes of each of the ``G * N`` codebooks."""

    def __init__(self, cfg: QuantizerConfig, groups: int):
        super().__init__(cfg)
        if groups < 1 or cfg.dim % groups:
            raise ValueError(f"group RVQ: dim {cfg.dim} does not split into {groups} equal groups")
        self.groups, self.width = groups, cfg.dim // groups
        self.num_codebooks, self.codebook_size = cfg.num_codebooks, cfg.codebook_size
        # Dropout is drawn once here for all groups; each group is then told its M.
        sub = replace(cfg, kind="rvq", dim=self.width, quantizer_dropout=0.0)
        self.parts = nn.ModuleList(ResidualVQ(sub) for _ in range(groups))

    def columns(self, m: int) -> int:
        return m * self.groups

    def column_groups(self, m: int) -> Tensor:
        return torch.arange(self.groups).repeat(m)

    def _slices(self, x: Tensor) -> list[Tensor]:
        return list(x.split(self.width, -1))

    def forward(self, z: Tensor, num_codebooks: int | None = None) -> QuantizeOutput:
        self._sync_once()
        with fp32(z):
            x = to_rows(z, self.dim)
            # The residual kind's draw (dropout share, M ~ U{1..N}), with this quantizer's generator.
            m = ResidualVQ._active(self, num_codebooks, self._next_generator() if self.training else None)
            outs = [q(part, m) for q, part in zip(self.parts, self._slices(x))]
            zq = torch.cat([o.z_q for o in outs], -1)  # each straight-through: d zq / d x is the identity
            idx = torch.stack([o.indices for o in outs], -1).reshape(len(x), -1)  # (n, N * G), level-major
            # The groups are equal in size, so the mean of their per-element means is the per-element mean.
            losses = {k: torch.stack([o.losses[k] for o in outs]).mean() for k in ("commit", "codebook")}
        n = self.num_codebooks
        stats = {k: interleave([o.stats[k] for o in outs], n) for k in ("usage", "perplexity", "dead")}
        stats["num_active_codebooks"] = m
        return QuantizeOutput(from_rows(zq, z).to(z.dtype), idx.reshape(*batch_shape(z), -1), losses, stats)

    @torch.no_grad()
    def encode(self, z: Tensor, num_codebooks: int | None = None) -> Tensor:
        m = self._check_m(num_codebooks)
        with fp32(z):
            rows = to_rows(z, self.dim)
            idx = torch.stack([q.encode(p, m) for q, p in zip(self.parts, self._slices(rows))], -1)
        return idx.reshape(*batch_shape(z), -1)

    @torch.no_grad()
    def decode(self, indices: Tensor, num_codebooks: int | None = None) -> Tensor:
        """Indices of the first M levels, ``(B, M' * G)`` columns (M' >= M), level-major."""
        check_indices(indices)
        G = self.groups
        if indices.shape[-1] % G:
            raise ValueError(f"group RVQ indices come in multiples of {G} columns, got {indices.shape[-1]}")
        m = self._check_m(num_codebooks if num_codebooks is not None else
                          min(indices.shape[-1] // G, self.num_codebooks))
        per = indices[..., :m * G].unflatten(-1, (m, G))
        # Each group's decode is (B, D / G) or (B, D / G, T): the dimensions are axis 1 either way.
        return torch.cat([q.decode(per[..., g], m) for g, q in enumerate(self.parts)], 1)

    @torch.no_grad()
    def codebooks(self) -> Tensor:
        """``(N * G, K, D)`` in column order, each group's codes in its own dimensions (zero
        elsewhere), so that the sum of one code per column is what :meth:`decode` gives."""
        out = None
        for g, q in enumerate(self.parts):
            books = q.codebooks()
            if out is None:
                out = books.new_zeros(self.num_codebooks * self.groups, self.codebook_size, self.dim)
            for level in range(self.num_codebooks):
                out[level * self.groups + g, :, g * self.width:(g + 1) * self.width] = books[level]
        return out


class GroupedFSQ(FSQuantizer):
    """FSQ over ``groups * channels`` channels of ``levels`` levels: see the module docstring."""

    def __init__(self, cfg: QuantizerConfig, groups: int, channels: int, levels: int):
        if levels < 3 or levels % 2 == 0:
            raise ValueError(f"grouped FSQ needs an odd number of levels >= 3 (a group not in use sits at the "
                             f"zero level), got {levels}")
        super().__init__(replace(cfg, kind="fsq", fsq_levels=[levels] * (groups * channels)))
        self.groups, self.channels, self.num_levels = groups, channels, levels
        self.num_codebooks, self.codebook_size = groups, levels
        self.register_buffer("radix", levels ** torch.arange(channels), persistent=False)

    def columns(self, m: int) -> int:
        return m * self.channels

    def column_groups(self, m: int) -> Tensor:
        return torch.arange(m).repeat_interleave(self.channels)

    def _levels(self, codes: Tensor, m: int) -> Tensor:
        """Channel values in [-1, 1] -> level indices 0..L-1; channels of groups >= m: -1."""
        hw = self.half_width
        level = (codes * hw + hw).round().long()
        return torch.where(torch.arange(codes.shape[-1], device=codes.device) < m * self.channels, level, -1)

    def forward(self, z: Tensor, num_codebooks: int | None = None) -> QuantizeOutput:
        self._sync_once()
        with fp32(z):
            m = ResidualVQ._active(self, num_codebooks, self._next_generator() if self.training else None)
            codes = self._grid_codes(self.project_in(to_rows(z, self.dim)))  # straight-through on the rounding only
            keep = (torch.arange(codes.shape[-1], device=codes.device) < m * self.channels).to(codes.dtype)
            codes = codes * keep  # the groups not in use at the zero level, and no gradient through them
            idx = self._levels(codes.detach(), m)
            out = self.project_out(codes)
            # Statistics per group code (its channels' levels as one mixed-radix number).
            group_code = (idx.clamp(min=0).unflatten(-1, (self.groups, self.channels)) * self.radix).sum(-1)
            counts: list[Tensor | None] = [None] * self.groups
            for g in range(m):
                c = torch.bincount(group_code[:, g], minlength=self.num_levels ** self.channels).float()
                counts[g] = all_reduce_sum(c) if self.training else c
            zero = out.new_zeros(())
        per = [torch.stack(code_stats(c)) if c is not None else out.new_zeros(2) for c in counts]
        values = torch.stack(per).tolist()
        stats = {"usage": [v[0] for v in values], "perplexity": [v[1] for v in values],
                 "dead": [0] * self.groups, "num_active_codebooks": m}
        return QuantizeOutput(from_rows(out, z).to(z.dtype), idx.reshape(*batch_shape(z), -1),
                              {"commit": zero, "codebook": zero.clone()}, stats)

    @torch.no_grad()
    def encode(self, z: Tensor, num_codebooks: int | None = None) -> Tensor:
        m = self._check_m(num_codebooks)
        with fp32(z):
            codes = self._grid_codes(self.project_in(to_rows(z, self.dim)))
            return self._levels(codes, m).reshape(*batch_shape(z), -1)

    @torch.no_grad()
    def decode(self, indices: Tensor, num_codebooks: int | None = None) -> Tensor:
        """Levels of the first M groups' channels, ``(B, M' * C)`` columns (M' >= M); -1 is the zero level."""
        check_indices(indices)
        m = self._check_m(num_codebooks if num_codebooks is not None else
                          min(indices.shape[-1] // self.channels, self.num_codebooks))
        idx = indices[..., :m * self.channels]
        with fp32(indices):
            hw = self.half_width[:idx.shape[-1]]
            values = torch.where(idx >= 0, (idx - hw) / hw, torch.zeros((), device=idx.device))
            full = torch.zeros(*idx.shape[:-1], self.groups * self.channels, device=idx.device)
            full[..., :idx.shape[-1]] = values
            return channels_first(self.project_out(full))

    @torch.no_grad()
    def codebooks(self) -> Tensor:
        """``(G * C, L, D)``: what each channel's level adds through the output projection (its bias,
        which every code shares, not included)."""
        hw, device = float(self.half_width[0]), self.half_width.device
        values = (torch.arange(self.num_levels, dtype=torch.float32, device=device) - hw) / hw  # (L,)
        eye = torch.eye(self.groups * self.channels, device=device)
        weight = self.project_out.weight.T if isinstance(self.project_out, nn.Linear) else eye
        return values[None, :, None] * weight[:, None, :]
