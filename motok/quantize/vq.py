"""The single-codebook vector quantizer: kinds ``vq`` (codebook learned by gradient, VQ-VAE,
van den Oord et al. 2017 / T2M-GPT Sec. 3.1, Eq. 1-3), ``ema`` (codebook as moving averages,
van den Oord et al. 2017 app. A.1 / Razavi et al. 2019), ``reset`` and ``ema_reset`` (the same
plus T2M-GPT's dead-code reset). Conventions and shapes: :mod:`motok.quantize.base`.
"""

from __future__ import annotations

from typing import NamedTuple

import torch
import torch.nn.functional as F
from torch import Tensor, nn

from motok.quantize.base import (QuantizeOutput, Quantizer, QuantizerConfig, all_reduce_sum, batch_shape,
                                 channels_first, check_indices, draw_rows, fp32, straight_through, to_rows,
                                 world_size)

VQ_KINDS = ("vq", "ema", "reset", "ema_reset")
INITS = ("uniform", "batch", "t2m_gpt", "kmeans")  # QuantizerConfig.init
KMEANS_ITERS = 10


def init_method(cfg: QuantizerConfig, kind: str) -> str:
    """How a codebook of ``kind`` starts: ``"uniform"``, ``"batch"`` or ``"kmeans"``.

    ``init="t2m_gpt"`` follows T2M-GPT's ``models/quantize_cnn.py``: its plain ``Quantizer``
    draws U(-1/K, 1/K) (van den Oord et al.), while ``QuantizeEMA``, ``QuantizeReset`` and
    ``QuantizeEMAReset`` take their codes from the first training batch (``init_codebook``).
    ``kmeans_init=True`` is the older spelling of ``init="kmeans"``.
    """
    if cfg.kmeans_init:
        return "kmeans"
    if cfg.init == "t2m_gpt":
        return "uniform" if kind == "vq" else "batch"
    return cfg.init


def squared_distances(x: Tensor, codes: Tensor) -> Tensor:
    """(n, D) x (K, D) -> (n, K) as ||x||^2 - 2 x.e + ||e||^2: one matmul, no (n, K, D) tensor."""
    return torch.addmm(x.pow(2).sum(1, keepdim=True) + codes.pow(2).sum(1), x, codes.t(), alpha=-2.0)


def nearest_code(x: Tensor, codes: Tensor) -> Tensor:
    """Eq. 1 of T2M-GPT: index of the closest code (squared Euclidean) for each row of x."""
    with torch.no_grad():
        return squared_distances(x, codes).argmin(1)


class RowQuantization(NamedTuple):
    """What :meth:`VectorQuantizer.quantize_rows` returns for rows ``x`` (n, D)."""
    codes: Tensor                # (n, D) code values, detached
    indices: Tensor              # (n,) int64
    losses: dict[str, Tensor]    # "commit", "codebook" (see VectorQuantizer)
    counts: Tensor               # (K,) code histogram; all-rank when the codebook was updated
    dead: int                    # codes reset in this step


