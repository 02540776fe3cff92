"""Measurements the benchmarks share (a helper module beside them, not a benchmark: each script
runs with this folder first on ``sys.path`` and imports it as ``rates``)."""

from __future__ import annotations

import time

import numpy as np

import mujoco
from mujoco import rollout


def raw_rate(m, pairs, substeps: int, nthread: int = 2, repeats: int = 1, cpu: bool = False) -> float:
    """Best-of-``repeats`` mj_step/s of ``mujoco.rollout`` in C++ (no Python per step) on model
    ``m`` stepping the recorded ``(qpos, qvel, ctrl)`` pairs, each control held for ``substeps``;
    with ``cpu`` (one thread, on the caller's) per second of the thread's CPU time instead of wall
    time. One warm-up rollout first, so the pool's threads are up before the clock starts."""
    d = mujoco.MjData(m)
    spec = mujoco.mjtState.mjSTATE_FULLPHYSICS
    qpos, qvel, ctrl = (np.concatenate([p[i] for p in pairs]) for i in range(3))
    state = np.zeros((len(qpos), mujoco.mj_stateSize(m, spec)))
    for i in range(len(qpos)):
        d.qpos[:], d.qvel[:] = qpos[i], qvel[i]
        mujoco.mj_getState(m, d, state[i], spec)
    control = np.ascontiguousarray(np.repeat(ctrl[:, None], substeps, 1))
    out = np.zeros((len(qpos), substeps, state.shape[1]))
    datas = [mujoco.MjData(m) for _ in range(nthread)]
    clock = time.thread_time if cpu else time.perf_counter
    best = 0.0
    with rollout.Rollout(nthread=nthread if nthread > 1 else 0) as pool:
        pool.rollout([m] * len(qpos), datas, state, control, nstep=substeps, state=out)  # warm-up
        for _ in range(repeats):
            t0 = clock()
            pool.rollout([m] * len(qpos), datas, state, control, nstep=substeps, state=out)
            best = max(best, len(qpos) * substeps / (clock() - t0))
    return best


def steps_per_s(mdp, actions, seconds: float) -> float:
    """Env-steps per second of ``mdp`` (a ``TaskEnv``) under ``actions(rng) -> (N, ...)``, with resets."""
    mdp.reset()
    rng = np.random.default_rng(0)
    steps, t0 = 0, time.perf_counter()
    while time.perf_counter() - t0 < seconds:
        _, _, _, term, trunc, _ = mdp.step(actions(rng))
        done = term | trunc
        if done.any():
            mdp.reset(np.flatnonzero(done))
        steps += mdp.num_envs
    return steps / (time.perf_counter() - t0)


def train_rate(tr, iterations: int) -> dict:
    """A control trainer's samples/s over ``iterations`` steps after one warm-up step (first-call
    allocations), and its mean rollout and update seconds per iteration."""
    tr.step()
    rows = [tr.step() for _ in range(iterations)]
    wall = sum(r["rollout_s"] + r["update_s"] for r in rows)
    return {"samples_per_s": tr.samples_per_iteration * iterations / wall,
            "rollout_s": float(np.mean([r["rollout_s"] for r in rows])),
            "update_s": float(np.mean([r["update_s"] for r in rows]))}
