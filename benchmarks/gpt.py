"""Sampling speed of the text-to-motion GPT: tokens per second with and without the KV cache.

    python benchmarks/gpt.py [--sizes small,paper] [--batches 1,32] [--tokens 50] [--threads 0] [--json out.json]

For each model size (the CPU default of recipes/gpt/default.yaml, the paper's 18 x 1024 x 16
of recipes/gpt/paper.yaml) and batch size, it generates ``--tokens`` codes per row (End masked
until then, so every row runs the full length) from randomly initialised weights (speed does
not depend on training) and reports generated tokens per second with the cache (one new
position per step) and without it (the whole prefix recomputed every step), and their ratio.
Both are measured in this run on this machine, so the ratio means something even on a busy
shared CPU where the absolute numbers do not.
"""

from __future__ import annotations

import argparse
import json
import platform
import sys
import time
from pathlib import Path

import torch

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from motok.config import load_config  # noqa: E402
from motok.gpt.model import MotionGPT, count_parameters  # noqa: E402
from motok.gpt.sample import generate  # noqa: E402
from motok.gpt.train import TrainConfig  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
RECIPES = {"small": ROOT / "recipes/gpt/default.yaml", "paper": ROOT / "recipes/gpt/paper.yaml"}
CODES, TEXT_DIM = 512, 384


def time_generation(model: MotionGPT, batch: int, tokens: int, use_cache: bool) -> float:
    text = torch.randn(batch, TEXT_DIM, generator=torch.Generator().manual_seed(0))
    target = torch.full((batch,), tokens)
    generate(model, text, target_len=torch.full((batch,), 2), use_cache=use_cache)  # warm-up
    t0 = time.perf_counter()
    g = generate(model, text, target_len=target, use_cache=use_cache, seeds=list(range(batch)))
    dt = time.perf_counter() - t0
    assert all(len(c) == tokens for c in g.codes)
    return batch * tokens / dt


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--sizes", default="small,paper")
    ap.add_argument("--batches", default="1,32")
    ap.add_argument("--tokens", type=int, default=50, help="codes generated per row (<= block_size - 1)")
    ap.add_argument("--threads", type=int, default=0, help="torch threads (0 = default)")
    ap.add_argument("--json", type=Path, default=None)
    args = ap.parse_args(argv)
    if args.threads:
        torch.set_num_threads(args.threads)
    rows = []
    for size in args.sizes.split(","):
        cfg = load_config(TrainConfig, RECIPES[size]).model
        torch.manual_seed(0)
        model = MotionGPT(cfg, CODES, TEXT_DIM).eval()
        n = min(args.tokens, model.max_codes)
        params = count_parameters(model)
        for b in map(int, args.batches.split(",")):
            cached = time_generation(model, b, n, True)
            full = time_generation(model, b, n, False)
            rows.append({"size": size, "layers": cfg.num_layers, "dim": cfg.dim, "heads": cfg.heads,
                         "params_M": round(params / 1e6, 1), "batch": b, "tokens": n,
                         "tok_s_cache": round(cached, 1), "tok_s_no_cache": round(full, 1),
                         "speedup": round(cached / full, 2)})
            r = rows[-1]
            print(f"{size:6s} {r['params_M']:7.1f}M batch {b:3d}: {cached:9.1f} tok/s cached, "
                  f"{full:9.1f} tok/s recomputed, x{r['speedup']:.2f}", flush=True)
        del model
    print()
    print(f"torch {torch.__version__}, {torch.get_num_threads()} threads, {platform.processor() or platform.machine()}")
    print("| model | params | batch | tokens/s with cache | tokens/s without | ratio |")
    print("|---|---|---|---|---|---|")
    for r in rows:
        print(f"| {r['size']} ({r['layers']} x {r['dim']} x {r['heads']}) | {r['params_M']}M | {r['batch']} | "
              f"{r['tok_s_cache']} | {r['tok_s_no_cache']} | {r['speedup']}x |")
    if args.json:
        args.json.write_text(json.dumps(rows, indent=2))
    return 0


if __name__ == "__main__":
    sys.exit(main())
