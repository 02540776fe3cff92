"""The T2M-GPT text-to-motion transformer (Zhang et al. 2023, Sec. 3.2, Eq. 4-5).

A decoder-only causal transformer in the GPT-2 / nanoGPT layout (pre-LayerNorm blocks,
GELU MLP, learned absolute positions, weight init N(0, 0.02)). The sequence is

    position 0:        W_c e        the text embedding e projected to the model width
    positions 1..L:    code tokens  S_1 .. S_L (codebook indices of the motion tokenizer)

and the output at position i is the distribution of token i+1 (Eq. 4: p(S_i | c, S_<i)). The
vocabulary is ``K`` codes, ``End = K`` and ``Pad = K + 1``. The head predicts only the ``K + 1``
classes codes + End: Pad fills inputs after End and is never a target (its loss is ignored), so
the model never learns to emit it.

Residual-VQ tokenizers: the model predicts the first codebook only (one token per step); the
motion is decoded from that codebook alone (``M = 1``), which quantizer dropout trained the
tokenizer to do. docs/gpt.md discusses it.

Token-level conditioning (``text_tokens: P``): instead of one pooled sentence vector,
the encoder's per-token outputs (padded or cut to P, a ``*_tokens`` text encoder) take positions
0..P-1, each projected by ``W_c``, and the causal self-attention reads them as a prefix (the
prefix-LM form of conditioning; cross-attention is the other). The output at position P - 1
scores the first code, so logits and sampling are unchanged for the caller.

Classifier-free guidance (Ho & Salimans 2022, as MoMask, Guo et al. 2024, uses it for text to
motion tokens): a model trained with caption dropout has a learned null text; sampling mixes the
logits ``l_u + g (l_c - l_u)`` of the caption and of the null text (:mod:`motok.gpt.sample`).

Sampling keeps a key/value cache (:class:`KVCache`) so each new token costs one position's
worth of compute instead of re-running the whole prefix.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from pathlib import Path

import torch
import torch.nn as nn
import torch.nn.functional as F

from motok.checkpoint import load_model, register_kind
from motok.config import ConfigError, from_dict
from motok.optim import OptimConfig
from motok.ranges import In


@dataclass
class GPTConfig:
    """Sizes; the default is a small CPU model. ``recipes/gpt/paper.yaml`` has 18 x 1024 x 16."""
    num_layers: In[int, ">= 1"] = 4  # transformer blocks (paper: 18)
    dim: In[int, ">= 1"] = 192  # width of the embeddings and the residual stream (paper: 1024)
    heads: In[int, ">= 1"] = 4  # attention heads; must divide dim (paper: 16)
    block_size: In[int, ">= 2"] = 51  # positions: the text + up to 50 codes (10 s at 20 fps, rate 4), as the paper
    ff_mult: In[int, ">= 1"] = 4  # the MLP's hidden width, in multiples of dim (paper: 4)
    dropout: In[float, "[0, 1)"] = 0.1  # on the embeddings, the attention weights and each residual branch (paper: 0.1)
    # Token-level conditioning: 0 = one pooled sentence vector at position 0 (the paper);
    # P > 0 = the encoder's P per-token outputs as a prefix of P positions (a ``*_tokens`` encoder).
    text_tokens: In[int, ">= 0"] = 0


class KVCache:
    """Preallocated keys/values per layer, ``(B, H, block_size, head_dim)``; ``length`` positions filled."""

    def __init__(self, cfg: GPTConfig, batch: int, device=None, dtype=torch.float32):
        hd = cfg.dim // cfg.heads
        shape = (batch, cfg.heads, cfg.block_size + max(cfg.text_tokens, 1) - 1, hd)
        self.k = [torch.zeros(shape, device=device, dtype=dtype) for _ in range(cfg.num_layers)]
        self.v = [torch.zeros(shape, device=device, dtype=dtype) for _ in range(cfg.num_layers)]
        self.length = 0

    def append(self, layer: int, k: torch.Tensor, v: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        a, b = self.length, self.length + k.shape[2]
        self.k[layer][:, :, a:b] = k
        self.v[layer][:, :, a:b] = v
        return self.k[layer][:, :, :b], self.v[layer][:, :, :b]


class CausalSelfAttention(nn.Module):
    def __init__(self, cfg: GPTConfig):
        super().__init__()
        if cfg.dim % cfg.heads:
            raise ConfigError(f"model.dim {cfg.dim} is not divisible by model.heads {cfg.heads}")
        self.heads, self.dropout = cfg.heads, cfg.dropout
        self.qkv = nn.Linear(cfg.dim, 3 * cfg.dim)
        self.proj = nn.Linear(cfg.dim, cfg.dim)
        self.resid_drop = nn.Dropout(cfg.dropout)

    def forward(self, x: torch.Tensor, cache: KVCache | None = None, layer: int = 0) -> torch.Tensor:
        B, T, C = x.shape
        q, k, v = self.qkv(x).view(B, T, 3, self.heads, C // self.heads).permute(2, 0, 3, 1, 4)
        past = cache.length if cache is not None else 0
        if cache is not None:
            k, v = cache.append(layer, k, v)
        p = self.dropout if self.training else 0.0
        if past == 0:
            y = F.scaled_dot_product_attention(q, k, v, dropout_p=p, is_causal=T > 1)
        elif T == 1:  # one new query sees every cached position: no mask needed
            y = F.scaled_dot_product_attention(q, k, v, dropout_p=p)
        else:
            # T new queries after `past` cached ones: query i sees keys 0 .. past + i
            mask = torch.ones(T, past + T, dtype=torch.bool, device=x.device).tril(past)
            y = F.scaled_dot_product_attention(q, k, v, attn_mask=mask, dropout_p=p)
        return self.resid_drop(self.proj(y.transpose(1, 2).reshape(B, T, C)))


class Block(nn.Module):
    def __init__(self, cfg: GPTConfig):
        super().__init__()
        self.ln1 = nn.LayerNorm(cfg.dim)
        self.attn = CausalSelfAttention(cfg)
        self.ln2 = nn.LayerNorm(cfg.dim)
        self.mlp = nn.Sequential(nn.Linear(cfg.dim, cfg.ff_mult * cfg.dim), nn.GELU(),
                                 nn.Linear(cfg.ff_mult * cfg.dim, cfg.dim), nn.Dropout(cfg.dropout))

    def forward(self, x, cache=None, layer=0):
        x = x + self.attn(self.ln1(x), cache, layer)
        return x + self.mlp(self.ln2(x))


class MotionGPT(nn.Module):
    """``forward(text, idx) -> logits (B, 1 + L, K + 1)``: position i scores token i + 1 (Eq. 4)."""

    def __init__(self, cfg: GPTConfig, codebook_size: int, text_dim: int, null_text: bool = False):
        super().__init__()
        if cfg.block_size < 2:
            raise ConfigError("model.block_size must be >= 2 (the text and one code)")
        self.cfg, self.codebook_size, self.text_dim = cfg, codebook_size, text_dim
        self.end_id, self.pad_id = codebook_size, codebook_size + 1
        self.tok_emb = nn.Embedding(codebook_size + 2, cfg.dim)
        self.prefix = max(cfg.text_tokens, 1)  # positions the text takes
        if text_dim % self.prefix:
            raise ConfigError(f"model.text_tokens {cfg.text_tokens} does not divide the text features' size {text_dim}")
        self.text_proj = nn.Linear(text_dim // self.prefix, cfg.dim)
        # The learned "no caption" input of classifier-free guidance (Ho & Salimans 2022), trained by
        # caption dropout; only in models trained with it, so older checkpoints load unchanged.
        self.null_text = nn.Parameter(torch.zeros(cfg.dim)) if null_text else None
        self.default_guidance = 1.0  # the sampling default recorded at training (TrainConfig.guidance)
        self.pos_emb = nn.Embedding(cfg.block_size + self.prefix - 1, cfg.dim)
        self.drop = nn.Dropout(cfg.dropout)
        self.blocks = nn.ModuleList([Block(cfg) for _ in range(cfg.num_layers)])
        self.ln_f = nn.LayerNorm(cfg.dim)
        self.head = nn.Linear(cfg.dim, codebook_size + 1, bias=False)
        self.apply(self._init)
        # GPT-2's scaling of residual output projections: keeps the residual stream's variance
        # from growing with depth.
        for name, p in self.named_parameters():
            if name.endswith("attn.proj.weight") or name.endswith("mlp.2.weight"):
                nn.init.normal_(p, 0.0, 0.02 / math.sqrt(2 * cfg.num_layers))

    @staticmethod
    def _init(m: nn.Module):
        if isinstance(m, nn.Linear):
            nn.init.normal_(m.weight, 0.0, 0.02)
            if m.bias is not None:
                nn.init.zeros_(m.bias)
        elif isinstance(m, nn.Embedding):
            nn.init.normal_(m.weight, 0.0, 0.02)

    @property
    def max_codes(self) -> int:
        """Longest code sequence the positions allow (the End token takes the step after it)."""
        return self.cfg.block_size - 1

    def new_cache(self, batch: int) -> KVCache:
        p = next(self.parameters())
        return KVCache(self.cfg, batch, p.device, p.dtype)

    def forward(self, text: torch.Tensor | None, idx: torch.Tensor | None = None,
                cache: KVCache | None = None, drop_text: torch.Tensor | None = None) -> torch.Tensor:
        """``text`` (B, text_dim) is position 0 and must come first (with or without a cache);
        ``idx`` (B, L) are tokens at the following positions. With a cache, only the new
        positions are computed and the logits returned are theirs. ``drop_text`` (B,) bool puts
        the learned null text at position 0 of those rows instead (caption dropout; CFG)."""
        start = cache.length if cache is not None else 0
        parts = []
        if text is not None:
            if start != 0:
                raise ValueError("the text embedding is position 0: pass it on the first call only")
            t = self.text_proj(text.reshape(text.shape[0], self.prefix, -1))
            if drop_text is not None:
                if self.null_text is None:
                    raise ValueError("this model has no null text: it was trained without caption_dropout")
                t = torch.where(drop_text[:, None, None], self.null_text.to(t.dtype).expand_as(t), t)
            parts.append(t)
        elif start == 0:
            raise ValueError("the first call needs the text embedding")
        if idx is not None and idx.shape[1]:
            parts.append(self.tok_emb(idx))
        x = torch.cat(parts, dim=1) if len(parts) > 1 else parts[0]
        T = x.shape[1]
        if start + T > self.cfg.block_size + self.prefix - 1:
            raise ValueError(f"sequence of {start + T - self.prefix + 1} positions exceeds block_size "
                             f"{self.cfg.block_size}")
        pos = torch.arange(start, start + T, device=x.device)
        x = self.drop(x + self.pos_emb(pos))
        for i, blk in enumerate(self.blocks):
            x = blk(x, cache, i)
        if cache is not None:
            cache.length += T
        if text is not None and self.prefix > 1:
            x = x[:, self.prefix - 1:]  # the last text position scores the first code, as position 0 does
        return self.head(self.ln_f(x))


def count_parameters(model: nn.Module) -> int:
    return sum(p.numel() for p in model.parameters())


KIND = "gpt"
register_kind(KIND, (1,))


@dataclass
class TrainConfig:
    model: GPTConfig = field(default_factory=GPTConfig)  # the transformer's sizes
    # The paper's GPT optimizer: AdamW (0.5, 0.99), lr 1e-4, no warm-up (T2M-GPT Sec. 4.1).
    optim: OptimConfig = field(default_factory=lambda: OptimConfig(lr=1e-4, betas=[0.5, 0.99], weight_decay=1e-6,
                                                                   warmup=0))
    text_encoder: str = "minilm"  # minilm | clip | bow
    text_cache: str = ""  # text-embeddings artifact; "" = next to the tokens artifact
    tau: In[float, "[0, 1]"] = 0.5  # fraction of input codes replaced by random codes
    tau_uniform: bool = False  # draw tau ~ U[0, 1] per sequence instead
    # holdout "v1": captions in the held-out wordings of motok.text.phrasings never train.
    holdout: str = ""
    # Caption augmentation (motok.gpt.augment), all off by default:
    recombine: In[int, ">= 0"] = 0  # new captions per group of clips, recombined from the captions' own phrases
    # probability of dropping a word, in word_dropout_variants copies per caption
    word_dropout: In[float, "[0, 1)"] = 0.0
    word_dropout_variants: In[int, ">= 0"] = 0  # k: word-dropped copies of every caption (0: word dropout off)
    text_noise: In[float, ">= 0"] = 0.0  # Gaussian noise on the embedding, as a fraction of its norm
    caption_dropout: In[float, "[0, 1)"] = 0.0  # share of steps' rows conditioned on the learned null text (for CFG)
    guidance: In[float, ">= 0"] = 1.0  # classifier-free guidance scale sampling uses by default (needs caption_dropout)
    # sampling default: condition a new sentence on its k nearest training captions (motok.gpt.snap)
    snap: In[int, ">= 0"] = 0
    iterations: In[int, ">= 1"] = 2000  # optimiser steps, one batch each (the paper's: 300K)
    batch_size: In[int, ">= 1"] = 64  # global: split evenly over the ranks
    split: str = "train"  # the tokens artifact's split the sequences come from
    val_split: str = "val"  # "" = no validation loss
    seed: In[int, ">= 0"] = 123  # weights, batches, code corruption and caption augmentation
    log_every: In[int, ">= 1"] = 50  # iterations per metrics.jsonl row (their mean); the last is always logged
    eval_every: In[int, ">= 1"] = 250  # iterations between val_* losses, taken on logged iterations only
    save_every: In[int, ">= 1"] = 500  # iterations between checkpoints; the last is always saved
    device: str = "auto"  # auto | cpu | cuda
    threads: In[int, ">= 0"] = 0  # torch intra-op threads; 0 = torch's default

    def resume_may_change(self) -> set[str]:
        """What ``--resume`` may change (motok.resume): the run's length (the schedule's milestones
        are absolute iterations) and how often it logs, evaluates and saves, none of which changes a step."""
        return {"iterations", "log_every", "eval_every", "save_every"}


def build_model(cfg: TrainConfig | dict, codebook_size: int, text_dim: int) -> MotionGPT:
    cfg = cfg if isinstance(cfg, TrainConfig) else from_dict(TrainConfig, cfg)
    model = MotionGPT(cfg.model, codebook_size, text_dim, null_text=cfg.caption_dropout > 0)
    model.default_guidance = float(cfg.guidance)
    return model


def load_gpt(run: str | Path, device: str | torch.device = "cpu") -> tuple[MotionGPT, dict]:
    """A trained GPT in eval mode and its bundle metadata."""
    return load_model(run, KIND, lambda meta: build_model(meta["config"], int(meta["extra"]["codebook_size"]),
                                                          int(meta["extra"]["text_dim"])), device)
