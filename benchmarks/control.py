"""Expert training throughput against the physics it stands on, for today's humanoid and the build
before the physics options (every pair colliding, Newton 20/10, dense Jacobian, islands), side by
side in one run:

1. raw: ``mujoco.rollout`` on 2 threads stepping (state, control) pairs recorded from the
   imitation MDP under PD tracking: the physics alone, mj_step/s;
2. env: the imitation MDP alone (physics + Eq. 7/9 observation, Eq. 10 reward, terminations,
   resets), N envs, small random residual actions (the recipe's policy std); ``env/raw`` =
   control steps x substeps over the raw rate (target >= 0.8);
3. train: the expert trainer (policy inference, AMP reward and discriminator update, PPO update)
   for a few iterations, samples/s; ``train/env`` = that over the env-alone rate (target >= 0.8).

    .venv/bin/python benchmarks/control.py --data DATA.h5 [--clips 'dataset-2_walk_normal*']
        [--recipe recipes/control/expert.yaml] [--iterations 8] [--seconds 4]

Run it on a quiet machine for clean numbers (the load average is printed before and after).
"""

from __future__ import annotations

import argparse
import os
import tempfile
import time
from pathlib import Path

import numpy as np
import torch

import mujoco

from motok.config import load_config
from motok.control.expert.model import ExpertConfig
from motok.control.expert.train import ExpertTrainer, imitation_mdp
from motok.data.dataset import select_clips
from motok.sim.humanoid import HumanoidConfig, load_humanoid
from motok.sim.mjcf import humanoid_xml, measure_humanoid
from motok.sim.reference import load_library
from rates import raw_rate, train_rate  # benchmarks/rates.py, beside this file

PREVIOUS = dict(self_collision="all", solver_iterations=20, ls_iterations=10, jacobian="auto", islands=True)


def env_rate(mdp, std: float, seconds: float, record: list | None = None) -> float:
    """Env-steps per second of the MDP alone; with ``record`` also the (qpos, qvel, ctrl) it stepped."""
    env = mdp.env
    mdp.reset()
    rng = np.random.default_rng(0)
    steps, t0 = 0, time.perf_counter()
    while time.perf_counter() - t0 < seconds:
        a = rng.normal(0.0, std, (env.num_envs, env.action_dim))
        if record is not None:
            ctrl = np.clip(mdp.action_map(a, env, mdp.task), env.ctrl_low, env.ctrl_high)
            record.append((env.qpos.copy(), env.qvel.copy(), ctrl))
        _, _, _, term, trunc, _ = mdp.step(a)
        done = term | trunc
        if done.any():
            mdp.reset(np.flatnonzero(done))
        steps += env.num_envs
    return steps / (time.perf_counter() - t0)


def expert_rate(hum, lib, cfg: ExpertConfig, iterations: int) -> dict:
    torch.set_num_threads(max(1, cfg.torch_threads))
    tr = ExpertTrainer(cfg, hum, lib)
    tr.start_segment()
    return train_rate(tr, iterations)


def measure(name: str, xml: str, data, clips, cfg: ExpertConfig, tmp: Path, a) -> dict:
    path = tmp / f"{name}.xml"
    path.write_text(xml)
    hum = load_humanoid(path)
    lib = load_library(hum, data, control_hz=cfg.env.control_hz, clips=clips, cache_dir=tmp)
    std = float(np.exp(cfg.net.log_std))
    mdp = imitation_mdp(hum, lib, cfg.env, cfg.task, cfg.action, cfg.seed)
    pairs: list = []
    env_rate(mdp, std, min(a.seconds, 2.0), record=pairs)
    raw = raw_rate(hum.model, pairs, mdp.env.substeps, repeats=3)
    env = max(env_rate(mdp, std, a.seconds) for _ in range(2))
    train = expert_rate(hum, lib, cfg, a.iterations)
    return {"name": name, "substeps": mdp.env.substeps, "raw": raw, "env": env, **train}


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--data", default="runs/bandai2.h5")
    ap.add_argument("--clips", default="dataset-2_walk_normal*")
    ap.add_argument("--recipe", default="recipes/control/expert.yaml")
    ap.add_argument("--set", dest="sets", action="append", default=[])
    ap.add_argument("--iterations", type=int, default=8)
    ap.add_argument("--seconds", type=float, default=4.0)
    a = ap.parse_args()
    cfg = load_config(ExpertConfig, a.recipe, a.sets)
    clips = select_clips(a.data, a.clips)
    print(f"load average {os.getloadavg()[0]:.2f} on {os.cpu_count()} cores; mujoco {mujoco.__version__}; "
          f"{len(clips)} clips, N = {cfg.env.num_envs} envs x horizon {cfg.ppo.horizon}, "
          f"torch threads {cfg.torch_threads}, MuJoCo threads {cfg.env.nthread}")
    body = measure_humanoid(a.data)
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        for name, over in (("today", {}), ("previous", PREVIOUS)):
            xml, _ = humanoid_xml(body, HumanoidConfig(**over))
            rows.append(measure(name, xml, a.data, clips, cfg, Path(tmp), a))
    print(f"{'physics':>9} {'raw mj_step/s':>14} {'env-steps/s':>12} {'env/raw':>8} {'train samples/s':>16} "
          f"{'train/env':>10} {'rollout s':>10} {'update s':>9}")
    for r in rows:
        print(f"{r['name']:>9} {r['raw']:>14,.0f} {r['env']:>12,.0f} {r['env'] * r['substeps'] / r['raw']:>8.2f} "
              f"{r['samples_per_s']:>16,.0f} {r['samples_per_s'] / r['env']:>10.2f} {r['rollout_s']:>10.3f} "
              f"{r['update_s']:>9.3f}")
    new, old = rows
    print(f"today / previous: raw {new['raw'] / old['raw']:.2f}x, env {new['env'] / old['env']:.2f}x, "
          f"train {new['samples_per_s'] / old['samples_per_s']:.2f}x; load average after {os.getloadavg()[0]:.2f}")


if __name__ == "__main__":
    main()
