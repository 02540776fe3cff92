"""The physics timestep against a learned expert: how much cheaper a coarser step would be and
what it does to tracking, measured side by side in one run.

A trained expert (``RUN``, trained at the humanoid's timestep, 1/120 s by default: 4 substeps per
30 Hz control step) plays the chosen clips from frame 0 (``motok.control.tasks.imitation``) on the same
humanoid rebuilt with each timestep; only the integration step changes (gains, contacts,
solver and the policy stay). Per timestep: substeps per control step, control steps per second
of the imitation MDP (its ratio to the trained timestep's), success (played to the end, the run's
failure test), MPJPE and G-MPJPE.

    .venv/bin/python benchmarks/timestep.py --run RUN [--data DATA.h5] [--split test]
        [--clips 'dataset-2_walk*'] [--hz 120 90 60]

PD tracking cannot answer this: it falls within half a second at any timestep (docs/sim.md).
"""

from __future__ import annotations

import argparse
import os
import tempfile
import time
from dataclasses import replace
from pathlib import Path

import numpy as np

from motok.control.tasks.imitation import evaluate
from motok.control.expert.model import load_expert
from motok.control.expert.train import imitation_mdp
from motok.data.dataset import select_clips
from motok.sim.humanoid import HumanoidConfig, load_humanoid
from motok.sim.mjcf import humanoid_xml, measure_humanoid
from motok.sim.reference import load_library


def control_rate(hum, lib, cfg, seconds: float = 3.0) -> float:
    """Control steps per second of the imitation MDP with zero residual actions (64 envs)."""
    mdp = imitation_mdp(hum, lib, replace(cfg.env, num_envs=64), cfg.task, cfg.action, 0)
    mdp.reset()
    zero = np.zeros((64, mdp.action_dim))
    steps, t0 = 0, time.perf_counter()
    while time.perf_counter() - t0 < seconds:
        _, _, _, term, trunc, _ = mdp.step(zero)
        done = term | trunc
        if done.any():
            mdp.reset(np.flatnonzero(done))
        steps += 1
    return steps / (time.perf_counter() - t0)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--run", required=True, type=Path)
    ap.add_argument("--data", default=None)
    ap.add_argument("--split", default=None)
    ap.add_argument("--clips", default=None)
    ap.add_argument("--hz", type=float, nargs="*", default=[120.0, 90.0, 60.0], help="physics steps per second")
    a = ap.parse_args()
    cfg, hum0, ac, meta = load_expert(a.run)
    data = a.data or meta["extra"]["data"]
    names = select_clips(data, a.clips, a.split) if (a.clips or a.split) else meta["extra"]["clips"]
    trained = hum0.meta["config"]
    body = measure_humanoid(data, HumanoidConfig(**trained))
    print(f"{a.run} (iteration {meta['extra']['iteration']}, trained at {1 / trained['timestep']:.0f} Hz), "
          f"{len(names)} clips; load average {os.getloadavg()[0]:.2f}")
    print(f"{'physics Hz':>10} {'substeps':>8} {'ctrl steps/s':>13} {'cost':>6} {'success':>8} {'MPJPE':>7} {'G-MPJPE':>8}")
    base = None
    with tempfile.TemporaryDirectory() as tmp:
        for hz in a.hz:
            path = Path(tmp) / f"h{hz:g}.xml"
            path.write_text(humanoid_xml(body, HumanoidConfig(**{**trained, "timestep": 1.0 / hz}))[0])
            hum = load_humanoid(path)
            lib = load_library(hum, data, control_hz=cfg.env.control_hz, clips=names, cache_dir=tmp)
            rate = control_rate(hum, lib, cfg)
            base = base or rate
            o = evaluate(hum, ac, lib, cfg.env, cfg.task, cfg.action, batch=cfg.sampling.eval_batch)["overall"]
            print(f"{hz:>10g} {hum.substeps:>8} {rate:>13,.0f} {base / rate:>6.2f} {o['success_rate']:>8.1%} "
                  f"{o['mpjpe_mm']:>7.1f} {o['g_mpjpe_mm']:>8.1f}", flush=True)


if __name__ == "__main__":
    main()