class VectorQuantizer(Quantizer):
    """One codebook of K vectors; ``kind`` (or ``cfg.kind``) selects how it learns.

    - Assignment (all kinds): nearest code, T2M-GPT Eq. 1; ``z_q`` is straight-through (Eq. 3).
    - Losses (Eq. 2, L_vq = ||sg[e] - e_q|| + beta ||e - sg[e_q]||, as mean squared errors):
      ``commit`` = mean ||z - sg(z_q)||^2 always; ``codebook`` = mean ||sg(z) - z_q||^2 for the
      gradient-learned kinds (``vq``, ``reset``), zero for the EMA kinds.
    - ``ema``/``ema_reset`` (van den Oord 2017 app. A.1, Razavi 2019): with n_k vectors assigned
      to code k, N_k <- decay N_k + (1-decay) n_k, m_k <- decay m_k + (1-decay) sum z, and
      e_k = m_k / N~_k with N~_k = (N_k + eps) / (sum N + K eps) * sum N (Laplace smoothing).
      Counts start at 1 and sums at the initial codes, as in T2M-GPT, so e_k starts where it was.
    - ``reset``/``ema_reset`` (T2M-GPT Sec. 3.1): every ``reset_window`` training steps, codes
      whose usage (EMA count, or for ``reset`` the count accumulated over the window) is below
      ``reset_threshold`` are replaced by randomly chosen encoder outputs of the current batch.
      A replaced EMA code restarts with count max(threshold, 1), so it survives the next check
      only if it wins about ``threshold`` vectors.
    - Start (:func:`init_method`): every kind first draws U(-1/K, 1/K) (which keeps the global
      RNG draw order of fixed-seed runs); ``batch`` and ``kmeans`` then replace the codes with
      the first training batch's (:meth:`_data_init`).

    Shapes: ``z`` (B, D) -> ``z_q`` (B, D), indices (B, 1); ``z`` (B, D, T) -> ``z_q``
    (B, D, T), indices (B, T, 1). Every ``(B, D, T)`` row (b, :, t) is one vector to quantize.
    """

    def __init__(self, cfg: QuantizerConfig, kind: str | None = None):
        super().__init__(cfg)
        self.kind = kind or cfg.kind
        K, D = cfg.codebook_size, cfg.dim
        self.num_codebooks, self.codebook_size = 1, K
        self.learned = self.kind in ("vq", "reset")
        self.uses_ema = self.kind in ("ema", "ema_reset")
        self.resets = self.kind in ("reset", "ema_reset")
        self.init_method = init_method(cfg, self.kind)
        init = torch.empty(K, D).uniform_(-1.0 / K, 1.0 / K)  # van den Oord's init, as T2M-GPT's plain VQ
        if self.learned:
            self.embed = nn.Parameter(init)
        else:
            self.register_buffer("embed", init)
            self.register_buffer("ema_count", torch.ones(K))
            self.register_buffer("ema_sum", init.clone())
        if self.kind == "reset":
            self.register_buffer("window_count", torch.zeros(K))
        # Integer, not bool: gloo cannot broadcast bool tensors. 0: codes come from the first batch.
        self.register_buffer("initted", torch.tensor([1 if self.init_method == "uniform" else 0]))

    def quantize_rows(self, x: Tensor, update: bool) -> RowQuantization:
        """Rows x (n, D) float32 -> codes, indices, losses, histogram and number of codes reset.

        With ``update`` (training) the histogram is the all-rank one and the codebook is updated
        after the codes are read, so returned codes are those of the codebook the batch was
        assigned to. :class:`~motok.quantize.rvq.ResidualVQ` calls this once per residual layer.
        """
        g = self._next_generator() if update else None
        if update and not int(self.initted):
            self._data_init(x, g)
        idx = nearest_code(x, self.embed)
        q = self.embed[idx]
        losses = {"commit": F.mse_loss(x, q.detach()),
                  "codebook": F.mse_loss(q, x.detach()) if self.learned else x.new_zeros(())}
        counts = torch.bincount(idx, minlength=self.codebook_size).float()
        dead = 0
        if update:
            with torch.no_grad():
                counts, dead = self._update(x, idx, counts, g)
        return RowQuantization(q.detach(), idx, losses, counts, dead)

    def _update(self, x: Tensor, idx: Tensor, counts: Tensor, g: torch.Generator) -> tuple[Tensor, int]:
        if self.uses_ema:
            # A one-hot matmul rather than index_add_: deterministic on GPU, so reruns match.
            sums = F.one_hot(idx, self.codebook_size).float().t() @ x
            packed = all_reduce_sum(torch.cat([counts[:, None], sums], 1))  # one collective
            counts, sums = packed[:, 0], packed[:, 1:]
            d = self.cfg.decay
            self.ema_count.mul_(d).add_(counts, alpha=1 - d)
            self.ema_sum.mul_(d).add_(sums, alpha=1 - d)
            total = self.ema_count.sum()
            K, eps = self.codebook_size, self.cfg.eps
            smoothed = (self.ema_count + eps) / (total + K * eps) * total
            self.embed.copy_(self.ema_sum / smoothed[:, None])
        else:
            counts = all_reduce_sum(counts)
        return counts, (self._reset_dead(x, counts, g) if self.resets else 0)

    def _reset_dead(self, x: Tensor, counts: Tensor, g: torch.Generator) -> int:
        if self.kind == "reset":
            self.window_count += counts
        if int(self.train_steps) % self.cfg.reset_window:
            return 0
        usage = self.ema_count if self.uses_ema else self.window_count
        dead = (usage < self.cfg.reset_threshold).nonzero().squeeze(1)
        if self.kind == "reset":
            self.window_count.zero_()
        if dead.numel() == 0:
            return 0
        new = draw_rows(x, dead.numel(), g)
        self.embed.data.index_copy_(0, dead, new)
        if self.uses_ema:
            c = max(self.cfg.reset_threshold, 1.0)
            self.ema_count.index_fill_(0, dead, c)
            self.ema_sum.index_copy_(0, dead, new * c)
        return dead.numel()

    @torch.no_grad()
    def _data_init(self, x: Tensor, g: torch.Generator) -> None:
        """Codes from the first training batch ``x`` (every rank's rows), then EMA counts 1 and
        sums equal to the codes, as T2M-GPT's ``init_codebook`` (``kmeans``: counts the cluster
        sizes, as vector-quantize-pytorch's k-means start; with counts 1 every code would fall
        under a reset threshold above 1 at the first update, and the clustering would be lost).

        - ``batch``: K rows of the batch. T2M-GPT takes the first K rows of its shuffled batch;
          here K rows are drawn without replacement from all ranks' rows, so ranks agree. A
          batch with fewer rows than codes is tiled as T2M-GPT's ``_tile`` does (every row
          repeated; across ranks rows are drawn with replacement), and whenever the codes are
          not distinct every code gets N(0, (0.01/sqrt(D))^2) noise, as ``_tile`` adds: exact
          copies would tie, and all but the first copy would never win a vector.
        - ``kmeans``: those rows refined by Lloyd's algorithm; sums are all-reduced, so it
          clusters all ranks' rows.
        """
        K, n = self.codebook_size, x.shape[0]
        if self.init_method == "batch" and n < K and world_size() == 1:
            # T2M-GPT's _tile: every row repeated, so each row of a small batch gets a code.
            order = torch.cat([torch.randperm(n, generator=g) for _ in range(-(-K // n))])[:K]
            c = x[order.to(x.device)]
        else:
            c = draw_rows(x, K, g)
        if self.init_method == "kmeans":
            for _ in range(KMEANS_ITERS):
                idx = nearest_code(x, c)
                one_hot = F.one_hot(idx, K).float()
                packed = all_reduce_sum(torch.cat([one_hot.sum(0)[:, None], one_hot.t() @ x], 1))
                n, s = packed[:, :1], packed[:, 1:]
                c = torch.where(n > 0, s / n.clamp(min=1), c)  # empty clusters keep their centre
            # the final centres' cluster sizes; an empty cluster counts 1, as a batch start's codes
            count = all_reduce_sum(F.one_hot(nearest_code(x, c), K).float().sum(0)).clamp(min=1.0)
        elif len(c.unique(dim=0)) < K:  # c is identical on every rank, so is this decision
            c = c + torch.randn(c.shape, generator=g).to(c) * (0.01 / self.dim ** 0.5)
        self.embed.data.copy_(c)
        if self.uses_ema:
            if self.init_method == "kmeans":
                self.ema_count.copy_(count)
                self.ema_sum.copy_(c * count[:, None])
            else:
                self.ema_sum.copy_(c)
                self.ema_count.fill_(1.0)
        self.initted.fill_(1)

    def lookup(self, idx: Tensor) -> Tensor:
        """Code vectors for ``idx`` (any shape) -> (*idx.shape, D); -1 gives zeros."""
        valid = idx >= 0
        return self.embed.detach()[idx.clamp(min=0)].masked_fill(~valid[..., None], 0.0)

    def forward(self, z: Tensor, num_codebooks: int | None = None) -> QuantizeOutput:
        self._check_m(num_codebooks)
        self._sync_once()
        with fp32(z):
            x = to_rows(z, self.dim)
            r = self.quantize_rows(x, self.training)
            zq = straight_through(x, r.codes)
        return self._output(z, zq, r.indices[:, None], r.losses, [r.counts], [r.dead], 1)

    @torch.no_grad()
    def encode(self, z: Tensor, num_codebooks: int | None = None) -> Tensor:
        self._check_m(num_codebooks)
        with fp32(z):
            return nearest_code(to_rows(z, self.dim), self.embed).reshape(*batch_shape(z), 1)

    @torch.no_grad()
    def decode(self, indices: Tensor, num_codebooks: int | None = None) -> Tensor:
        self._check_m(num_codebooks)
        check_indices(indices)
        return channels_first(self.lookup(indices[..., 0]))

    def codebooks(self) -> Tensor:
        return self.embed.detach()[None]
