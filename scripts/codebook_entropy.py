"""Per-codebook entropy of a task policy's categoricals, averaged over the states of greedy episodes.

    python scripts/codebook_entropy.py runs/nav_hybrid runs/nav_hybrid_m4 [--episodes 32]

A policy over M residual codebooks has one categorical per codebook; its logged `entropy` is their
sum. This splits it, on the states the policy itself visits (the task's own evaluation, seed 0):
a codebook whose entropy stays near ln(codes) is one the policy never committed to
(docs/results.md, "Active codebooks (Fig. 13 form)")."""
import argparse
import math

import torch

from motok.control import runs
from motok.control.highlevel.evaluate import evaluate_policy
from motok.control.highlevel.policy import load_task_run


def codebook_entropy(run, episodes: int) -> tuple[list[float], float]:
    cfg, hum, ac, model, scale, meta = load_task_run(run)
    if not hasattr(ac.policy, "heads"):
        raise SystemExit(f"{run}: a continuous policy has no codebooks")
    _, lib = runs.run_library(run, meta, hum, cfg.env.control_hz, None, None, None)
    seen, log_probs = [], ac.policy.log_probs

    def recorded(x):  # every action the evaluation draws goes through here
        lp = log_probs(x)
        seen.append(ac.policy.entropies(lp))
        return lp

    ac.policy.log_probs = recorded
    cfg.env.num_envs = min(cfg.env.num_envs, episodes)
    evaluate_policy(cfg, hum, lib, model, scale, ac, episodes, 0)
    return torch.cat(seen).mean(0).tolist(), math.log(ac.policy.classes)


if __name__ == "__main__":
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("runs", nargs="+")
    ap.add_argument("--episodes", type=int, default=32)
    a = ap.parse_args()
    for run in a.runs:
        h, top = codebook_entropy(run, a.episodes)
        print(f"{run}: per codebook {', '.join(f'{x:.2f}' for x in h)} nats (uniform: {top:.2f})")
