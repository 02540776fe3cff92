"""Quantizers for the motion tokenizer: encoder outputs ``z`` (B, D, T) to discrete codes and back.

One interface (:class:`Quantizer`, built with :func:`build_quantizer`) covers every kind:
``vq`` (codebook learned by gradient, T2M-GPT Sec. 3.1, Eq. 1-3), ``ema`` (codebook as moving
averages, van den Oord et al. 2017 app. A.1 / Razavi et al. 2019), ``reset`` and ``ema_reset``
(the same plus T2M-GPT's dead-code reset), ``rvq`` (residual VQ, :mod:`motok.tokenizer.rvq`)
and ``fsq`` (finite scalar quantization, Mentzer et al. 2023, :mod:`motok.tokenizer.fsq`). Shared conventions:

- Distances and codebook statistics are computed in float32 with autocast off, whatever the
  encoder's precision: argmin over bf16 distances flips assignments between nearly equal codes.
- ``z_q`` carries the code values exactly (not ``z + (q - z)`` rounded) and passes the incoming
  gradient to ``z`` unchanged (the straight-through estimator of Eq. 3). The commitment weight
  (``cfg.beta``) is applied by the trainer, not here.
- Codebooks change only in training mode, inside ``forward``. ``encode``/``decode`` never change
  state, and eval-mode ``forward`` issues no collectives, so ranks may evaluate unequal numbers
  of batches.

Distributed training (``torch.distributed`` initialized): the first training ``forward``
copies rank 0's parameters and buffers to every rank; per-code counts and sums are all-reduced
(SUM) before each update, so dead-code decisions agree; replacement vectors are gathered from
all ranks and chosen by a generator whose seed and step counter are buffers (identical on all
ranks), so codebooks stay bit-identical without relying on DDP's buffer broadcast.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import torch
import torch.distributed as dist
import torch.nn.functional as F
from torch import Tensor, nn

KINDS = ("vq", "ema", "reset", "ema_reset", "rvq", "fsq")
SINGLE_KINDS = ("vq", "ema", "reset", "ema_reset")
KMEANS_ITERS = 10


@dataclass
class QuantizerConfig:
    kind: str = "ema_reset"        # one of KINDS
    codebook_size: int = 512       # ignored by fsq, whose codebook has prod(fsq_levels) codes
    dim: int = 512                 # code dimension
    beta: float = 1.0              # commitment weight, for the trainer: losses["commit"] is unweighted
    decay: float = 0.99            # EMA decay
    eps: float = 1e-5              # Laplace smoothing of EMA counts
    reset_threshold: float = 1.0   # a code is dead if its (EMA or windowed) usage count < threshold
    reset_window: int = 1          # training steps between dead-code checks (1 = every step, as T2M-GPT)
    num_codebooks: int = 1         # rvq: number of residual codebooks
    rvq_base: str = "ema_reset"    # rvq: how each residual codebook learns (one of SINGLE_KINDS)
    quantizer_dropout: float = 1.0  # rvq: probability that a training batch uses only M ~ U{1..N} codebooks
    kmeans_init: bool = False      # initialise codebooks by k-means on the first training batch
    fsq_levels: list[int] = field(default_factory=lambda: [8, 5, 5, 5])


@dataclass
class QuantizeOutput:
    z_q: Tensor                      # (B, D, T) code values; gradient passes to z unchanged
    indices: Tensor                  # (B, T, N) int64; -1 for codebooks not used (rvq)
    losses: dict[str, Tensor]        # "commit", "codebook": zero-dim, unweighted
    stats: dict[str, float | list]   # "usage", "perplexity", "dead" (per codebook), "num_active_codebooks"


# --- distributed helpers ------------------------------------------------------------------
# Collectives run only in training mode and only behind decisions every rank computes from
# reduced or shared-seed values, so all ranks issue the same collectives in the same order.

def _distributed() -> bool:
    return dist.is_available() and dist.is_initialized()


def _all_reduce_sum(t: Tensor) -> Tensor:
    if _distributed():
        dist.all_reduce(t, op=dist.ReduceOp.SUM)
    return t


def draw_rows(x: Tensor, n: int, g: torch.Generator) -> Tensor:
    """``n`` rows drawn from the union of every rank's ``x`` (n_local, D), identical on all ranks.

    Each rank proposes ``n`` of its own rows; the shared generator ``g`` picks which rank's
    proposal fills each slot. Only draws whose size does not depend on the local batch come
    from ``g``, so ranks with unequal batch sizes keep their generators in step.
    """
    world = dist.get_world_size() if _distributed() else 1
    src = torch.randint(world, (n,), generator=g)
    local_g = torch.Generator().manual_seed(int(torch.randint(2**62, (1,), generator=g)))
    m = x.shape[0]
    # Without replacement when possible: duplicated codes split their cluster and one dies again.
    pick = torch.randperm(m, generator=local_g)[:n] if m >= n else torch.randint(m, (n,), generator=local_g)
    local = x[pick.to(x.device)].contiguous()
    if world == 1:
        return local
    gathered = [torch.empty_like(local) for _ in range(world)]
    dist.all_gather(gathered, local)
    return torch.stack(gathered)[src.to(x.device), torch.arange(n, device=x.device)]


# --- shared numerics ------------------------------------------------------------------------

def squared_distances(x: Tensor, codes: Tensor) -> Tensor:
    """(n, D) x (K, D) -> (n, K) as ||x||^2 - 2 x.e + ||e||^2: one matmul, no (n, K, D) tensor."""
    return torch.addmm(x.pow(2).sum(1, keepdim=True) + codes.pow(2).sum(1), x, codes.t(), alpha=-2.0)


def nearest_code(x: Tensor, codes: Tensor) -> Tensor:
    """Eq. 1 of T2M-GPT: index of the closest code (squared Euclidean) for each row of x."""
    with torch.no_grad():
        return squared_distances(x, codes).argmin(1)


def code_stats(counts: Tensor) -> tuple[Tensor, Tensor]:
    """(fraction of codes used, perplexity = exp(entropy of the code histogram)), 0 log 0 = 0."""
    p = counts / counts.sum().clamp(min=1e-12)
    return (counts > 0).float().mean(), torch.exp(-torch.special.xlogy(p, p).sum())


class _StraightThrough(torch.autograd.Function):
    """Value of ``codes``, gradient of identity w.r.t. ``z``. Unlike ``z + (codes - z).detach()``
    the forward value is bit-exact, so ``decode(encode(z))`` equals ``forward(z).z_q``."""

    @staticmethod
    def forward(ctx, z, codes):
        return codes.detach().clone()

    @staticmethod
    def backward(ctx, grad):
        return grad, None


def _rows(z: Tensor, dim: int) -> Tensor:
    if z.dim() != 3 or z.shape[1] != dim:
        raise ValueError(f"expected z of shape (B, {dim}, T), got {tuple(z.shape)}")
    return z.transpose(1, 2).reshape(-1, dim).float()


def _fp32(z: Tensor):
    return torch.autocast(device_type=z.device.type, enabled=False)


# --- interface ------------------------------------------------------------------------------

class Quantizer(nn.Module):
    """Common base: see the module docstring. Build with :func:`build_quantizer`."""

    num_codebooks: int
    codebook_size: int
    dim: int

    def __init__(self, cfg: QuantizerConfig):
        super().__init__()
        self.cfg = cfg
        self.dim = cfg.dim
        # Seed and step count of the generator every rank shares. Buffers, so checkpoints
        # resume the same random stream and rank 0's seed reaches all ranks with the state.
        self.register_buffer("rng_seed", torch.randint(0, 2**62, (1,)))
        self.register_buffer("train_steps", torch.zeros(1, dtype=torch.long))
        self._synced = False

    def _next_generator(self) -> torch.Generator:
        seed = (int(self.rng_seed) * 0x9E3779B97F4A7C15 + int(self.train_steps)) % 2**63
        self.train_steps += 1
        return torch.Generator().manual_seed(seed)

    def _sync_once(self) -> None:
        # Ranks built with different seeds must start from one state; DDP does this for what
        # it wraps, but a quantizer must not depend on being wrapped.
        if self.training and not self._synced and _distributed():
            with torch.no_grad():
                for t in [*self.parameters(), *self.buffers()]:
                    dist.broadcast(t.data, src=0)
            self._synced = True

    def _check_m(self, num_codebooks: int | None) -> int:
        if num_codebooks is None:
            return self.num_codebooks
        if not 1 <= num_codebooks <= self.num_codebooks:
            raise ValueError(f"num_codebooks must be in 1..{self.num_codebooks}, got {num_codebooks}")
        return num_codebooks

    def _output(self, z: Tensor, zq_rows: Tensor, idx: Tensor, losses: dict[str, Tensor],
                counts: list[Tensor | None], dead: list[int], m: int) -> QuantizeOutput:
        B, _, T = z.shape
        z_q = zq_rows.reshape(B, T, -1).transpose(1, 2).contiguous().to(z.dtype)
        # One host transfer for all statistics: each .item() would be its own device sync.
        per = [torch.stack(code_stats(c)) if c is not None else zq_rows.new_zeros(2) for c in counts]
        values = torch.stack(per).tolist()
        stats = {"usage": [v[0] for v in values], "perplexity": [v[1] for v in values],
                 "dead": dead, "num_active_codebooks": m}
        return QuantizeOutput(z_q, idx.reshape(B, T, -1), losses, stats)

    # Interface: forward(z, num_codebooks=None) -> QuantizeOutput; encode(z, num_codebooks=None)
    # -> (B, T, N) int64; decode(indices, num_codebooks=None) -> (B, D, T); codebooks() -> (N, K, D).
    def codebooks(self) -> Tensor:
        raise NotImplementedError


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
    """

    def __init__(self, cfg: QuantizerConfig, kind: str | None = None):
        super().__init__(cfg)
        self.kind = kind or cfg.kind
        K, D = cfg.codebook_size, cfg.dim
        self.num_codebooks, self.codebook_size = 1, K
        self.learned = self.kind in ("vq", "reset")
        self.uses_ema = self.kind in ("ema", "ema_reset")
        self.resets = self.kind in ("reset", "ema_reset")
        init = torch.empty(K, D).uniform_(-1.0 / K, 1.0 / K)  # van den Oord's init, as T2M-GPT's plain VQ
        if self.learned:
            self.embed = nn.Parameter(init)
        else:
            self.register_buffer("embed", init)
            self.register_buffer("ema_count", torch.ones(K))
            self.register_buffer("ema_sum", init.clone())
        if self.kind == "reset":
            self.register_buffer("window_count", torch.zeros(K))
        # Integer, not bool: gloo cannot broadcast bool tensors.
        self.register_buffer("initted", torch.tensor([0 if cfg.kmeans_init else 1]))

    def _quantize(self, x: Tensor, update: bool):
        """Rows x (n, D) float32 -> (codes (n, D) detached, indices (n,), losses, histogram, #reset).

        With ``update`` the histogram is the all-rank one and the codebook is updated after the
        codes are read, so returned codes are those of the codebook the batch was assigned to.
        """
        g = self._next_generator() if update else None
        if update and not int(self.initted):
            self._kmeans_init(x, g)
        idx = nearest_code(x, self.embed)
        q = self.embed[idx]
        losses = {"commit": F.mse_loss(x, q.detach()),
                  "codebook": F.mse_loss(q, x.detach()) if self.learned else x.new_zeros(())}
        counts = torch.bincount(idx, minlength=self.codebook_size).float()
        dead = 0
        if update:
            with torch.no_grad():
                counts, dead = self._update(x, idx, counts, g)
        return q.detach(), idx, losses, counts, dead

    def _update(self, x: Tensor, idx: Tensor, counts: Tensor, g: torch.Generator) -> tuple[Tensor, int]:
        if self.uses_ema:
            # A one-hot matmul rather than index_add_: deterministic on GPU, so reruns match.
            sums = F.one_hot(idx, self.codebook_size).float().t() @ x
            packed = _all_reduce_sum(torch.cat([counts[:, None], sums], 1))  # one collective
            counts, sums = packed[:, 0], packed[:, 1:]
            d = self.cfg.decay
            self.ema_count.mul_(d).add_(counts, alpha=1 - d)
            self.ema_sum.mul_(d).add_(sums, alpha=1 - d)
            total = self.ema_count.sum()
            K, eps = self.codebook_size, self.cfg.eps
            smoothed = (self.ema_count + eps) / (total + K * eps) * total
            self.embed.copy_(self.ema_sum / smoothed[:, None])
        else:
            counts = _all_reduce_sum(counts)
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
    def _kmeans_init(self, x: Tensor, g: torch.Generator) -> None:
        """Lloyd's algorithm on the first batch; sums are all-reduced, so it clusters all ranks' rows."""
        K = self.codebook_size
        c = draw_rows(x, K, g)
        for _ in range(KMEANS_ITERS):
            idx = nearest_code(x, c)
            one_hot = F.one_hot(idx, K).float()
            packed = _all_reduce_sum(torch.cat([one_hot.sum(0)[:, None], one_hot.t() @ x], 1))
            n, s = packed[:, :1], packed[:, 1:]
            c = torch.where(n > 0, s / n.clamp(min=1), c)  # empty clusters keep their centre
        self.embed.data.copy_(c)
        if self.uses_ema:
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
        with _fp32(z):
            x = _rows(z, self.dim)
            q, idx, losses, counts, dead = self._quantize(x, self.training)
            zq = _StraightThrough.apply(x, q)
        return self._output(z, zq, idx[:, None], losses, [counts], [dead], 1)

    @torch.no_grad()
    def encode(self, z: Tensor, num_codebooks: int | None = None) -> Tensor:
        self._check_m(num_codebooks)
        with _fp32(z):
            return nearest_code(_rows(z, self.dim), self.embed).reshape(z.shape[0], z.shape[2], 1)

    @torch.no_grad()
    def decode(self, indices: Tensor, num_codebooks: int | None = None) -> Tensor:
        self._check_m(num_codebooks)
        return self.lookup(indices[..., 0]).transpose(1, 2).contiguous()

    def codebooks(self) -> Tensor:
        return self.embed.detach()[None]


