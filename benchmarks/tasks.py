"""Task-learning throughput (``motok control train --task``) against what it stands on, in one run:

1. env: the task's MDP alone with PD targets holding the current pose (physics, the task's goal,
   reward and terminations, resets), control steps/s;
2. decoded: the same MDP with random high-level actions decoded by the frozen prior
   (``LatentActionMap``: normalise, codes or offset to ``z_bar``, decoder); ``decoded/env`` is
   the price of the prior at every step;
3. train: the high-level PPO trainer (policy inference, the decoder, PPO update) for a few
   iterations, samples/s; ``train/decoded`` the share of the stepping rate training keeps.

    .venv/bin/python benchmarks/tasks.py --data runs/bandai2.h5 [--prior PRIOR]
        [--task navigation] [--recipe recipes/control/task_navigation.yaml] [--iterations 6]

Without ``--prior`` the prior is a randomly initialised hybrid of ``recipes/control/prior_hybrid.yaml``'s
sizes on the humanoid built from ``--data``: the same arithmetic per step as a trained one.
Run it on a quiet machine for clean numbers (the load average is printed before and after).
"""

from __future__ import annotations

import argparse
import os

import numpy as np
import torch

from motok.config import load_config
from motok.control.priors.model import DistillConfig, load_prior
from motok.control.mdp.actions import ActionConfig, pd_targets
from motok.control.priors.model import LatentPrior
from motok.control.highlevel.policy import TaskTrainConfig, task_mdp
from motok.control.highlevel.train import TaskTrainer
from motok.control.mdp.task_env import TaskEnv
from motok.data.dataset import select_clips
from motok.sim.reference import humanoid_for, load_library
from rates import steps_per_s, train_rate  # benchmarks/rates.py, beside this file


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--data", default="runs/bandai2.h5")
    ap.add_argument("--clips", default="dataset-2_walk_*")
    ap.add_argument("--prior", default=None)
    ap.add_argument("--task", default="navigation")
    ap.add_argument("--recipe", default="recipes/control/task_navigation.yaml")
    ap.add_argument("--set", dest="sets", action="append", default=[])
    ap.add_argument("--iterations", type=int, default=6)
    ap.add_argument("--seconds", type=float, default=4.0)
    a = ap.parse_args()
    cfg = load_config(TaskTrainConfig, a.recipe, [*a.sets, f"task={a.task}"])
    torch.set_num_threads(max(1, cfg.torch_threads))
    if a.prior:
        pcfg, hum, model, _ = load_prior(a.prior)
    else:
        pcfg = load_config(DistillConfig, "recipes/control/prior_hybrid.yaml")
        hum = humanoid_for(a.data)
        model = None
    lib = load_library(hum, a.data, control_hz=cfg.env.control_hz, clips=select_clips(a.data, a.clips))
    plain = task_mdp(cfg, hum, lib, model or _random_prior(pcfg, hum, lib), 1.0, cfg.seed)
    model = plain.action_map.model
    print(f"load average {os.getloadavg()[0]:.2f} on {os.cpu_count()} cores; task {cfg.task}, prior {model.kind} "
          f"({'trained' if a.prior else 'random weights'}), N = {cfg.env.num_envs} envs x horizon {cfg.ppo.horizon}, "
          f"MuJoCo threads {cfg.env.nthread}, {len(lib)} clips")
    hold = TaskEnv(plain.env, plain.task, lambda x, env, task: pd_targets(ActionConfig("current"), x, env, task))
    zeros = np.zeros((cfg.env.num_envs, plain.action_dim))
    env = max(steps_per_s(hold, lambda rng: zeros, a.seconds) for _ in range(2))
    tr = TaskTrainer(cfg, hum, lib, pcfg, model)
    pol = tr.ac.policy

    def random_actions(rng):
        if pol.action_dtype == torch.int64:
            return rng.integers(0, pol.classes, (cfg.env.num_envs, pol.heads))
        return rng.normal(0.0, cfg.net.std, (cfg.env.num_envs, model.cfg.latent_dim)).astype(np.float32)

    decoded = max(steps_per_s(plain, random_actions, a.seconds) for _ in range(2))
    tr.start_segment()
    t = train_rate(tr, a.iterations)
    train = t["samples_per_s"]
    print(f"{'env-steps/s':>12} {'decoded/s':>10} {'decoded/env':>12} {'train samples/s':>16} {'train/decoded':>14} "
          f"{'rollout s':>10} {'update s':>9}")
    print(f"{env:>12,.0f} {decoded:>10,.0f} {decoded / env:>12.2f} {train:>16,.0f} {train / decoded:>14.2f} "
          f"{t['rollout_s']:>10.3f} {t['update_s']:>9.3f}")
    print(f"load average after {os.getloadavg()[0]:.2f}")


def _random_prior(pcfg: DistillConfig, hum, lib) -> LatentPrior:
    from motok.sim.env import HumanoidEnv, SimConfig

    env = HumanoidEnv(hum, SimConfig(num_envs=1, nthread=1))
    torch.manual_seed(0)
    return LatentPrior(pcfg.prior, env.obs_dim, len(hum.skeleton.joints) * 15, env.action_dim).eval()


if __name__ == "__main__":
    main()
