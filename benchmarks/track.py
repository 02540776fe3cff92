"""Tracking throughput (``motok control track``) against realtime and the physics it stands on, in
one run, on the same humanoid and batch size:

1. physics: ``HumanoidEnv.step`` alone on N environments started from the clips' first frames,
   PD targets holding the current pose (no policy, no reference, no failure test), simulated
   seconds per wall second;
2. track: the whole ``track()`` call on K clips (the reference library, the controller's inference,
   the failure test, resampling to the motion's rate, features, the artifact written), motion
   seconds tracked per wall second (the seconds each clip played, up to its end or failure).

``track/physics`` is the share of the physics rate the tracking keeps (below it: the policy, and
the environments of a batch that keep stepping after their clip ended or failed, until the
batch's last one does); ``track x realtime`` says how long a GPT evaluation's samples take.

    .venv/bin/python benchmarks/track.py --prior runs/prior_hybrid --data runs/bandai2.h5
        [--split test] [--clips 'dataset-2_walk*'] [--batch 64] [--seconds 4]

Run it on a quiet machine for clean numbers (the load average is printed before and after).
"""

from __future__ import annotations

import argparse
import os
import tempfile
import time
from dataclasses import replace
from pathlib import Path

import numpy as np
import torch

from motok.control.priors.load import load_controller
from motok.control.track import track
from motok.data.dataset import select_clips
from motok.sim.env import HumanoidEnv
from motok.sim.reference import load_library


def physics_rate(hum, sim, lib, n: int, seconds: float) -> float:
    """Simulated seconds per wall second of ``n`` environments holding their pose (no policy)."""
    env = HumanoidEnv(hum, replace(sim, num_envs=n, on_device=False))
    starts = lib.starts[np.arange(n) % len(lib)]
    env.set_state(np.arange(n), lib.qpos[starts], lib.qvel[starts])
    steps, t0 = 0, time.perf_counter()
    while time.perf_counter() - t0 < seconds:
        env.step(env.qpos[:, env.hinge_adr])
        steps += 1
    return steps * n * env.dt / (time.perf_counter() - t0)


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--prior", default=None)
    ap.add_argument("--expert", default=None)
    ap.add_argument("--data", default="runs/bandai2.h5")
    ap.add_argument("--split", default="test")
    ap.add_argument("--clips", default="dataset-2_walk*", help="a glob of clip names (with --split)")
    ap.add_argument("--batch", type=int, default=64)
    ap.add_argument("--seconds", type=float, default=4.0)
    a = ap.parse_args()
    if a.prior is None and a.expert is None:
        a.prior = "runs/prior_hybrid"
    torch.set_num_threads(1)
    controller = load_controller(a.expert, a.prior)
    cfg, hum = controller.cfg, controller.humanoid
    names = select_clips(a.data, a.clips, a.split)
    hz = float(cfg.env.control_hz or hum.control_hz)
    lib = load_library(hum, a.data, control_hz=hz, clips=names, use_cache=False)
    print(f"load average {os.getloadavg()[0]:.2f} on {os.cpu_count()} cores; controller "
          f"{a.prior or a.expert}; {len(names)} clips of {a.split}, batch {a.batch}, control {hz:g} Hz, "
          f"MuJoCo threads {cfg.env.nthread}")
    phys = max(physics_rate(hum, cfg.env, lib, min(a.batch, len(names)), a.seconds) for _ in range(2))
    with tempfile.TemporaryDirectory() as tmp:
        t0 = time.perf_counter()
        res = track(controller, a.data, Path(tmp) / "tracked.h5", clips=a.clips, split=a.split, batch=a.batch)
        wall = time.perf_counter() - t0
    played = sum(v.get("seconds", 0.0) for v in res["per_clip"].values())
    rate = played / wall
    print(f"{'physics sim-s/s':>16} {'track sim-s/s':>14} {'track/physics':>14} {'track x realtime':>17} "
          f"{'clips/s':>8} {'tracked to end':>15}")
    print(f"{phys:>16,.1f} {rate:>14,.1f} {rate / phys:>14.2f} {rate:>17.1f} {len(names) / wall:>8.2f} "
          f"{res['tracked_to_end']:>15.1%}")
    print(f"load average after {os.getloadavg()[0]:.2f}")


if __name__ == "__main__":
    main()
