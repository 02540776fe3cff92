"""The full T2M evaluation of a test split, generation excluded: real-motion and reconstruction
rows, 20 repeats each (R-precision, FID, MM-Dist, Diversity), plus the physical metrics; the
target is under five minutes on this machine (2 shared cores, no GPU).

For scale, the same run times the reference's per-pair distances: a Python loop over every
(caption, motion) pair of the 32x32 R-precision batches on a subset of batches, extrapolated to
all the batches of the evaluation, against motok's one-matrix-product distances on that subset.

    .venv/bin/python benchmarks/eval.py --evaluator RUN [--tokenizer RUN] [--data DATA.h5]
"""

from __future__ import annotations

import argparse
import json
import math
import time
from pathlib import Path

import numpy as np

from motok.eval import metrics as M
from motok.eval.report import T2MConfig, markdown, t2m


def naive_distances(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """One pair at a time, as a straightforward port would do."""
    out = np.zeros((len(a), len(b)))
    for i in range(len(a)):
        for j in range(len(b)):
            s = 0.0
            for k in range(a.shape[1]):
                d = float(a[i, k]) - float(b[j, k])
                s += d * d
            out[i, j] = math.sqrt(s)
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--evaluator", required=True, type=Path)
    ap.add_argument("--tokenizer", type=Path, default=None)
    ap.add_argument("--data", type=Path, default=Path("/tmp/motok-data/bandai2.h5"))
    ap.add_argument("--repeats", type=int, default=20)
    ap.add_argument("--naive-batches", type=int, default=4, help="R-precision batches timed with the pair loop")
    ap.add_argument("--out-json", type=Path, default=None)
    args = ap.parse_args()

    cfg = T2MConfig(repeats=args.repeats)
    t0 = time.perf_counter()
    report = t2m(args.evaluator, args.data, cfg, tokenizer=args.tokenizer)
    total = time.perf_counter() - t0
    print(markdown(report))
    print()
    rows = len(report["rows"])
    batches = report["clips"] // cfg.batch
    print(f"full evaluation: {rows} rows x {cfg.repeats} repeats of {report['clips']} clips "
          f"({batches} R-precision batches each): {total:.1f} s (target < 300 s)")

    # The reference: per-pair distance loops on a few 32x32 batches, extrapolated.
    rng = np.random.default_rng(0)
    d = int(json.loads((args.evaluator / "bundle.json").read_text())["config"]["embed_dim"])
    a = rng.normal(size=(args.naive_batches, cfg.batch, d))
    b = rng.normal(size=(args.naive_batches, cfg.batch, d))
    t1 = time.perf_counter()
    slow = [naive_distances(x, y) for x, y in zip(a, b)]
    naive = (time.perf_counter() - t1) / args.naive_batches
    t1 = time.perf_counter()
    for _ in range(20):
        fast = [M.euclidean_distances(x, y) for x, y in zip(a, b)]
    vec = (time.perf_counter() - t1) / (20 * args.naive_batches)
    assert all(np.allclose(s, f) for s, f in zip(slow, fast))
    n_batches = rows * cfg.repeats * batches
    print(f"distance matrices, per 32x32 batch: pair loop {naive * 1e3:.1f} ms, motok {vec * 1e3:.3f} ms "
          f"({naive / vec:,.0f}x); for the {n_batches} batches of this evaluation the pair loop alone "
          f"would take {naive * n_batches:.0f} s, motok's {vec * n_batches:.2f} s")
    if args.out_json:
        args.out_json.write_text(json.dumps({**report, "benchmark_seconds": total}, indent=2, default=str))


if __name__ == "__main__":
    main()
