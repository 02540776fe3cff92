"""Exact nearest-neighbour search of motion matching (``motok eval motion-matching``): transitions
searched per second by the chunked torch search (``motok.eval.motion_matching.nearest``) against
a brute-force numpy baseline (one query at a time against every key, float64) measured in the
same run on a subset of the same queries, with both answers compared on that subset. The last
line extrapolates to the paper's 800,000 generated transitions against the keys.

    .venv/bin/python benchmarks/motion_matching.py [--queries 100000] [--keys 300000] [--dim 130]
    .venv/bin/python benchmarks/motion_matching.py --data runs/bandai2.h5 --queries 100000   # real transitions

With ``--data`` the keys are the dataset's normalised transitions and the queries dataset
transitions with 1 cm of noise per joint coordinate (the search costs the same for any content:
it is exact, nothing is pruned); without it both are Gaussian.
"""

from __future__ import annotations

import argparse
import time

import numpy as np
import torch

from motok.eval.motion_matching import brute_force, nearest, normaliser
from motok.eval.transitions import load_set

PAPER_TRANSITIONS = 800_000


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--queries", type=int, default=100_000)
    ap.add_argument("--keys", type=int, default=300_000, help="synthetic keys (ignored with --data)")
    ap.add_argument("--dim", type=int, default=130, help="synthetic dimension (ignored with --data)")
    ap.add_argument("--data", default=None, help="a motion-dataset: its transitions are the keys")
    ap.add_argument("--baseline-queries", type=int, default=20)
    ap.add_argument("--threads", type=int, default=torch.get_num_threads())
    args = ap.parse_args()
    torch.set_num_threads(args.threads)
    rng = np.random.default_rng(0)
    if args.data:
        ds = load_set(args.data)
        mean, std = normaliser(ds.x)
        keys = (ds.x - mean) / std
        sel = rng.choice(len(keys), args.queries, replace=len(keys) < args.queries)
        # 1 cm on every coordinate of the raw transition, then normalised like the keys
        queries = ((ds.x[sel] + rng.normal(0, 0.01, (len(sel), keys.shape[1])).astype(np.float32)) - mean) / std
    else:
        keys = rng.normal(size=(args.keys, args.dim)).astype(np.float32)
        queries = rng.normal(size=(args.queries, args.dim)).astype(np.float32)
    nq, nk, dim = len(queries), len(keys), keys.shape[1]
    print(f"{nq:,} queries x {nk:,} keys, {dim} dimensions, {args.threads} torch threads")

    t0 = time.perf_counter()
    d, i = nearest(queries, keys)
    exact_s = time.perf_counter() - t0
    rate = nq / exact_s

    b = args.baseline_queries
    t0 = time.perf_counter()
    bd, bi = brute_force(queries[:b], keys)
    base_s = (time.perf_counter() - t0) / b
    agree = float((bi == i[:b]).mean())
    assert np.allclose(bd, d[:b], rtol=1e-4, atol=1e-4), (bd, d[:b])

    print(f"chunked torch search: {exact_s:.1f} s, {rate:,.0f} transitions/s "
          f"({nq * nk / exact_s / 1e6:,.0f} M pairs/s)")
    print(f"brute-force numpy:    {base_s * 1e3:.0f} ms per transition ({1 / base_s:,.1f} transitions/s) on {b} of "
          f"them; same neighbours {agree:.0%}, same distances")
    print(f"speed-up: {rate * base_s:,.0f}x")
    print(f"paper scale ({PAPER_TRANSITIONS:,} generated transitions against these {nk:,}): "
          f"{PAPER_TRANSITIONS / rate / 60:.1f} min exact, {PAPER_TRANSITIONS * base_s / 3600:.0f} h brute force")


if __name__ == "__main__":
    main()
