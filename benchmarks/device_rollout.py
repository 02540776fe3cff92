"""The rollout on MuJoCo Warp with host arrays against the same rollout kept on the device
(``env.on_device``), side by side in one run, on the same stepper:

1. env: the imitation MDP alone (physics, Eq. 7 observation, Eq. 9 goal, Eq. 10 reward,
   terminations, resets), small random residual actions; env-steps/s host and device;
2. train: the expert trainer (rollout, AMP, PPO) for a few iterations; samples/s host and device.

The ratio device/host is what the on-device path buys: on a GPU the host path copies the state
to the host and the controls back every control step and runs the terms on the CPU; on Warp's
CPU device (the only one here) both paths run on the CPU, and the ratio measures what the host
path's float64 mirrors and conversions cost.

    .venv/bin/python benchmarks/device_rollout.py --data DATA.h5 [--clips 'dataset-2_walk_normal*']
        [--device cpu|cuda] [--envs 64] [--seconds 8] [--iterations 3]
"""

from __future__ import annotations

import argparse
import os
import tempfile
import time
from dataclasses import replace

import numpy as np
import torch

from motok.control.expert.model import ExpertConfig
from motok.control.expert.train import ExpertTrainer, imitation_mdp
from motok.control.mdp.actions import ActionConfig
from motok.control.tasks.imitation import ImitationTaskConfig
from motok.data.dataset import select_clips
from motok.sim.env import SimConfig
from motok.sim.reference import humanoid_for, load_library


def env_rate(mdp, seconds: float) -> float:
    env = mdp.env
    mdp.reset()
    rng = np.random.default_rng(0)
    steps, t0 = 0, None
    while t0 is None or time.perf_counter() - t0 < seconds:
        a = rng.normal(0.0, 0.055, (env.num_envs, env.action_dim))
        if env.on_device:
            a = torch.as_tensor(a, dtype=torch.float32, device=env.torch_device)
        obs, goal, _, term, trunc, _ = mdp.step(a)
        mdp.restart_done(term | trunc, obs, goal)
        if t0 is None:  # the first step compiles and loads kernels: not timed
            t0 = time.perf_counter()
            continue
        steps += env.num_envs
    return steps / (time.perf_counter() - t0)


def train_rate(cfg: ExpertConfig, hum, lib, iterations: int) -> float:
    tr = ExpertTrainer(cfg, hum, lib)
    tr.start_segment()
    tr.step()  # warm-up
    t0 = time.perf_counter()
    for _ in range(iterations):
        tr.step()
    return iterations * tr.samples_per_iteration / (time.perf_counter() - t0)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--data", required=True)
    ap.add_argument("--clips", default="dataset-2_walk_normal*")
    ap.add_argument("--device", default="cpu")
    ap.add_argument("--envs", type=int, default=64)
    ap.add_argument("--seconds", type=float, default=8.0)
    ap.add_argument("--iterations", type=int, default=3)
    args = ap.parse_args()
    torch.set_num_threads(1)
    os.environ.setdefault("MOTOK_CACHE", os.path.join(tempfile.gettempdir(), "motok-bench-cache"))
    hum = humanoid_for(args.data)
    lib = load_library(hum, args.data, clips=select_clips(args.data, args.clips, None))
    sim = SimConfig(num_envs=args.envs, nthread=1, backend="warp", device=args.device)
    tc, ac = ImitationTaskConfig(termination="mean"), ActionConfig(base="reference")
    print(f"{len(lib)} clips, {args.envs} envs, MuJoCo Warp on {args.device}; load {os.getloadavg()[0]:.2f}")
    rates = {}
    for on in (False, True):  # interleaved twice: the machine's speed drifts
        for rnd in range(2):
            mdp = imitation_mdp(hum, lib, replace(sim, on_device=on), tc, ac, 0)
            rates.setdefault(("env", on), []).append(env_rate(mdp, args.seconds))
    cfg = ExpertConfig(seed=0, iterations=10**6)
    cfg.env = replace(sim)
    cfg.ppo.horizon, cfg.ppo.minibatch_size = 16, 256
    cfg.action, cfg.task = ac, tc
    for rnd in range(2):
        for on in (False, True):
            cfg.env = replace(sim, on_device=on)
            rates.setdefault(("train", on), []).append(train_rate(cfg, hum, lib, args.iterations))
    for what, unit in (("env", "env-steps/s"), ("train", "samples/s")):
        host, dev = np.median(rates[(what, False)]), np.median(rates[(what, True)])
        print(f"{what:5s}  host {host:10,.0f} {unit}   device {dev:10,.0f} {unit}   device/host {dev / host:.2f}")
    print(f"load {os.getloadavg()[0]:.2f}")


if __name__ == "__main__":
    main()
