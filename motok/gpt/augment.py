"""Caption augmentation for the text-to-motion GPT (to follow sentences never seen).

The GPT reads a frozen sentence embedding, so it can only be as robust to new wordings as the
variety of wordings (and embeddings) it was trained on. Three augmentations, all off by default:

- **Recombined captions** (``recombine``): new captions made from the captions' own phrases. Clips
  that share a caption text describe the same thing (Bandai captions are written from labels), so
  they form a group; two captions of a group are cut at a word they share and the head of one is
  joined to the tail of the other ("A tired person walks forward" + "Someone walks straight ahead
  wearily" -> "A tired person walks straight ahead wearily"). Up to ``recombine`` new captions per
  group, seeded, embedded once with the others before training (the encoder never runs in the loop).
- **Word dropout** (``word_dropout`` p, ``word_dropout_variants`` k): k variants of every caption,
  each word dropped with probability p (at least one word kept), embedded once likewise.
- **Embedding noise** (``text_noise`` s): Gaussian noise on the embedding at every step,
  ``e + s * |e| * z / sqrt(d)``, so the noise is s times the embedding's norm on average.

Caption dropout for classifier-free guidance (Ho & Salimans 2022; MoMask, Guo et al. 2024, Sec. 3.3)
lives in the model (a learned null embedding) and the training loop (``caption_dropout``).
"""

from __future__ import annotations

import re

import numpy as np
import torch

_WORDS = re.compile(r"\S+")


def _key(word: str) -> str:
    return word.lower().strip(".,;:!?")


def caption_groups(captions: list[list[str]]) -> list[list[int]]:
    """Clips (indices into ``captions``) joined when they share a caption text (union-find)."""
    parent = list(range(len(captions)))

    def find(i: int) -> int:
        while parent[i] != i:
            parent[i] = parent[parent[i]]
            i = parent[i]
        return i

    owner: dict[str, int] = {}
    for i, caps in enumerate(captions):
        for t in caps:
            j = owner.setdefault(t, i)
            parent[find(i)] = find(j)
    groups: dict[int, list[int]] = {}
    for i in range(len(captions)):
        groups.setdefault(find(i), []).append(i)
    return list(groups.values())


_GLUE = {"with", "like", "while", "that", "then", "this", "from", "into", "when"}


def crossover(a: str, b: str) -> list[str]:
    """Every caption made of a head of ``a`` up to a word both share and the tail of ``b`` from it.
    Cuts only at words of four letters or more that are not glue ("with", "while", ...), never at
    the first word, and a result shorter than the shorter source is dropped (it lost a phrase)."""
    wa, wb = _WORDS.findall(a), _WORDS.findall(b)
    out = []
    for i, x in enumerate(wa):
        k = _key(x)
        if i == 0 or len(k) < 4 or k in _GLUE:
            continue
        for j, y in enumerate(wb):
            if j > 0 and _key(y) == k and i + len(wb) - j >= min(len(wa), len(wb)):
                out.append(" ".join(wa[:i] + wb[j:]))
    return out


def recombined_captions(captions: list[list[str]], per_group: int, seed: int,
                        keep=lambda t: True) -> list[tuple[list[int], str]]:
    """Up to ``per_group`` new captions per group of clips, ``(clips of the group, caption)``; never
    an existing caption, only those ``keep`` accepts (the held-out wordings stay out)."""
    if per_group <= 0:
        return []
    rng = np.random.default_rng([seed, 18])
    existing = {t for caps in captions for t in caps}
    out = []
    for group in caption_groups(captions):
        texts = sorted({t for i in group for t in captions[i]})
        new = sorted({c for a in texts for b in texts if a != b for c in crossover(a, b)}
                     - existing)
        new = [c for c in new if keep(c)]
        if len(new) > per_group:
            new = [new[k] for k in sorted(rng.choice(len(new), per_group, replace=False))]
        out += [(group, c) for c in new]
    return out


def word_dropout_captions(texts: list[str], p: float, variants: int, seed: int) -> list[tuple[str, str]]:
    """``variants`` copies of each text with every word dropped with probability ``p`` (one word at
    least is kept); ``(source text, variant)``, variants equal to their source left out."""
    if p <= 0 or variants <= 0:
        return []
    rng = np.random.default_rng([seed, 19])
    out = []
    for t in texts:
        words = _WORDS.findall(t)
        seen = {t}
        for _ in range(variants):
            keep = rng.random(len(words)) >= p
            if not keep.any():
                keep[rng.integers(len(words))] = True
            v = " ".join(w for w, k in zip(words, keep) if k)
            if v not in seen:
                seen.add(v)
                out.append((t, v))
    return out


def noisy(text: torch.Tensor, scale: float, gen: torch.Generator | None = None) -> torch.Tensor:
    """``e + scale * |e| * z / sqrt(d)``, z ~ N(0, I): noise of ``scale`` times the norm on average."""
    if scale <= 0:
        return text
    z = torch.randn(text.shape, generator=gen)
    return text + scale * text.norm(dim=-1, keepdim=True) * z / text.shape[-1] ** 0.5
