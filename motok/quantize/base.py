"""What every quantizer shares: config, output type, base class, straight-through estimator,
the float32 region, the row layout and the collectives.

A quantizer maps latents ``z`` to discrete codes and back. Two input layouts are accepted:

- ``(B, D, T)``, a sequence per batch item (the motion tokenizer's encoder output):
  ``z_q`` is ``(B, D, T)``, indices are ``(B, T, N)``;
- ``(B, D)``, one latent per batch item (per-step latents of the physics stage's priors):
  ``z_q`` is ``(B, D)``, indices are ``(B, N)``.

``N`` is ``num_codebooks`` (1 for every kind but ``rvq``), kept as the last axis for every kind
so that callers index codebooks the same way whatever the kind. A ``(B, D)`` input is
quantized exactly as the ``(B, D, 1)`` input with the time axis removed: values, indices,
losses, statistics, state updates and gradients are bitwise the same.

Shared conventions:

- Distances and codebook statistics are computed in float32 with autocast off (:func:`fp32`),
  whatever the encoder's precision: argmin over bf16 distances flips assignments between nearly
  equal codes.
- ``z_q`` carries the code values exactly (not ``z + (q - z)`` rounded) and passes the incoming
  gradient to ``z`` unchanged (:class:`StraightThrough`, the straight-through estimator of
  VQ-VAE, van den Oord et al. 2017 Eq. 3 / T2M-GPT Eq. 3). The commitment weight
  (``cfg.beta``) is applied by the trainer, not here.
- Codebooks change only in training mode, inside ``forward``. ``encode``/``decode`` never change
  state, and eval-mode ``forward`` issues no collectives, so ranks may evaluate unequal numbers
  of batches.

Distributed training (``torch.distributed`` initialized): the first training ``forward``
copies rank 0's parameters and buffers to every rank; per-code counts and sums are all-reduced
(:func:`all_reduce_sum`) before each update, so dead-code decisions agree; replacement vectors
are gathered from all ranks (:func:`draw_rows`) and chosen by a generator whose seed and step
counter are buffers (identical on all ranks), so codebooks stay bit-identical without relying
on DDP's buffer broadcast.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import torch
import torch.distributed as dist
from torch import Tensor, nn

from motok.ranges import In


@dataclass
class QuantizerConfig:
    kind: str = "ema_reset"        # one of motok.quantize.registry.KINDS
    codebook_size: In[int, ">= 1"] = 512       # ignored by fsq, whose codebook has prod(fsq_levels) codes
    dim: In[int, ">= 1"] = 512                 # code dimension
    beta: In[float, ">= 0"] = 1.0              # commitment weight, for the trainer: losses["commit"] is unweighted
    decay: In[float, "[0, 1]"] = 0.99            # EMA decay
    eps: In[float, "> 0"] = 1e-5              # Laplace smoothing of EMA counts
    reset_threshold: In[float, ">= 0"] = 1.0   # a code is dead if its (EMA or windowed) usage count < threshold
    reset_window: In[int, ">= 1"] = 1          # training steps between dead-code checks (1 = every step, as T2M-GPT)
    num_codebooks: In[int, ">= 1"] = 1         # rvq: number of residual codebooks
    rvq_base: str = "ema_reset"    # rvq: how each residual codebook learns (one of vq.VQ_KINDS)
    # rvq: probability that a training batch uses only M ~ U{1..N} codebooks
    quantizer_dropout: In[float, "[0, 1]"] = 1.0
    # Codebook start (see motok.quantize.vq.INITS): "uniform" U(-1/K, 1/K) for every kind (the
    # shared default, which the physics priors rely on); "batch": encoder outputs of the first
    # training batch; "t2m_gpt": per kind as T2M-GPT's code (uniform for vq, batch for ema, reset,
    # ema_reset); "kmeans": Lloyd's algorithm on the first batch (same as kmeans_init=True).
    init: str = "uniform"
    kmeans_init: bool = False      # older spelling of init="kmeans" (the priors' configs use it)
    # fsq: the levels L_i of each channel, one entry a channel: prod(L_i) codes (Mentzer et al.'s [8, 5, 5, 5]: 1000)
    fsq_levels: In[list[int], ">= 2"] = field(default_factory=lambda: [8, 5, 5, 5])


@dataclass
class QuantizeOutput:
    z_q: Tensor                      # the input's shape, (B, D) or (B, D, T); gradient passes to z unchanged
    indices: Tensor                  # (B, N) or (B, T, N) int64; -1 for codebooks not used (rvq)
    losses: dict[str, Tensor]        # "commit", "codebook": zero-dim, unweighted
    stats: dict[str, float | list]   # "usage", "perplexity", "dead" (per codebook), "num_active_codebooks"


# --- collectives ----------------------------------------------------------------------------
# Collectives run only in training mode and only behind decisions every rank computes from
# reduced or shared-seed values, so all ranks issue the same collectives in the same order.

def is_distributed() -> bool:
    return dist.is_available() and dist.is_initialized()


def world_size() -> int:
    return dist.get_world_size() if is_distributed() else 1


def all_reduce_sum(t: Tensor) -> Tensor:
    """``t`` summed over all ranks, in place; ``t`` itself when not distributed."""
    if is_distributed():
        dist.all_reduce(t, op=dist.ReduceOp.SUM)
    return t


def broadcast_from_rank0(tensors) -> None:
    """Overwrite every rank's ``tensors`` (in place, in order) with rank 0's."""
    if is_distributed():
        with torch.no_grad():
            for t in tensors:
                dist.broadcast(t.data, src=0)


def draw_rows(x: Tensor, n: int, g: torch.Generator) -> Tensor:
    """``n`` rows drawn from the union of every rank's ``x`` (n_local, D), identical on all ranks.

    Each rank proposes ``n`` of its own rows; the shared generator ``g`` picks which rank's
    proposal fills each slot. Only draws whose size does not depend on the local batch come
    from ``g``, so ranks with unequal batch sizes keep their generators in step.
    """
    world = world_size()
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


# --- precision, straight-through, layout --------------------------------------------------

def fp32(t: Tensor):
    """Context manager turning autocast off on ``t``'s device: inside it, float32 rows stay
    float32 (see the module docstring for why assignments need that)."""
    return torch.autocast(device_type=t.device.type, enabled=False)


class StraightThrough(torch.autograd.Function):
    """Value of ``codes``, gradient of identity w.r.t. ``z`` (VQ-VAE's straight-through
    estimator, van den Oord et al. 2017 Eq. 3). Unlike ``z + (codes - z).detach()`` the forward
    value is bit-exact, so ``decode(encode(z))`` equals ``forward(z).z_q``."""

    @staticmethod
    def forward(ctx, z, codes):
        return codes.detach().clone()

    @staticmethod
    def backward(ctx, grad):
        return grad, None


def straight_through(z: Tensor, codes: Tensor) -> Tensor:
    """:class:`StraightThrough` applied: the values of ``codes`` with ``z``'s gradient path."""
    return StraightThrough.apply(z, codes)


