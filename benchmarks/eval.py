"""The full T2M evaluation of a test split, generation excluded: real-motion and reconstruction
rows, 20 repeats each (R-precision, FID, MM-Dist, Diversity), plus the physical metrics; the
target is under five minutes on this machine (2 shared cores, no GPU).

Beside it, motok's R-precision batches against the reference's own numpy code path (Guo et al.
2022, text2motion ``utils/metrics.py``, as T2M-GPT's ``utils/eval_trans.py`` carries it): the
distance matrix by the same ``|a|^2 - 2ab + |b|^2`` expansion, a full ``argsort`` of every row
and top-k as a running OR over the first k columns. Both run on the same random 32 x 32 batches
(as many as the evaluation has); their hit counts must be equal (random embeddings have no
ties), and their times are compared. Without ``--evaluator`` only this comparison runs.

    .venv/bin/python benchmarks/eval.py [--evaluator RUN [--tokenizer RUN] [--data DATA.h5]] [--batches N]
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import numpy as np

from motok.eval import metrics as M


def reference_hits(text: np.ndarray, motion: np.ndarray, top_k: int) -> np.ndarray:
    """Guo et al.'s path for one batch: hits at 1..k summed over the captions."""
    dist = np.sqrt(-2 * text @ motion.T + (text ** 2).sum(1, keepdims=True) + (motion ** 2).sum(1))
    order = np.argsort(dist, axis=1)
    own = order == np.arange(len(text))[:, None]
    return np.logical_or.accumulate(own[:, :top_k], axis=1).sum(0)


def compare(batches: int, dim: int, size: int = 32, top_k: int = 3, repeat: int = 5) -> dict:
    """Hits and best-of-``repeat`` seconds of both paths over ``batches`` random batches."""
    rng = np.random.default_rng(0)
    t = rng.normal(size=(batches, size, dim)).astype(np.float32)
    m = rng.normal(size=(batches, size, dim)).astype(np.float32)

    def best(fn):
        out, dt = None, float("inf")
        for _ in range(repeat):
            t0 = time.perf_counter()
            out = fn()
            dt = min(dt, time.perf_counter() - t0)
        return out, dt

    ref, t_ref = best(lambda: sum(reference_hits(a, b, top_k) for a, b in zip(t, m)))
    ours, t_ours = best(lambda: sum(M.r_precision_hits(a, b, top_k) for a, b in zip(t, m)))
    if not np.array_equal(ref, ours):
        raise SystemExit(f"R-precision hits differ: reference {ref.tolist()}, motok {ours.tolist()}")
    return {"batches": batches, "dim": dim, "hits": ours.tolist(), "reference_s": t_ref, "motok_s": t_ours}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--evaluator", type=Path, default=None)
    ap.add_argument("--tokenizer", type=Path, default=None)
    ap.add_argument("--data", type=Path, default=Path("/tmp/motok-data/bandai2.h5"))
    ap.add_argument("--repeats", type=int, default=20)
    ap.add_argument("--batches", type=int, default=None, help="R-precision batches to compare (default: as many "
                    "as the evaluation has; 2 rows x 20 repeats x 13 without --evaluator)")
    ap.add_argument("--dim", type=int, default=128, help="embedding size without --evaluator")
    ap.add_argument("--out-json", type=Path, default=None)
    args = ap.parse_args()

    from motok.eval.report import T2MConfig, markdown, t2m
    cfg = T2MConfig(repeats=args.repeats)
    out: dict = {}
    n_batches, dim = args.batches or 2 * cfg.repeats * (427 // cfg.batch), args.dim
    if args.evaluator is not None:
        t0 = time.perf_counter()
        report = t2m(args.evaluator, args.data, cfg, tokenizer=args.tokenizer)
        total = time.perf_counter() - t0
        print(markdown(report))
        print()
        rows, per_row = len(report["rows"]), report["clips"] // cfg.batch
        print(f"full evaluation: {rows} rows x {cfg.repeats} repeats of {report['clips']} clips "
              f"({per_row} R-precision batches each): {total:.1f} s (target < 300 s)")
        n_batches = args.batches or rows * cfg.repeats * per_row
        dim = int(json.loads((args.evaluator / "bundle.json").read_text())["config"]["embed_dim"])
        out = {**report, "benchmark_seconds": total}
    c = compare(n_batches, dim)
    print(f"R-precision of {c['batches']} batches of 32 x 32 ({c['dim']}-d), best of 5: reference numpy path "
          f"{c['reference_s'] * 1e3:.1f} ms, motok {c['motok_s'] * 1e3:.1f} ms "
          f"({c['reference_s'] / c['motok_s']:.2f}x); identical hits {c['hits']}")
    if args.out_json:
        args.out_json.write_text(json.dumps({**out, "r_precision_comparison": c}, indent=2, default=str))


if __name__ == "__main__":
    main()
