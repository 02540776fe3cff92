"""Online distillation throughput (``motok control distill``) against what it stands on, in one run:

1. env: the imitation MDP alone, PD targets holding the current pose (the student's action map,
   physics, the goal, r_im, terminations, resets), control steps/s;
2. labelled: the DAgger collector, in which the student acts and the frozen expert labels every
   visited state (two networks and the label conversion per step), samples/s; ``labelled/env``
   is the price of the networks;
3. train: the distillation trainer (that collection plus the Eq. 6 update of each iteration),
   samples/s; ``train/labelled`` the share of the collection rate training keeps, and where the
   rest goes (rollout and update seconds per iteration).

    .venv/bin/python benchmarks/distill.py --expert RUN --data runs/bandai2.h5 [--prior hybrid]
        [--recipe recipes/control/prior_hybrid.yaml] [--clips 'dataset-2_*'] [--iterations 6]

The student starts from its initial weights: the arithmetic per step is a trained one's. Run it
on a quiet machine for clean numbers (the load average is printed before and after).
"""

from __future__ import annotations

import argparse
import os
import time

import numpy as np
import torch

from motok.config import load_config
from motok.control.priors.distill import DistillTrainer
from motok.control.priors.model import DistillConfig
from motok.control.expert.model import load_expert
from motok.control.expert.train import imitation_mdp
from motok.data.dataset import select_clips
from motok.sim.reference import load_library
from rates import steps_per_s, train_rate  # benchmarks/rates.py, beside this file


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--expert", required=True)
    ap.add_argument("--data", default="runs/bandai2.h5")
    ap.add_argument("--clips", default="dataset-2_*")
    ap.add_argument("--prior", default="hybrid")
    ap.add_argument("--recipe", default=None, help="default: recipes/control/prior_PRIOR.yaml")
    ap.add_argument("--set", dest="sets", action="append", default=[])
    ap.add_argument("--iterations", type=int, default=6)
    ap.add_argument("--seconds", type=float, default=4.0)
    a = ap.parse_args()
    cfg = load_config(DistillConfig, a.recipe or f"recipes/control/prior_{a.prior}.yaml", a.sets)
    cfg.prior.kind = a.prior
    torch.set_num_threads(max(1, cfg.torch_threads))
    ecfg, hum, expert, _ = load_expert(a.expert)
    lib = load_library(hum, a.data, control_hz=cfg.env.control_hz, clips=select_clips(a.data, a.clips))
    N, T = cfg.env.num_envs, cfg.horizon
    print(f"load average {os.getloadavg()[0]:.2f} on {os.cpu_count()} cores; prior {a.prior}, N = {N} envs x "
          f"horizon {T}, MuJoCo threads {cfg.env.nthread}, update threads {cfg.update_threads}, {len(lib)} clips")

    mdp = imitation_mdp(hum, lib, cfg.env, cfg.task, cfg.action, cfg.seed)
    zeros = np.zeros((N, mdp.action_dim))
    env = max(steps_per_s(mdp, lambda rng: zeros, a.seconds) for _ in range(2))
    tr = DistillTrainer(cfg, hum, lib, ecfg, expert)
    tr.start_segment()
    tr.collector.collect()  # warm-up
    t0 = time.perf_counter()
    for _ in range(a.iterations):
        tr.collector.collect()
    labelled = N * T * a.iterations / (time.perf_counter() - t0)
    t = train_rate(tr, a.iterations)  # its warm-up step warms the update up
    train = t["samples_per_s"]
    print(f"{'env-steps/s':>12} {'labelled/s':>11} {'labelled/env':>13} {'train samples/s':>16} "
          f"{'train/labelled':>15} {'rollout s':>10} {'update s':>9}")
    print(f"{env:>12,.0f} {labelled:>11,.0f} {labelled / env:>13.2f} {train:>16,.0f} {train / labelled:>15.2f} "
          f"{t['rollout_s']:>10.3f} {t['update_s']:>9.3f}")
    print(f"load average after {os.getloadavg()[0]:.2f}")


if __name__ == "__main__":
    main()