def to_rows(z: Tensor, dim: int) -> Tensor:
    """``(B, dim)`` or ``(B, dim, T)`` -> float32 rows ``(B, dim)`` or ``(B * T, dim)``, batch-major."""
    if z.dim() == 2 and z.shape[1] == dim:
        return z.float()
    if z.dim() == 3 and z.shape[1] == dim:
        return z.transpose(1, 2).reshape(-1, dim).float()
    raise ValueError(f"expected z of shape (B, {dim}) or (B, {dim}, T), got {tuple(z.shape)}")


def batch_shape(z: Tensor) -> tuple[int, ...]:
    """The axes of a quantizer input that index its rows: ``(B,)`` or ``(B, T)``."""
    return (z.shape[0],) if z.dim() == 2 else (z.shape[0], z.shape[2])


def from_rows(rows: Tensor, like: Tensor) -> Tensor:
    """Inverse of :func:`to_rows`: rows ``(n, C)`` back to ``like``'s layout, ``(B, C)`` or ``(B, C, T)``."""
    if like.dim() == 2:
        return rows.reshape(like.shape[0], -1)
    return rows.reshape(like.shape[0], like.shape[2], -1).transpose(1, 2).contiguous()


def channels_first(x: Tensor) -> Tensor:
    """Decoded values ``(B, T, C)`` -> ``(B, C, T)``; per-item values ``(B, C)`` are already laid out."""
    return x.transpose(1, 2).contiguous() if x.dim() == 3 else x


def check_indices(indices: Tensor) -> None:
    if indices.dim() not in (2, 3):
        raise ValueError(f"expected indices of shape (B, N) or (B, T, N), got {tuple(indices.shape)}")


