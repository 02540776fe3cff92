"""Simulation speed: the humanoid's raw ``mj_step`` rate (the physical limit) against the batched
environment's control steps per second, observation, goal, reward, termination and resets
included, at N = 1, 16, 64, 256 environments on 2 threads.

The environment is driven by plain PD tracking (targets = next reference frame) with
reference-state resets of the environments that fall, so it visits the states training does.
Every (state, control) pair it steps is recorded, and the raw rate is measured by stepping
exactly those pairs again with ``mujoco.rollout`` in C++ (no Python per step) on 1 and on 2
threads. ratio = env steps/s x substeps / raw 2-thread steps/s: the share of the machine's
physics throughput that survives the environment's Python.

    .venv/bin/python benchmarks/sim.py [--data DATA.h5] [--seconds 3] [--repeats 3]
    .venv/bin/python benchmarks/sim.py --backend warp [--device cuda] --envs 64 1024 4096

``--backend warp`` adds the MuJoCo Warp stepper (``pip install motok[gpu]``) to the same run: its
environment rows (stepper ``warp``) and its raw rate, the recorded pairs stepped by MuJoCo Warp
alone on the device (``mjw.step`` only, no host copies), so its rows sit beside the C MuJoCo ones.

Other jobs may share the cores, and their load drifts within seconds: every environment run is
paired with a raw-rate run just before it, each ratio uses its own pair, and the table gives the
best environment rate with the median and range of the ratios over ``--repeats`` pairs. The
load average is printed; rerun on a quiet machine for the real ceiling.
"""

from __future__ import annotations

import argparse
import os
import tempfile
import time
from pathlib import Path

import numpy as np

import mujoco

from motok.control.expert.train import imitation_mdp
from motok.control.mdp.actions import ActionConfig
from motok.control.mdp.task_env import TaskEnv
from motok.control.tasks.imitation import ImitationTaskConfig
from motok.sim.env import SimConfig
from motok.sim.humanoid import load_humanoid
from motok.sim.mjcf import build_humanoid
from motok.sim.reference import load_library
from rates import raw_rate  # benchmarks/rates.py, beside this file


def _dataset(tmp: Path) -> Path:
    """The 24 walk_normal clips of Bandai-Namco set 2, preprocessed (as the test fixture does)."""
    from motok.data.preprocess import PreprocessConfig, preprocess
    from motok.data.root import resolve_data_root

    root = resolve_data_root(None) / "bandai-namco"
    cfg = PreprocessConfig(data=[str(root / "bandai-namco-2.tar.xz")], annotations=str(root / "annotations"),
                           clips="dataset-2_walk_normal_*", skeleton="bandai21")
    out = tmp / "walk_normal.h5"
    preprocess(cfg, out, command="benchmarks/sim.py")
    return out


def _pd(mdp: TaskEnv) -> np.ndarray:
    """Residual actions on the current pose that send the PD targets to the next reference frame."""
    env = mdp.env
    return mdp.task.next_reference()[0][:, env.hinge_adr] - env.qpos[:, env.hinge_adr]


def run_env(hum, lib, n: int, stepper: str, seconds: float, record: list | None = None,
            device: str = "cpu") -> tuple[float, float]:
    """Control steps per second (env-steps/s = this x n), and the CPU seconds per control step the
    calling thread spends outside the stepper's physics call (observation, goal, reward, resets,
    bookkeeping). Thread CPU time, unlike wall time, does not count time lost to other processes."""
    sim = (SimConfig(num_envs=n, backend="warp", device=device) if stepper == "warp"
           else SimConfig(num_envs=n, nthread=2, stepper=stepper))
    mdp = imitation_mdp(hum, lib, sim, ImitationTaskConfig(), ActionConfig("current"), 0)
    env = mdp.env
    mdp.reset()
    for _ in range(5):
        mdp.step(_pd(mdp))
    inner, physics = env.stepper.step, [0.0]

    def timed(ctrl):
        t = time.thread_time()
        out = inner(ctrl)
        physics[0] += time.thread_time() - t
        return out

    env.stepper.step = timed
    steps, t0, c0 = 0, time.perf_counter(), time.thread_time()
    while time.perf_counter() - t0 < seconds:
        a = _pd(mdp)
        if record is not None:
            q = env.qpos[:, env.hinge_adr]
            record.append((env.qpos.copy(), env.qvel.copy(), np.clip(q + a, env.ctrl_low, env.ctrl_high)))
        _, _, _, term, trunc, _ = mdp.step(a)
        done = np.flatnonzero(term | trunc)
        if len(done):
            mdp.reset(done)
        steps += 1
    return steps / (time.perf_counter() - t0), (time.thread_time() - c0 - physics[0]) / steps


