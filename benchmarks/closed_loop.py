"""Closed-loop text to physics against the open loop, in one run, on the same GPT, controller,
texts and seeds: how many seconds of motion each makes per wall second (its realtime factor),
and their ratio.

1. open loop: ``gpt sample --prior`` (:func:`motok.control.text_to_physics.text_to_physics`):
   sample the whole motion, then track it;
2. closed loop: ``gpt sample --prior --closed-loop`` (:func:`motok.control.closed_loop.loop.closed_loop`):
   re-plan every ``--replan-every`` seconds from the simulated character.

Both calls are timed whole (loading the runs, generating, simulating, writing), best of
``--repeats``; the closed loop's generation and simulation alone (``time_run_s``, the target
cost: a 10-s sample in under 10 s on 2 cores, a realtime factor of at least 1) and the part of it
spent planning (encoding windows, the GPT, decoding) are printed beside. Realtime factor: the
seconds of motion simulated (to the end or to a failure) per wall second.

    .venv/bin/python benchmarks/closed_loop.py --gpt runs/gpt --prior runs/prior_hybrid
        [--text "a person walks forward"] [--seconds 10] [--replan-every 1] [-n 1] [--repeats 2]

Run it on a quiet machine for clean numbers (the load average is printed before and after).
"""

from __future__ import annotations

import argparse
import os
import tempfile
import time
from pathlib import Path

import torch

from motok.control.closed_loop.loop import closed_loop
from motok.control.text_to_physics import text_to_physics


def best_of(repeats: int, fn) -> tuple[float, dict]:
    """The shortest wall time of ``repeats`` calls of ``fn(k)`` and that call's result."""
    best = None
    for k in range(repeats):
        t0 = time.perf_counter()
        res = fn(k)
        wall = time.perf_counter() - t0
        if best is None or wall < best[0]:
            best = (wall, res)
    return best


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--gpt", default="runs/gpt")
    ap.add_argument("--prior", default="runs/prior_hybrid")
    ap.add_argument("--text", action="append", default=None, help="repeatable (default: a walk)")
    ap.add_argument("--seconds", type=float, default=10.0)
    ap.add_argument("--replan-every", type=float, default=1.0)
    ap.add_argument("-n", "--num-samples", type=int, default=1)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--repeats", type=int, default=2)
    a = ap.parse_args()
    texts = a.text or ["a person walks forward"]
    print(f"load average {os.getloadavg()[0]:.2f} on {os.cpu_count()} cores; torch threads {torch.get_num_threads()}; "
          f"GPT {a.gpt}, prior {a.prior}; {len(texts)} text(s) x {a.num_samples}, {a.seconds:g} s, "
          f"re-plan every {a.replan_every:g} s")
    opts = dict(num_samples=a.num_samples, seed=a.seed, seconds=a.seconds)
    with tempfile.TemporaryDirectory() as tmp:
        tmp = Path(tmp)
        w_open, r_open = best_of(a.repeats, lambda k: text_to_physics(a.gpt, texts, tmp / f"open{k}.h5",
                                                                      prior=a.prior, **opts))
        w_loop, r_loop = best_of(a.repeats, lambda k: closed_loop(a.gpt, tmp / f"loop{k}.h5", texts=texts,
                                                                  prior=a.prior, replan_every=a.replan_every, **opts))
    sim_open = sum(v.get("seconds", 0.0) for v in r_open["per_clip"].values())
    sim_loop = r_loop["seconds_simulated"]
    print(f"{'':12} {'wall s':>8} {'motion s':>9} {'x realtime':>11} {'tracked to end':>15} {'re-plans':>9}")
    print(f"{'open loop':12} {w_open:>8.2f} {sim_open:>9.2f} {sim_open / w_open:>11.2f} "
          f"{r_open['tracked_to_end']:>15.1%} {0:>9}")
    print(f"{'closed loop':12} {w_loop:>8.2f} {sim_loop:>9.2f} {sim_loop / w_loop:>11.2f} "
          f"{r_loop['tracked_to_end']:>15.1%} {r_loop['replans']:>9}")
    print(f"closed/open realtime factor {(sim_loop / w_loop) / (sim_open / w_open):.2f}; closed loop's generation "
          f"and simulation alone {r_loop['time_run_s']:.2f} s ({r_loop['realtime_factor']:.2f}x realtime), of which "
          f"planning {r_loop['time_plan_s']:.2f} s")
    print(f"load average after {os.getloadavg()[0]:.2f}")


if __name__ == "__main__":
    main()
