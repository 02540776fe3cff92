"""Conditioning on the nearest training caption (``snap``): a sentence the GPT never
trained on is replaced, before sampling, by the embedding of the training caption nearest to it.

The GPT maps training-caption embeddings to the right motion (label accuracy 0.91 on test
captions in training wordings) but extrapolates poorly to embeddings it has not seen: a new
wording lands between training captions, and the small direction that separates left from right
(cosine 0.97-0.99 between "turns left" and "turns right", docs/gpt.md) is lost among the larger
changes of wording. Snapping keeps the GPT on the embeddings it knows: with ``snap: 1`` a new
sentence is sampled as its nearest training caption (cosine of unit-norm embeddings, the
retrieval baseline's choice); with ``snap: k > 1`` as the mean of its k nearest, weighted by
``softmax(cos / 0.05)``, renormalised. A sentence that is a training caption is left unchanged, so
the test-split metrics of training captions do not move. Candidates are the captions the run trained
on (its split, without the held-out wordings of its ``holdout``, without augmented captions).

A retrieval step in the embedding space, the conditioning-side twin of the retrieval baseline of
``motok eval labels --retrieval`` (no paper: a kNN projection onto the training distribution).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

TEMPERATURE = 0.05


def training_captions(tokens: str | Path, split: str, holdout: str) -> list[str]:
    from motok.text.phrasings import is_heldout
    from motok.tokenizer.tokens import TokenFile

    with TokenFile(tokens) as tf:
        texts = {c[0] for i, s in enumerate(tf.splits) if s == split for c in tf.captions(i)}
    return sorted(t for t in texts if not (holdout and is_heldout(t)))


class SnappingCache:
    """Wraps a :class:`motok.text.cache.TextEmbeddingCache`: ``embed`` returns snapped embeddings."""

    def __init__(self, cache, captions: list[str], encoder: str, k: int):
        self.cache, self.k, self.encoder = cache, int(k), encoder
        self.captions = list(captions)
        self.known = set(self.captions)
        self.ref = cache.embed(self.captions, encoder, write=False).astype(np.float64)
        self.ref_unit = self.ref / np.maximum(np.linalg.norm(self.ref, axis=1, keepdims=True), 1e-12)
        self.snapped: dict[str, list[str]] = {}  # text -> the training captions it was replaced by

    def __getattr__(self, name):  # hits, misses, truncated, path, ... of the wrapped cache
        return getattr(self.cache, name)

    def embed(self, texts: list[str], encoder: str = "minilm", write: bool = True) -> np.ndarray:
        e = self.cache.embed(texts, encoder, write=write)
        if encoder != self.encoder or not len(texts):
            return e
        out = e.copy()
        for i, t in enumerate(texts):
            if t in self.known:
                continue
            q = e[i].astype(np.float64)
            cos = self.ref_unit @ (q / max(np.linalg.norm(q), 1e-12))
            top = np.argsort(-cos)[:self.k]
            w = np.exp((cos[top] - cos[top].max()) / TEMPERATURE)
            v = (w[:, None] * self.ref[top]).sum(0) / w.sum()
            if self.k > 1:
                v *= np.linalg.norm(self.ref[top], axis=1).mean() / max(np.linalg.norm(v), 1e-12)
            out[i] = v.astype(np.float32)
            self.snapped[t] = [self.captions[j] for j in top]
        return out


def snapping(cache, run: Path, meta: dict, k: int):
    """``cache`` wrapped to snap new sentences onto the run's training captions (``k`` nearest)."""
    from motok.checkpoint import bundle_ref

    if k <= 0:
        return cache
    cfg = meta["config"]
    tokens = bundle_ref(run, meta, "tokens", hint="; snapping needs the run's tokens artifact (its captions)")
    caps = training_captions(tokens, cfg.get("split", "train"), cfg.get("holdout", ""))
    return SnappingCache(cache, caps, meta["extra"]["text_encoder"], k)
