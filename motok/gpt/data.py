"""The GPT's training data (T2M-GPT Sec. 3.2): first-codebook codes of every clip with the
embeddings of its captions, corrupted inputs, padded batches and the random-crop sampler.

Held-out wordings: ``load_code_data`` drops the captions in held-out wordings (``holdout``,
:mod:`motok.text.phrasings`) and adds the augmented captions of :mod:`motok.gpt.augment`.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch

from motok.config import ConfigError
from motok.errors import MotokError
from motok.text.cache import TextEmbeddingCache
from motok.tokenizer.tokens import TokenFile

IGNORE = -100
HOLDOUTS = ("", "v1")


class GPTError(MotokError, ValueError):
    pass


@dataclass
class CodeData:
    codes: torch.Tensor  # (S,) first-codebook codes of every clip, concatenated
    starts: torch.Tensor  # (C,) per clip
    lengths: torch.Tensor  # (C,)
    pair_clip: torch.Tensor  # (P,) one (clip, caption) pair per row: the clip ...
    pair_text: torch.Tensor  # (P,) ... and the row of its caption in `text`
    text: torch.Tensor  # (U, text_dim) embeddings of the unique captions


def default_cache_path(tokens: str | Path) -> Path:
    tokens = Path(tokens)
    return tokens.with_name(tokens.stem + ".text-embeddings.h5")


def load_code_data(tokens: str | Path, split: str, encoder: str, cache: TextEmbeddingCache,
                   cfg=None) -> CodeData:
    """Codes of the first codebook of every clip in ``split`` with their caption embeddings; with
    ``cfg``, its held-out wordings removed and its augmented captions added (motok.gpt.augment)."""
    from motok.gpt import augment
    from motok.text.phrasings import is_heldout

    with TokenFile(tokens) as tf:
        clips = [i for i, s in enumerate(tf.splits) if s == split]
        if not clips:
            raise GPTError(f"{tokens}: no clip in split {split!r} (splits: {sorted(set(tf.splits))})")
        seqs = [torch.from_numpy(tf.indices(i)[:, 0].astype(np.int64)) for i in clips]
        caps = [[c[0] for c in tf.captions(i)] for i in clips]
    if cfg is not None and cfg.holdout not in HOLDOUTS:
        raise ConfigError(f"holdout {cfg.holdout!r}: choose from {list(HOLDOUTS)}")
    if cfg is not None and cfg.holdout:
        caps = [[t for t in cs if not is_heldout(t)] for cs in caps]
    extra: list[tuple[int, str]] = []  # augmented (clip, caption) pairs
    if cfg is not None:
        keep = (lambda t: not is_heldout(t)) if cfg.holdout else (lambda t: True)
        for group, t in augment.recombined_captions(caps, cfg.recombine, cfg.seed, keep):
            extra += [(k, t) for k in group]
        variants = augment.word_dropout_captions(sorted({t for cs in caps for t in cs}), cfg.word_dropout,
                                                 cfg.word_dropout_variants, cfg.seed)
        by_text: dict[str, list[int]] = {}
        for k, cs in enumerate(caps):
            for t in cs:
                by_text.setdefault(t, []).append(k)
        extra += [(k, v) for src, v in variants for k in by_text[src]]
    texts = sorted({t for cs in caps for t in cs} | {t for _, t in extra})
    row = {t: k for k, t in enumerate(texts)}
    pairs = [(k, row[t]) for k, cs in enumerate(caps) for t in cs] + [(k, row[t]) for k, t in extra]
    if not pairs:
        raise GPTError(f"{tokens}: the {split} clips have no captions")
    lengths = torch.tensor([len(s) for s in seqs])
    starts = torch.cat([torch.zeros(1, dtype=torch.long), lengths.cumsum(0)[:-1]])
    emb = torch.from_numpy(cache.embed(texts, encoder))
    return CodeData(torch.cat(seqs), starts, lengths, torch.tensor([p[0] for p in pairs]),
                    torch.tensor([p[1] for p in pairs]), emb)


def corrupt(codes: torch.Tensor, valid: torch.Tensor, tau: torch.Tensor, codebook_size: int,
            gen: torch.Generator | None = None) -> tuple[torch.Tensor, torch.Tensor]:
    """Replace each valid code with probability ``tau`` (per row, ``(B,)``) by a different random
    code; returns the corrupted codes and the boolean mask of replaced positions."""
    hit = (torch.rand(codes.shape, generator=gen) < tau[:, None]) & valid
    shift = torch.randint(1, codebook_size, codes.shape, generator=gen) if codebook_size > 1 else 0
    return torch.where(hit, (codes + shift) % codebook_size, codes), hit


def make_batch(seqs: list[torch.Tensor], ends: list[bool], end_id: int, pad_id: int):
    """Inputs ``(B, n)`` padded with Pad and targets ``(B, n + 1)``: codes, End (when the clip
    ends there), ignore past it. Position i of the model's output scores target i."""
    n = max(len(s) for s in seqs)
    inp = torch.full((len(seqs), n), pad_id, dtype=torch.long)
    tgt = torch.full((len(seqs), n + 1), IGNORE, dtype=torch.long)
    for b, (s, e) in enumerate(zip(seqs, ends)):
        inp[b, :len(s)] = s
        tgt[b, :len(s)] = s
        if e:
            tgt[b, len(s)] = end_id
    return inp, tgt


class SequenceSampler:
    """Random (clip, caption) pairs, cropped to ``max_codes``; own generator per rank."""

    def __init__(self, data: CodeData, batch: int, max_codes: int, seed: int, rank: int):
        self.data, self.batch, self.max_codes = data, batch, max_codes
        self.gen = torch.Generator().manual_seed(seed * 1_000_003 + 7919 * (rank + 1))

    def sample(self):
        d, g = self.data, self.gen
        pick = torch.randint(len(d.pair_clip), (self.batch,), generator=g)
        clips = d.pair_clip[pick]
        seqs, ends = [], []
        for c in clips.tolist():
            L, s0 = int(d.lengths[c]), int(d.starts[c])
            off = int(torch.randint(L - self.max_codes + 1, (1,), generator=g)) if L > self.max_codes else 0
            n = min(L, self.max_codes)
            seqs.append(d.codes[s0 + off:s0 + off + n])
            ends.append(off + n == L)
        return d.text[d.pair_text[pick]], seqs, ends
