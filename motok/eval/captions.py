"""What the captions of an evaluation split allow, before any model is involved
(``motok eval captions``, and the caption filter of ``motok eval t2m``).

- **Overlap** (:func:`caption_overlap`): the share of the split's captions that occur word for
  word among the training split's captions. Bandai-Namco's captions are written from labels
  (content x style), so a test caption often repeats a training caption exactly; retrieval and
  text-to-motion on such captions measure recall of training text, not generalisation.
  :func:`unseen_only` keeps only the captions that do not occur in training, so ``motok eval t2m
  --captions unseen`` reports the rows on those alone.
- **Label-reader ceiling** (:func:`label_ceiling`): the R-precision of a perfect reader of
  labels under the protocol's batches of 32 (Guo et al. 2022 / T2M-GPT): it ranks the clips of
  its caption's label first, in random order, so a hit at k has probability ``min(k / n, 1)``
  with ``n`` the clips of that label in the batch. Several clips sharing a label cap what any
  evaluator can reach.
"""

from __future__ import annotations

import re
from pathlib import Path

import numpy as np

from motok.artifacts import read_strings
from motok.data.dataset import MotionFile
from motok.eval.evaluator import EvaluatorError
from motok.eval.sets import MotionSet

_SPACE = re.compile(r"\s+")


def normalise(text: str) -> str:
    """Lower case, single spaces, no trailing full stop: differences a reader does not see."""
    return _SPACE.sub(" ", text.strip().lower()).rstrip(".").strip()


def split_captions(mf: MotionFile, split: str | None, with_labels: bool = False):
    """Each clip's captions for the clips of ``split`` that have any (all clips for ``None``),
    reading only the caption columns (no features); with ``with_labels`` also their labels as
    :func:`motok.eval.evaluator.load_split` gives them ("" for none)."""
    which = mf.split_indices(split) if split else list(range(len(mf)))
    g = mf.h5["captions"]
    by_clip: dict[int, list[str]] = {}
    for c, t in zip(g["clip"][()], read_strings(g["text"])):
        by_clip.setdefault(int(c), []).append(t)
    keep = [i for i in which if by_clip.get(i)]
    caps = [by_clip[i] for i in keep]
    if not with_labels:
        return caps
    labels = read_strings(mf.h5["clips/labels"])
    return caps, ["" if labels[i] in ("{}", "") else labels[i] for i in keep]


def training_captions(data: str | Path, train_split: str = "train") -> set[str]:
    with MotionFile(data, "motion-dataset") as mf:
        if not mf.split_indices(train_split):
            raise EvaluatorError(f"{data}: no clip in split {train_split!r} (splits: {sorted(set(mf.splits))})")
        return {t for caps in split_captions(mf, train_split) for t in caps}


def caption_overlap(data: str | Path, split: str = "test", train_split: str = "train") -> dict:
    """How many of ``split``'s captions occur word for word in ``train_split`` (exact strings;
    ``normalised_*`` also ignores case, spacing and a final full stop)."""
    seen = training_captions(data, train_split)
    with MotionFile(data, "motion-dataset") as mf:
        caps = split_captions(mf, split)
    if not caps:
        raise EvaluatorError(f"{data}: no captioned clip in split {split!r}")
    flat = [t for c in caps for t in c]
    distinct = set(flat)
    seen_norm = {normalise(t) for t in seen}
    n = len(flat)
    in_train = sum(t in seen for t in flat)
    return {
        "data": str(data), "split": split, "train_split": train_split,
        "clips": len(caps), "captions": n, "distinct_captions": len(distinct),
        "captions_in_train": in_train, "share_in_train": in_train / n,
        "distinct_in_train": sum(t in seen for t in distinct),
        "share_distinct_in_train": sum(t in seen for t in distinct) / len(distinct),
        "normalised_share_in_train": sum(normalise(t) in seen_norm for t in flat) / n,
        "clips_with_unseen_caption": sum(any(t not in seen for t in c) for c in caps),
        "unseen_captions": n - in_train,
    }


def unseen_only(ms: MotionSet, seen: set[str]) -> MotionSet:
    """``ms`` restricted to the captions not in ``seen``: clips without one are dropped, the
    others keep only their unseen captions; MModality groups of a seen caption are dropped."""
    keep = [i for i, caps in enumerate(ms.captions) if any(t not in seen for t in caps)]
    groups = [(g, t) for g, t in zip(ms.mm_groups, ms.mm_texts or [None] * len(ms.mm_groups))
              if t is None or t not in seen]
    return ms.subset(keep, captions=[[t for t in ms.captions[i] if t not in seen] for i in keep],
                     mm_groups=[g for g, _ in groups], mm_texts=[t for _, t in groups] if ms.mm_texts else [],
                     extra={**ms.extra, "captions": "unseen"})


def label_ceiling(labels: list[str], batch: int = 32, top_k: int = 3, shuffles: int = 200,
                  seed: int = 0) -> dict | None:
    """R-precision top-1..k of a perfect label reader in shuffled batches of ``batch`` (the
    remainder dropped, as the protocol), averaged over ``shuffles``; ``None`` when a clip has no
    label (there is nothing to read)."""
    if not labels or any(lab == "" for lab in labels):
        return None
    ids = {v: k for k, v in enumerate(dict.fromkeys(labels))}
    lab = np.array([ids[x] for x in labels])
    n, size = len(lab), min(batch, len(lab))
    kept = n // size * size
    rng = np.random.default_rng(seed)
    k = np.arange(1, top_k + 1)
    total = np.zeros(top_k)
    for _ in range(shuffles):
        b = lab[rng.permutation(n)[:kept]].reshape(-1, size)
        same = (b[:, :, None] == b[:, None, :]).sum(2)  # clips of each caption's label in its batch
        total += np.minimum(k / same[..., None], 1.0).mean((0, 1))
    r = total / shuffles
    return {"batch": size, "shuffles": shuffles, **{f"R@{j}": float(r[j - 1]) for j in k}}


def caption_report(data: str | Path, split: str = "test", train_split: str = "train", batch: int = 32) -> dict:
    """``motok eval captions``: :func:`caption_overlap` and :func:`label_ceiling` of ``split``."""
    out = caption_overlap(data, split, train_split)
    with MotionFile(data, "motion-dataset") as mf:
        _, labels = split_captions(mf, split, with_labels=True)
    out["label_ceiling"] = label_ceiling(labels, batch)
    return out