def _validate(cfg: QuantizerConfig) -> None:
    problems = []
    if cfg.kind not in KINDS:
        problems.append(f"kind {cfg.kind!r} is not one of {KINDS}")
    if cfg.kind == "rvq" and cfg.rvq_base not in SINGLE_KINDS:
        problems.append(f"rvq_base {cfg.rvq_base!r} is not one of {SINGLE_KINDS}")
    if cfg.kind != "rvq" and cfg.num_codebooks != 1:
        problems.append(f"num_codebooks={cfg.num_codebooks} needs kind 'rvq' (kind is {cfg.kind!r})")
    if cfg.codebook_size < 1 or cfg.dim < 1 or cfg.num_codebooks < 1 or cfg.reset_window < 1:
        problems.append("codebook_size, dim, num_codebooks and reset_window must be >= 1")
    if not 0.0 <= cfg.decay < 1.0 or cfg.eps < 0 or not 0.0 <= cfg.quantizer_dropout <= 1.0:
        problems.append("need 0 <= decay < 1, eps >= 0 and 0 <= quantizer_dropout <= 1")
    if cfg.kind == "fsq" and (not cfg.fsq_levels or min(cfg.fsq_levels) < 2):
        problems.append(f"fsq_levels must be a non-empty list of integers >= 2, got {cfg.fsq_levels}")
    if problems:
        raise ValueError("bad QuantizerConfig: " + "; ".join(problems))


def build_quantizer(cfg: QuantizerConfig) -> Quantizer:
    _validate(cfg)
    if cfg.kind == "rvq":
        from motok.tokenizer.rvq import ResidualVQ  # rvq builds on this module's VectorQuantizer

        return ResidualVQ(cfg)
    if cfg.kind == "fsq":
        from motok.tokenizer.fsq import FSQuantizer

        return FSQuantizer(cfg)
    return VectorQuantizer(cfg)