def code_stats(counts: Tensor) -> tuple[Tensor, Tensor]:
    """(fraction of codes used, perplexity = exp(entropy of the code histogram)), 0 log 0 = 0."""
    p = counts / counts.sum().clamp(min=1e-12)
    return (counts > 0).float().mean(), torch.exp(-torch.special.xlogy(p, p).sum())


# --- interface ------------------------------------------------------------------------------

class Quantizer(nn.Module):
    """Common base of every kind: see the module docstring. Build with
    :func:`motok.quantize.registry.build_quantizer`.

    Subclasses implement :meth:`forward`, :meth:`encode`, :meth:`decode` and :meth:`codebooks`
    and set ``num_codebooks`` and ``codebook_size``; the underscored methods are their shared
    machinery (shared generator, first-step sync, codebook-count check, output assembly).
    """

    num_codebooks: int
    codebook_size: int
    dim: int

    def __init__(self, cfg: QuantizerConfig):
        super().__init__()
        self.cfg = cfg
        self.dim = cfg.dim
        # Seed and step count of the generator every rank shares. Buffers, so checkpoints
        # resume the same random stream and rank 0's seed reaches all ranks with the state.
        # Drawn before any subclass draws its initial codes: fixed-seed runs depend on the order.
        self.register_buffer("rng_seed", torch.randint(0, 2**62, (1,)))
        self.register_buffer("train_steps", torch.zeros(1, dtype=torch.long))
        self._synced = False

    def forward(self, z: Tensor, num_codebooks: int | None = None) -> QuantizeOutput:
        """Quantize ``z`` (B, D) or (B, D, T); in training mode also update the codebooks.
        ``num_codebooks`` (rvq) uses only the first M codebooks."""
        raise NotImplementedError

    def encode(self, z: Tensor, num_codebooks: int | None = None) -> Tensor:
        """``z`` (B, D) or (B, D, T) -> int64 indices (B, N) or (B, T, N); never changes state."""
        raise NotImplementedError

    def decode(self, indices: Tensor, num_codebooks: int | None = None) -> Tensor:
        """Indices (B, N) or (B, T, N) -> code values (B, D) or (B, D, T); entries -1 are skipped."""
        raise NotImplementedError

    def codebooks(self) -> Tensor:
        """Every code's value, ``(N, K, D)``."""
        raise NotImplementedError

    def columns(self, m: int) -> int:
        """Index columns the first ``m`` codebooks fill (a prefix): one each here; the grouped
        quantizers (:mod:`motok.quantize.grouped`) fill several."""
        return m

    def column_groups(self, m: int) -> Tensor:
        """The group of each of the first :meth:`columns` ``(m)`` columns: one group here."""
        return torch.zeros(self.columns(m), dtype=torch.long)

    def _next_generator(self) -> torch.Generator:
        seed = (int(self.rng_seed) * 0x9E3779B97F4A7C15 + int(self.train_steps)) % 2**63
        self.train_steps += 1
        return torch.Generator().manual_seed(seed)

    def _sync_once(self) -> None:
        # Ranks built with different seeds must start from one state; DDP does this for what
        # it wraps, but a quantizer must not depend on being wrapped.
        if self.training and not self._synced and is_distributed():
            broadcast_from_rank0([*self.parameters(), *self.buffers()])
            self._synced = True

    def _check_m(self, num_codebooks: int | None) -> int:
        if num_codebooks is None:
            return self.num_codebooks
        if not 1 <= num_codebooks <= self.num_codebooks:
            raise ValueError(f"num_codebooks must be in 1..{self.num_codebooks}, got {num_codebooks}")
        return num_codebooks

    def _output(self, z: Tensor, zq_rows: Tensor, idx: Tensor, losses: dict[str, Tensor],
                counts: list[Tensor | None], dead: list[int], m: int) -> QuantizeOutput:
        """Rows back to ``z``'s layout (see :func:`from_rows`) plus the per-codebook statistics."""
        z_q = from_rows(zq_rows, z).to(z.dtype)
        # One host transfer for all statistics: each .item() would be its own device sync.
        per = [torch.stack(code_stats(c)) if c is not None else zq_rows.new_zeros(2) for c in counts]
        values = torch.stack(per).tolist()
        stats = {"usage": [v[0] for v in values], "perplexity": [v[1] for v in values],
                 "dead": dead, "num_active_codebooks": m}
        return QuantizeOutput(z_q, idx.reshape(*batch_shape(z), -1), losses, stats)