def raw_warp(hum, pairs, substeps: int, n: int, device: str, seconds: float) -> float:
    """mj_step/s (world-steps) of MuJoCo Warp on ``n`` worlds started from recorded states, timing
    only its step calls: the device's physics limit, as ``raw_rate`` is the CPU's."""
    import warp as wp

    from motok.sim.warp_stepper import WarpStepper

    st = WarpStepper(hum, n, substeps, device=device)
    qpos = np.concatenate([p[0] for p in pairs])
    qvel = np.concatenate([p[1] for p in pairs])
    ctrl = np.concatenate([p[2] for p in pairs])
    rows = np.arange(n) % len(qpos)
    st.set_state(np.arange(n), qpos[rows], qvel[rows])
    st.step(ctrl[rows])  # compiles (first run only) and, on a GPU, captures the graph on the next step
    st.step(ctrl[rows])
    steps, t0 = 0, time.perf_counter()
    while time.perf_counter() - t0 < seconds or steps == 0:
        st.step_tensor(st.ctrl_t)  # the same controls again: the state moves on, no host round trip
        steps += 1
    wp.synchronize_device(st.device)
    return steps * n * substeps / (time.perf_counter() - t0)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--data", type=Path, default=None, help="motion-dataset (default: walk_normal slice of set 2)")
    ap.add_argument("--humanoid", type=Path, default=None)
    ap.add_argument("--envs", type=int, nargs="*", default=[1, 16, 64, 256])
    ap.add_argument("--steppers", nargs="*", default=["batch", "rollout"])
    ap.add_argument("--seconds", type=float, default=3.0, help="timed seconds per measurement")
    ap.add_argument("--repeats", type=int, default=3, help="best of this many runs")
    ap.add_argument("--backend", choices=["mujoco", "warp"], default="mujoco",
                    help="warp: also the MuJoCo Warp stepper and its raw rate, in the same run")
    ap.add_argument("--device", default="cpu", help="MuJoCo Warp's device (cpu, cuda)")
    args = ap.parse_args()
    if args.backend == "warp" and "warp" not in args.steppers:
        args.steppers = [*args.steppers, "warp"]
    with tempfile.TemporaryDirectory() as tmp:
        data = args.data or _dataset(Path(tmp))
        xml = args.humanoid or Path(tmp) / "humanoid.xml"
        if args.humanoid is None:
            build_humanoid(data, xml)
        hum = load_humanoid(xml)
        lib = load_library(hum, data, cache_dir=tmp)
    S = hum.substeps
    print(f"humanoid: {hum.model.nbody - 1} bodies, {hum.model.nu} hinges, timestep 1/{1 / hum.model.opt.timestep:.0f} s, "
          f"{S} substeps per {hum.control_hz:g} Hz control step; mujoco {mujoco.__version__}; "
          f"load average {os.getloadavg()[0]:.1f} on {os.cpu_count()} cores")
    pairs: list = []
    run_env(hum, lib, 64, args.steppers[0], min(args.seconds, 2.0), record=pairs)
    raw1 = max(raw_rate(hum.model, pairs, S, 1) for _ in range(args.repeats))
    raw2 = max(raw_rate(hum.model, pairs, S, 2) for _ in range(args.repeats))
    raw_cpu = max(raw_rate(hum.model, pairs, S, 1, cpu=True) for _ in range(args.repeats))
    print(f"raw mj_step rate on {sum(len(p[0]) for p in pairs)} recorded env states (best of {args.repeats}): "
          f"{raw1:,.0f} steps/s on 1 thread, {raw2:,.0f} steps/s on 2 threads, {raw_cpu:,.0f} per CPU second")
    print("ratio: env mj_step/s over the raw 2-thread rate measured just before. python: CPU ms per control step")
    print("of the calling thread outside physics. quiet: projected ratio on two idle cores, the physics at twice")
    print("the raw rate per CPU second plus that Python time, both in CPU time (see docs/sim.md)")
    print(f"{'stepper':>8} {'N':>4} {'ctrl steps/s':>13} {'env-steps/s':>12} {'mj_step/s':>10} {'raw 2-thr':>10} "
          f"{'ratio':>6} {'(range)':>12} {'python ms':>10} {'quiet':>6}")
    for stepper in args.steppers:
        for n in args.envs:
            runs = []
            for _ in range(args.repeats):
                raw = raw_rate(hum.model, pairs, S, 2)
                runs.append((*run_env(hum, lib, n, stepper, args.seconds, device=args.device), raw))
            ratios = [r * n * S / raw for r, _, raw in runs]
            rate, _, raw = max(runs)
            py_ms = 1e3 * min(py for _, py, _ in runs)
            phys_quiet = 1e3 * n * S / (2 * raw_cpu)
            print(f"{stepper:>8} {n:>4} {rate:>13,.1f} {rate * n:>12,.0f} {rate * n * S:>10,.0f} {raw:>10,.0f} "
                  f"{np.median(ratios):>6.2f} {f'{min(ratios):.2f}-{max(ratios):.2f}':>12} {py_ms:>10.2f} "
                  f"{f'{phys_quiet / (phys_quiet + py_ms):.2f}' if stepper != 'warp' else '-':>6}", flush=True)
    if "warp" in args.steppers:
        import warp as wp
        print(f"MuJoCo Warp on {args.device} (warp {wp.__version__}): raw mj_step/s timing only its step calls, "
              f"best of {args.repeats}; ratio: env mj_step/s over it")
        for n in args.envs:
            raw = max(raw_warp(hum, pairs, S, n, args.device, args.seconds) for _ in range(args.repeats))
            rate, _ = run_env(hum, lib, n, "warp", args.seconds, device=args.device)
            print(f"{'warp raw':>8} {n:>4} {raw:>10,.0f} mj_step/s; env {rate * n * S:,.0f} mj_step/s "
                  f"({rate * n:,.0f} env-steps/s), ratio {rate * n * S / raw:.2f}", flush=True)
    kinematics(hum, lib, args.repeats)
    print(f"load average after: {os.getloadavg()[0]:.1f}")


def kinematics(hum, lib, repeats: int) -> None:
    """The reference library's kinematics (``body_states``: body states and lowest points of every
    frame) against MuJoCo's three kinematics calls alone in the same per-frame loop, the floor any
    per-frame use of MjData has: their ratio is what the library adds to MuJoCo."""
    from motok.sim.kinematics import body_states

    q, v = lib.qpos, lib.qvel
    m, d = hum.model, mujoco.MjData(hum.model)

    def raw():
        for t in range(len(q)):
            d.qpos[:], d.qvel[:] = q[t], v[t]
            mujoco.mj_kinematics(m, d)
            mujoco.mj_comPos(m, d)
            mujoco.mj_comVel(m, d)

    def best(f):
        times = []
        for _ in range(repeats):
            t0 = time.perf_counter()
            f()
            times.append(time.perf_counter() - t0)
        return len(q) / min(times)

    r, b = best(raw), best(lambda: body_states(hum, q, v))
    print(f"library kinematics, {len(q)} frames (best of {repeats}): body_states {b:,.0f} frames/s, MuJoCo's "
          f"kinematics alone {r:,.0f} frames/s, ratio {b / r:.2f}")


if __name__ == "__main__":
    main()
