"""PPO training throughput against the raw environment step rate, measured in the same run.

    .venv/bin/python benchmarks/control.py --data DATA.h5 [--clips 'dataset-2_walk_normal*']
        [--recipe recipes/control/expert.yaml] [--iterations 10] [--seconds 5]

1. env: the imitation environment alone, N envs, small random residual actions (std as the
   recipe's policy), finished environments reset: the ceiling for a learner on this machine.
2. ppo: the expert trainer (rollouts with policy inference, Eq. 10 reward, AMP reward and
   discriminator update, PPO update) for a few iterations; samples/s and its split.
Ratio = PPO samples/s / env steps/s. Run it on a quiet machine for clean numbers.
"""

from __future__ import annotations

import argparse
import tempfile
import time

import numpy as np
import torch

from motok.config import load_config
from motok.control.clips import select_clips
from motok.control.expert import ExpertConfig, ExpertTrainer, imitation_mdp
from motok.sim.reference import humanoid_for, load_library


def env_rate(hum, lib, cfg: ExpertConfig, seconds: float) -> float:
    env = imitation_mdp(hum, lib, cfg.env, cfg.task, cfg.action, cfg.seed)
    env.reset()
    rng = np.random.default_rng(0)
    std = float(np.exp(cfg.net.log_std))
    steps, t0 = 0, time.perf_counter()
    while time.perf_counter() - t0 < seconds:
        _, _, _, term, trunc, _ = env.step(rng.normal(0.0, std, (env.num_envs, env.action_dim)))
        done = term | trunc
        if done.any():
            env.reset(np.flatnonzero(done))
        steps += env.num_envs
    return steps / (time.perf_counter() - t0)


def ppo_rate(hum, lib, cfg: ExpertConfig, iterations: int) -> dict:
    torch.set_num_threads(max(1, cfg.torch_threads))
    tr = ExpertTrainer(cfg, hum, lib)
    tr.start_segment()
    tr.step()  # warm-up: first-call allocations
    rows = [tr.step() for _ in range(iterations)]
    n = cfg.ppo.horizon * cfg.env.num_envs * iterations
    wall = sum(r["rollout_s"] + r["update_s"] for r in rows)
    return {"samples_per_s": n / wall, "rollout_s": np.mean([r["rollout_s"] for r in rows]),
            "update_s": np.mean([r["update_s"] for r in rows])}


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--data", default="/tmp/motok-data/bandai2.h5")
    ap.add_argument("--clips", default="dataset-2_walk_normal*")
    ap.add_argument("--recipe", default="recipes/control/expert.yaml")
    ap.add_argument("--set", dest="sets", action="append", default=[])
    ap.add_argument("--iterations", type=int, default=10)
    ap.add_argument("--seconds", type=float, default=5.0)
    a = ap.parse_args()
    cfg = load_config(ExpertConfig, a.recipe, a.sets)
    hum = humanoid_for(a.data)
    lib = load_library(hum, a.data, clips=select_clips(a.data, a.clips))
    with tempfile.TemporaryDirectory():
        raw = env_rate(hum, lib, cfg, a.seconds)
        ppo = ppo_rate(hum, lib, cfg, a.iterations)
    N, T = cfg.env.num_envs, cfg.ppo.horizon
    print(f"{len(lib)} clips, N = {N} envs, horizon {T} ({N * T} samples/iteration), torch threads {cfg.torch_threads}")
    print(f"env alone:  {raw:9,.0f} env-steps/s")
    print(f"PPO + AMP:  {ppo['samples_per_s']:9,.0f} samples/s  (rollout {ppo['rollout_s']:.2f} s + update "
          f"{ppo['update_s']:.2f} s per iteration)")
    print(f"ratio:      {ppo['samples_per_s'] / raw:9.2f}")


if __name__ == "__main__":
    main()
