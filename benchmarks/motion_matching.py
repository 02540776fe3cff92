"""Nearest-neighbour search of motion matching (``motok eval motion-matching``): the faiss IVF
index (``motok.eval.nn_search.build_index``, the default) against the exact torch search
(``--exact``), side by side on the same queries: time, the speed ratio, recall (the share of
queries whose found neighbour is at the exact nearest distance) and the Eq. 8 statistics (mean
and std of the valid transitions' squared distances, filtered rate) of both, with their relative
difference; the leave-one-clip-out threshold both ways; then the index alone on ``--queries``
transitions, the paper's 800,000 per row.

    .venv/bin/python benchmarks/motion_matching.py --data runs/bandai2.h5 [--queries 800000] [--exact-queries 20000]

The reference is the ``--split`` (train) clips of ``--data``; the queries are transitions of the
held-out ``--heldout`` (test) clips: the first ``--exact-queries`` of a fixed-seed shuffle of them
for the comparison, and ``--queries`` synthetic ones for the scale run, each a random held-out
transition with Gaussian noise on its raw values (sigma drawn per query from 0, 0.5, 1 and 2 cm)
so that some fall beyond the threshold, as generated motion does.
"""

from __future__ import annotations

import argparse
import time

import numpy as np
import torch

from motok.data.dataset import select_clips
from motok.eval.motion_matching import PERCENTILE, derive_threshold, match_metrics, normaliser
from motok.eval.nn_search import NPROBE, build_index, ivf_cells, nearest, search_index
from motok.eval.transitions import load_set

NOISE_M = (0.0, 0.005, 0.01, 0.02)


def stats(d, i, n, thr) -> dict:
    m = match_metrics(d, i, n, thr)
    return {k: m[k] for k in ("distance_mean", "distance_std", "filtered_rate")}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--data", required=True, help="a motion-dataset with splits")
    ap.add_argument("--split", default="train")
    ap.add_argument("--heldout", default="test")
    ap.add_argument("--queries", type=int, default=800_000, help="synthetic queries of the scale run (0: none)")
    ap.add_argument("--exact-queries", type=int, default=20_000)
    ap.add_argument("--threshold-queries", type=int, default=5_000)
    ap.add_argument("--nprobe", type=int, default=NPROBE)
    ap.add_argument("--threads", type=int, default=torch.get_num_threads())
    args = ap.parse_args()
    torch.set_num_threads(args.threads)
    rng = np.random.default_rng(0)
    ref = load_set(args.data, select_clips(args.data, None, args.split))
    held = load_set(args.data, select_clips(args.data, None, args.heldout))
    mean, std = normaliser(ref.x)
    keys = (ref.x - mean) / std
    print(f"reference: {args.split} split, {len(keys):,} transitions; queries from the {args.heldout} split "
          f"({len(held.x):,} transitions); {args.threads} threads")

    t0 = time.perf_counter()
    index = build_index(keys, nprobe=args.nprobe, threads=args.threads)
    build_s = time.perf_counter() - t0
    print(f"IVF index: nlist {ivf_cells(len(keys))}, nprobe {index.nprobe}, built in {build_s:.1f} s")

    t0 = time.perf_counter()
    thr_e = derive_threshold(keys, ref.clip, PERCENTILE, args.threshold_queries)
    te = time.perf_counter() - t0
    t0 = time.perf_counter()
    thr_f = derive_threshold(keys, ref.clip, PERCENTILE, args.threshold_queries, index=index)
    tf = time.perf_counter() - t0
    print(f"threshold ({args.threshold_queries:,} leave-one-clip-out queries): exact {thr_e['value']:.4f} in "
          f"{te:.1f} s, faiss {thr_f['value']:.4f} in {tf:.1f} s ({thr_f['value'] / thr_e['value'] - 1:+.2%})")
    thr = thr_e["value"]

    q = ((held.x - mean) / std)[rng.permutation(len(held.x))[:args.exact_queries]]
    t0 = time.perf_counter()
    de, ie = nearest(q, keys)
    exact_s = time.perf_counter() - t0
    t0 = time.perf_counter()
    df, i_f = search_index(index, keys, q)
    faiss_s = time.perf_counter() - t0
    recall = float(np.mean(df <= de * (1 + 1e-5) + 1e-7))
    se, sf = stats(de, ie, len(keys), thr), stats(df, i_f, len(keys), thr)
    print(f"\n{len(q):,} held-out queries    exact            faiss IVF        difference")
    print(f"time                     {exact_s:8.1f} s       {faiss_s:8.1f} s       {exact_s / faiss_s:.1f}x faster")
    print(f"transitions/s            {len(q) / exact_s:10,.0f}       {len(q) / faiss_s:10,.0f}")
    print(f"recall                   {'1':>10}       {recall:10.4f}")
    for k in se:
        print(f"{k:24} {se[k]:10.4f}       {sf[k]:10.4f}       {sf[k] / se[k] - 1:+.3%}")

    if args.queries:
        pick = rng.integers(0, len(held.x), args.queries)
        sigma = rng.choice(NOISE_M, args.queries).astype(np.float32)
        t0 = time.perf_counter()
        for a in range(0, args.queries, 65_536):  # built a block at a time: 800k x 130 floats is 416 MB
            p, s = pick[a:a + 65_536], sigma[a:a + 65_536, None]
            raw = held.x[p] + rng.normal(size=(len(p), keys.shape[1])).astype(np.float32) * s
            d, i = search_index(index, keys, (raw - mean) / std)
            filtered = (d > thr).sum() if a == 0 else filtered + (d > thr).sum()
        big_s = time.perf_counter() - t0
        exact_min = args.queries * exact_s / len(q) / 60
        print(f"\nscale: {args.queries:,} noisy held-out transitions through the index in {big_s:.1f} s "
              f"({args.queries / big_s:,.0f} transitions/s; {filtered / args.queries:.1%} filtered); with the "
              f"index build, {big_s + build_s:.1f} s; exact at the rate above: {exact_min:.1f} min")


if __name__ == "__main__":
    main()
