"""The text-to-motion protocol of Guo et al. (CVPR 2022) as T2M-GPT (Zhang et al. 2023, Table 1)
reports it: how motion sets (:mod:`motok.eval.sets`) are measured against the real motion.

Each row is measured ``repeats`` times (20) against the real motion of the split; a repeat
draws, as the reference evaluation loader does, one caption per clip and a crop of each clip to
a multiple of 4 frames (one unit shorter with probability 1/3, at a random offset), then
R-precision/MM-Dist in shuffled batches of 32, FID against that repeat's real crops, Diversity
over 300 pairs and, where several samples per caption exist, MModality. Mean and 95% CI per
metric; the physical metrics (:mod:`motok.eval.physical`) are deterministic and computed once
per row.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from motok import progress as _progress
from motok.eval import metrics as M
from motok.eval.evaluator import UNIT, EvaluatorError, LoadedEvaluator
from motok.eval.physical import PhysicalSums, clip_sums
from motok.eval.sets import MotionSet
from motok.features.humanml3d import recover_from_ric
from motok.ranges import In


@dataclass
class T2MConfig:
    split: str = "test"  # the data set's split whose real motion is the reference (--split)
    repeats: In[int, ">= 1"] = 20  # draws of captions and crops per row; mean and 95% CI over them (reference: 20)
    batch: In[int, ">= 1"] = 32  # R-precision batch: 1 true caption and 31 others
    top_k: In[int, ">= 1"] = 3  # R-precision reported at 1..top_k (Table 1: R@1, R@2, R@3)
    diversity_times: In[int, ">= 1"] = 300  # random motion pairs Diversity averages over (reference: 300)
    mm_pairs: In[int, ">= 1"] = 10  # MModality pairs per caption (reference: 10 of 30 samples)
    # MModality's captions drawn with replacement in each repeat: samples are generated once, not
    # per repeat as the reference does, so the CI must carry the spread between captions.
    mm_resample: bool = True
    unit_crop: bool = True  # the reference loader's crop to a multiple of 4 frames
    seed: In[int, ">= 0"] = 0  # the repeats' draws, and the captions and samples of a --gpt row
    physical: bool = True  # add the physical metrics (skating, penetration, floating, jitter) per row
    # "unseen": only the split's captions that do not occur word for word in train_split
    # (motok.eval.captions); clips without one are left out of every row and of the reference.
    captions: str = "all"
    train_split: str = "train"  # the split "unseen" compares with, and the caption overlap reported
    # Rows holding clips of the same names (a tracked file beside what it tracked) scored on the
    # names all of them hold (motok.eval.sets.common_clips); the reference statistics stay whole.
    common_clips: bool = False
    # --motions rows keep only the clips `control track` played to their end (labels; others keep all)
    tracked_to_end: bool = False
    # Generation with --gpt: sets of one sample per clip (the protocol regenerates every repeat:
    # gen_sets = repeats; fewer sets are reused in turn) and the MModality samples.
    gen_sets: In[int, ">= 1"] = 20
    gt_length: bool = False  # target the ground-truth length instead of stopping at End
    mm_captions: In[int, ">= 1"] = 100  # MModality: captions drawn (at most the split's; reference: 100)
    mm_samples: In[int, ">= 1"] = 30  # MModality: samples per caption (reference: 30; 1 leaves MModality out)
    temperature: In[float, "> 0"] = 1.0  # the GPT's softmax temperature when sampling
    top_k_sampling: In[int | None, ">= 1"] = None  # sample among the k likeliest codes only (None: all)
    top_p: In[float | None, "(0, 1]"] = None  # nucleus sampling: the likeliest codes up to this mass (None: off)
    gen_batch: In[int, ">= 1"] = 64  # GPT samples per batch (speed and memory: each sample has its own seed)
    threads: In[int, ">= 0"] = 1  # torch threads (one is fastest on a shared 2-core machine)


def unit_crop(n: int, rng: np.random.Generator) -> tuple[int, int]:
    """The reference evaluation crop: length a multiple of 4, one unit less 1 time in 3, random start."""
    if n < 2 * UNIT:
        return 0, n
    m = (n // UNIT - int(rng.random() < 1 / 3)) * UNIT
    return int(rng.integers(0, n - m + 1)), m


class Embedder:
    """Motion embeddings of crops, cached: a crop recurs across repeats (few offsets per clip)."""

    def __init__(self, ev: LoadedEvaluator):
        self.ev, self.cache = ev, {}

    def __call__(self, key: str, clips: list[np.ndarray], idx: list[int], rng, crop: bool) -> np.ndarray:
        spans = [unit_crop(len(clips[i]), rng) if crop else (0, len(clips[i])) for i in idx]
        keys = [(key, i, s, m) for i, (s, m) in zip(idx, spans)]
        todo = [k for k in dict.fromkeys(keys) if k not in self.cache]
        if todo:
            vecs = self.ev.motions([clips[i][s:s + m] for _, i, s, m in todo])
            self.cache.update(zip(todo, vecs))
        return np.stack([self.cache[k] for k in keys])


def physical_of(ms: MotionSet, fps: float, feet) -> dict:
    tot = PhysicalSums()
    for k, c in enumerate(ms.clips):
        j = ms.joints[k] if ms.joints is not None else recover_from_ric(np.asarray(c, np.float64), ms.extra["num_joints"])
        tot.add(clip_sums(j, fps, feet))
    return tot.result()


def evaluate_rows(ev: LoadedEvaluator, ref: MotionSet, rows: list[MotionSet], cfg: T2MConfig) -> list[dict]:
    """Every row against the reference (real motion of the split), ``cfg.repeats`` times."""
    emb = Embedder(ev)
    per_row = [{} for _ in rows]
    with _progress.make_progress("repeats") as bar:
        task = bar.add_task("t2m", total=cfg.repeats * len(rows))
        for r in range(cfg.repeats):
            rng = np.random.default_rng([cfg.seed, r])
            ref_emb = emb("real", ref.clips, list(range(len(ref.clips))), rng, cfg.unit_crop)
            for k, row in enumerate(rows):
                rrng = np.random.default_rng([cfg.seed, r, k + 1])
                idx = row.for_repeat(r)
                if len(idx) < 2:
                    raise EvaluatorError(f"row {row.name}: {len(idx)} motion(s) in repeat {r}; need 2+")
                key = "real" if row is ref else f"row{k}"  # the real row shares the reference's crops
                m = emb(key, row.clips, idx, rrng, cfg.unit_crop)
                caps = [row.captions[i][rrng.integers(len(row.captions[i]))] for i in idx]
                t = ev.texts(caps)
                rp, mmd = M.r_precision(t, m, rrng, cfg.batch, cfg.top_k)
                vals = {f"R@{j + 1}": float(rp[j]) for j in range(cfg.top_k)}
                vals.update({"FID": M.fid(ref_emb, m), "MM-Dist": mmd,
                             "Diversity": M.diversity(m, rrng, cfg.diversity_times)})
                if row.mm_groups:
                    g = emb(f"row{k}/mm", row.mm_clips, list(range(len(row.mm_clips))), rrng, cfg.unit_crop)
                    vals["MModality"] = M.multimodality([g[ix] for ix in row.mm_groups], rrng, cfg.mm_pairs,
                                                        resample_captions=cfg.mm_resample)
                for name, v in vals.items():
                    per_row[k].setdefault(name, []).append(v)
                bar.advance(task)
    out = []
    for row, vals in zip(rows, per_row):
        res = {"name": row.name, "motions": len(row.for_repeat(0)),
               "metrics": {n: dict(zip(("mean", "ci"), M.mean_ci(v))) for n, v in vals.items()},
               "repeats": {n: v for n, v in vals.items()}, **row.extra}
        if row.mm_groups:
            res["mmodality_counts"] = {"captions": len(row.mm_groups),
                                       "samples_per_caption": int(np.median([len(g) for g in row.mm_groups])),
                                       "pairs_per_caption": cfg.mm_pairs}
        out.append(res)
    return out
