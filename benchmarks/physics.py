"""What one physics step of the humanoid costs under each contact and solver option, and what the
options do to the physics.

The reference ("today") is the build before the options existed: every geom pair collides,
Newton with 20/10 iterations, MuJoCo's automatic (dense, at nv = 43) Jacobian, constraint islands
on. PD tracking (targets = next reference frame) of walk, run, turn and arm-raising/waving clips
of Bandai-Namco set 2, with fallen environments restarted at random reference frames, plus 3 s
without restarts (the states after falls), is recorded once with today's model; every option
then steps exactly those (state, control) pairs with ``mujoco.rollout`` for one control step
(4 substeps):

* ``cpu/s``: mj_step per second of CPU time on one thread (load on other cores barely moves it);
  ``ratio``: against today's, paired within each round and the median over ``--repeats`` rounds;
  ``2-thr/s``: wall-clock rate on 2 threads (best round), only meaningful on a quiet machine;
* contacts per step (foot-floor, other body-floor, self), constraint rows, Newton iterations
  (mean, max, % of steps at the cap), and the candidate geom pairs a GPU (MuJoCo Warp NXN)
  broadphase would test;
* quality: the rest pose under PD targets 0 after 5 s (standing?, root height ratio); plain PD
  tracking from frame 0 (``motok.control.expert.baselines.pd_track``: mean survival s and Eq. 10
  reward) of the 24 walk_normal clips and of the 42 others; divergence from today's physics: mean
  body-position difference (mm, legs + root / arms) after 10 and 30 control steps of PD tracking
  from 128 random reference states.

    .venv/bin/python benchmarks/physics.py [--data runs/bandai2.h5] [--repeats 4] [--more]
    .venv/bin/python benchmarks/physics.py --feet [--rates 30,60]

Takes about 70 s on 2 cores (``--more`` adds the elliptic cone and the CG solver).

A lever can change what a second of motion costs without changing a step's cost: ``--feet`` also
prints each world's CPU milliseconds of physics per simulated second (``ms/sim-s``: the timestep
sets how many mj_step a second takes), and for each control rate of ``--rates`` the cost of a
second of motion through the whole control step: the imitation MDP (physics, Eq. 7, Eq. 9,
Eq. 10, resets) and a forward pass of the expert recipe's policy, for PD tracking of the 24 walks
with restarts. At 60 Hz a second holds twice the control steps, each of half the substeps: the
physics per second stays, while everything done per control step (observation, goal, reward,
policy, and in training the PPO update per sample) doubles.
"""

from __future__ import annotations

import argparse
import dataclasses
import os
import tempfile
import time
from pathlib import Path

import numpy as np

import mujoco
from mujoco import rollout

from motok.control.expert.baselines import pd_track
from motok.control.expert.train import imitation_mdp
from motok.control.mdp.actions import ActionConfig
from motok.control.mdp.resets import reference_state
from motok.control.tasks.imitation import ImitationTaskConfig
from motok.data.dataset import MotionFile
from motok.sim.env import HumanoidEnv, SimConfig
from motok.sim.humanoid import HumanoidConfig, humanoid_from_model
from motok.sim.mjcf import humanoid_xml, measure_humanoid
from motok.sim.reference import load_library

TODAY = dict(self_collision="all", solver_iterations=20, ls_iterations=10, jacobian="auto", islands=True)
DEFAULT = {f.name: f.default for f in dataclasses.fields(HumanoidConfig) if f.name in TODAY}
VARIANTS = {
    "today (all, 20/10, auto, islands)": TODAY,
    "iterations 10/5": {**TODAY, "solver_iterations": 10, "ls_iterations": 5},
    "iterations 6/3": {**TODAY, "solver_iterations": 6, "ls_iterations": 3},
    "jacobian sparse": {**TODAY, "jacobian": "sparse"},
    "islands off": {**TODAY, "islands": False},
    "self_collision data": {**TODAY, "self_collision": "data"},
    "self_collision legs": {**TODAY, "self_collision": "legs"},
    "self_collision none": {**TODAY, "self_collision": "none"},
    "default (data, 10/5, sparse, no islands)": DEFAULT,
    "default + legs": {**DEFAULT, "self_collision": "legs"},
    "default + none": {**DEFAULT, "self_collision": "none"},
}
# --feet: the contact levers against sliding feet (docs/sim.md "Feet"), against today's default.
FEET = {"default": DEFAULT, "noslip 10": {**DEFAULT, "noslip_iterations": 10},
        "elliptic, impratio 3": {**DEFAULT, "cone": "elliptic", "impratio": 3.0},
        "PD damping x2 (derivative_time 0.2)": {**DEFAULT, "derivative_time": 0.2},
        "ankles at half stiffness": {**DEFAULT, "ankle_stiffness_scale": 0.5}}
MORE = {"today + elliptic cone": ("cone", mujoco.mjtCone.mjCONE_ELLIPTIC),
        "today + CG solver": ("solver", mujoco.mjtSolver.mjSOL_CG)}
GROUPS = {"walk": ["walk_normal"], "other": ["walk_elderly:3", "walk_exhausted:3", "walk_active:3", "run_normal:8",
                                             "run_active:4", "walk-turn-left_normal:4", "walk-turn-right_normal:4",
                                             "raise-up-both-hands_normal:4", "raise-up-both-hands_active:2",
                                             "wave-both-hands_normal:3", "raise-up-left-hand_normal:2",
                                             "wave-right-hand_active:2"]}
SUBSTEPS = 4


def _clips(data: Path) -> dict[str, list[str]]:
    with MotionFile(data) as mf:
        names = list(mf.names)
    out = {}
    for g, specs in GROUPS.items():
        out[g] = []
        for spec in specs:
            kind, _, n = spec.partition(":")
            out[g] += [x for x in names if x.startswith(f"dataset-2_{kind}_")][:int(n) if n else None]
    return out


def record(hum, lib, clips: list[str]) -> tuple[np.ndarray, ...]:
    """(qpos, qvel, ctrl) of PD tracking with restarts (5 s) and without (3 s, after falls)."""
    out = []
    for restart, steps in ((True, 150), (False, 90)):
        mdp = imitation_mdp(hum, lib, SimConfig(num_envs=len(clips), nthread=2),
                            ImitationTaskConfig(early_termination=restart), ActionConfig("current"), 0)
        env, task = mdp.env, mdp.task
        mdp.reset(clips=np.array([lib.index(c) for c in clips]), frames=0)
        for _ in range(steps):
            target = np.clip(task.next_reference()[0][:, env.hinge_adr], env.ctrl_low, env.ctrl_high)
            out.append((env.qpos.copy(), env.qvel.copy(), target))
            _, _, _, term, trunc, _ = mdp.step(target - env.qpos[:, env.hinge_adr])
            done = np.flatnonzero(term | trunc)
            if restart and len(done):
                mdp.reset(done)
    return tuple(np.concatenate([o[k] for o in out]) for k in range(3))


def _states(m, qpos, qvel) -> np.ndarray:
    d, spec = mujoco.MjData(m), mujoco.mjtState.mjSTATE_FULLPHYSICS
    st = np.zeros((len(qpos), mujoco.mj_stateSize(m, spec)))
    for i in range(len(qpos)):
        d.qpos[:], d.qvel[:] = qpos[i], qvel[i]
        mujoco.mj_getState(m, d, st[i], spec)
    return st


def rate(m, pool, datas, state, control, cpu: bool) -> float:
    clock = time.thread_time if cpu else time.perf_counter
    t0 = clock()
    pool.rollout([m] * len(state), datas, state, control, nstep=SUBSTEPS, skip_checks=True)
    return len(state) * SUBSTEPS / (clock() - t0)


def contact_stats(hum, qpos, qvel, ctrl) -> dict:
    m = hum.model
    d = mujoco.MjData(m)
    sk = hum.skeleton
    feet = set(hum.body_ids[[*sk.feet_left, *sk.feet_right]].tolist())
    kinds, nefc, niter, pairs = np.zeros(3), 0, [], {}
    for i in range(len(qpos)):
        d.qpos[:], d.qvel[:], d.ctrl[:] = qpos[i], qvel[i], ctrl[i]
        for _ in range(SUBSTEPS):
            mujoco.mj_step(m, d)
            nefc += d.nefc
            niter.append(int(d.solver_niter[0]))
            for c in d.contact[:d.ncon]:
                b = sorted((int(m.geom_bodyid[c.geom[0]]), int(m.geom_bodyid[c.geom[1]])))
                kinds[2 if b[0] else (0 if b[1] in feet else 1)] += 1
                if b[0]:
                    pairs[tuple(b)] = pairs.get(tuple(b), 0) + 1
    n, niter = len(qpos) * SUBSTEPS, np.array(niter)
    name = lambda b: mujoco.mj_id2name(m, mujoco.mjtObj.mjOBJ_BODY, b)
    top = sorted(pairs.items(), key=lambda kv: -kv[1])[:4]
    return {"foot": kinds[0] / n, "body": kinds[1] / n, "self": kinds[2] / n, "nefc": nefc / n, "niter": niter.mean(),
            "niter_max": niter.max(), "capped": 100 * (niter >= m.opt.iterations).mean(),
            "pairs": ", ".join(f"{name(a)}-{name(b)} {k / n:.2f}" for (a, b), k in top), "nxn": nxn_pairs(m)}


def nxn_pairs(m) -> int:
    """Geom pairs MuJoCo Warp's all-pairs broadphase keeps: filter bits, not same/parent body, not excluded."""
    g1, g2 = np.triu_indices(m.ngeom, 1)
    b1, b2 = m.geom_bodyid[g1], m.geom_bodyid[g2]
    bits = ((m.geom_contype[g1] & m.geom_conaffinity[g2]) | (m.geom_contype[g2] & m.geom_conaffinity[g1])) != 0
    parent = ((m.body_parentid[b1] == b2) | (m.body_parentid[b2] == b1)) & (b1 > 0) & (b2 > 0)
    excluded = np.isin((np.minimum(b1, b2) << 16) + np.maximum(b1, b2), m.exclude_signature)
    return int((bits & (b1 != b2) & ~parent & ~excluded).sum())


def standing(hum) -> tuple[bool, float]:
    m = hum.model
    d = mujoco.MjData(m)
    z0, head = d.qpos[2], hum.body_ids[hum.skeleton.head]
    for _ in range(int(round(5.0 / m.opt.timestep))):
        mujoco.mj_step(m, d)
    ok = (d.qpos[2] > 0.95 * z0 and d.xpos[head, 2] > 1.2 and np.linalg.norm(d.qpos[:2]) < 0.1
          and np.abs(d.qvel).max() < 0.5)  # as tests/test_sim.py
    return bool(ok), float(d.qpos[2] / z0)


def tracking_positions(hum, lib, starts, steps: int = 30) -> np.ndarray:
    """Body positions (N, steps, J, 3) of PD tracking from the reference states ``starts``."""
    clips, frames = starts
    env = HumanoidEnv(hum, SimConfig(num_envs=len(clips), nthread=2))
    env.set_state(np.arange(len(clips)), *reference_state(lib, clips, frames))
    out = []
    for t in range(steps):
        env.step(lib.qpos[lib.frame_index(clips, frames + t + 1)][:, env.hinge_adr])
        out.append(env.bodies.pos.copy())
    return np.stack(out, 1)


def control_rate_cost(hum, data: Path, clips: list[str], hz: float, seconds: float = 4.0) -> dict:
    """CPU seconds per simulated second of PD tracking through the imitation MDP at ``hz``, with a
    forward pass of the expert recipe's policy every control step (its actions unused: PD tracking
    keeps the states the same whatever the network's weights), fallen environments restarted."""
    import torch

    from motok.config import load_config
    from motok.control.expert.model import ExpertConfig, build_actor_critic

    net = load_config(ExpertConfig, Path(__file__).parents[1] / "recipes/control/expert.yaml").net
    with tempfile.TemporaryDirectory() as tmp:
        lib = load_library(hum, data, control_hz=hz, clips=clips, cache_dir=tmp)
    mdp = imitation_mdp(hum, lib, SimConfig(num_envs=len(clips), nthread=1, control_hz=hz), ImitationTaskConfig(),
                        ActionConfig("reference"), 0)
    ac = build_actor_critic(net, mdp.obs_dim, mdp.goal_dim, mdp.action_dim)
    obs, goal = mdp.reset()
    steps = int(round(seconds * hz))
    zero = np.zeros((mdp.num_envs, mdp.action_dim))
    t0 = time.process_time()
    with torch.no_grad():
        for _ in range(steps):
            ac.act(torch.as_tensor(np.concatenate([obs, goal], 1), dtype=torch.float32))
            obs, goal, _, term, trunc, _ = mdp.step(zero)
            obs, goal = mdp.restart_done(term | trunc, obs, goal)
    cpu = time.process_time() - t0
    return {"hz": hz, "substeps": mdp.env.substeps, "steps_per_s": hz,
            "cpu_ms_per_sim_s": 1e3 * cpu / (seconds * mdp.num_envs)}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--data", type=Path, default=Path("runs/bandai2.h5"), help="Bandai-Namco set 2 motion-dataset")
    ap.add_argument("--repeats", type=int, default=4, help="rounds of rate measurements")
    ap.add_argument("--more", action="store_true", help="also the elliptic cone and the CG solver")
    ap.add_argument("--feet", action="store_true", help="the contact levers against sliding feet, against the default")
    ap.add_argument("--rates", default="30,60", help="with --feet: the control rates (Hz) whose cost per simulated "
                    "second of motion to measure")
    args = ap.parse_args()
    t_start = time.perf_counter()
    body = measure_humanoid(args.data)
    hums = {k: humanoid_from_model(mujoco.MjModel.from_xml_string(humanoid_xml(body, HumanoidConfig(**v))[0]))
            for k, v in (FEET if args.feet else VARIANTS).items()}
    base = next(iter(hums))
    if args.more:  # runtime options of the solver, not builder options
        for k, (field, value) in MORE.items():
            hums[k] = humanoid_from_model(hums[base].model.__copy__())
            setattr(hums[k].model.opt, field, value)
    groups = _clips(args.data)
    every = [c for g in groups.values() for c in g]
    with tempfile.TemporaryDirectory() as tmp:
        lib = load_library(hums[base], args.data, clips=every, cache_dir=tmp)  # kinematics: the same for every option
    qpos, qvel, ctrl = record(hums[base], lib, every)
    sel = np.arange(0, len(qpos), 3)
    control = np.ascontiguousarray(np.repeat(ctrl[sel, None], SUBSTEPS, 1))
    states = {k: _states(h.model, qpos[sel], qvel[sel]) for k, h in hums.items()}
    print(f"mujoco {mujoco.__version__}; {len(sel)} recorded states x {SUBSTEPS} substeps from PD tracking of "
          f"{len(every)} clips (with falls); load average {os.getloadavg()[0]:.1f} on {os.cpu_count()} cores",
          flush=True)

    cpu = {k: [] for k in hums}
    wall = {k: [] for k in hums}
    with rollout.Rollout(nthread=0) as one, rollout.Rollout(nthread=2) as two:
        datas1 = {k: [mujoco.MjData(h.model)] for k, h in hums.items()}
        datas2 = {k: [mujoco.MjData(h.model) for _ in range(2)] for k, h in hums.items()}
        for k, h in hums.items():  # warm-up
            rate(h.model, one, datas1[k], states[k][:200], control[:200], True)
        for _ in range(args.repeats):
            for k, h in hums.items():
                cpu[k].append(rate(h.model, one, datas1[k], states[k], control, True))
                wall[k].append(rate(h.model, two, datas2[k], states[k], control, False))

    rng = np.random.default_rng(0)
    starts = lib.sample(128, rng, horizon=32)
    names = hums[base].layout.names
    legs = [i for i, n in enumerate(names) if i == 0 or any(p in n for p in ("Leg", "Foot", "Toes"))]
    arms = [i for i, n in enumerate(names) if "Arm" in n or "Hand" in n]
    ref_pos = tracking_positions(hums[base], lib, starts)
    per_s = {k: 1e3 / (np.median(cpu[k]) * h.model.opt.timestep) for k, h in hums.items()}  # ms/sim-s
    if args.feet:
        print(f"{'world':42s} {'ms/sim-s':>8s} (CPU ms of physics per simulated second, one thread)")
        for k in hums:
            print(f"{k:42s} {per_s[k]:8.1f}")
        rates = [control_rate_cost(hums[base], args.data, groups["walk"], float(r)) for r in args.rates.split(",")]
        print(f"{'control rate':>12s} {'substeps':>8s} {'steps/sim-s':>11s} {'CPU ms per env per sim-s':>24s} "
              f"{'ratio':>5s}   (imitation MDP + policy forward, {len(groups['walk'])} envs)")
        for r in rates:
            print(f"{r['hz']:10.0f}Hz {r['substeps']:8d} {r['steps_per_s']:11.0f} {r['cpu_ms_per_sim_s']:24.1f} "
                  f"{r['cpu_ms_per_sim_s'] / rates[0]['cpu_ms_per_sim_s']:5.2f}", flush=True)
    print(f"{'option':42s} {'cpu/s':>7s} {'ratio':>5s} {'2-thr/s':>8s} | {'foot':>4s} {'body':>4s} {'self':>4s} "
          f"{'rows':>4s} {'iter':>4s} {'max':>3s} {'cap%':>4s} {'nxn':>3s} | {'stand':>8s} {'walk s':>6s} {'rew':>5s} "
          f"{'other s':>7s} {'rew':>5s} | {'legs@10':>7s} {'@30':>5s} {'arms@10':>7s} {'@30':>5s} mm")
    for k, h in hums.items():
        ratio = np.median(np.array(cpu[k]) / np.array(cpu[base]))
        st = contact_stats(h, qpos[::12], qvel[::12], ctrl[::12])
        ok, zr = standing(h)
        walk = pd_track(h, lib, groups["walk"], seconds=4.0)
        other = pd_track(h, lib, groups["other"], seconds=4.0)
        e = np.linalg.norm(tracking_positions(h, lib, starts) - ref_pos, axis=-1) * 1e3
        print(f"{k:42s} {np.median(cpu[k]):7,.0f} {ratio:5.2f} {max(wall[k]):8,.0f} | {st['foot']:4.2f} "
              f"{st['body']:4.2f} {st['self']:4.2f} {st['nefc']:4.1f} {st['niter']:4.2f} {st['niter_max']:3d} "
              f"{st['capped']:4.1f} {st['nxn']:3d} | {('yes' if ok else 'NO') + f' {zr:.2f}':>8s} "
              f"{walk['survival_s'].mean():6.3f} {walk['mean_reward'].mean():5.3f} {other['survival_s'].mean():7.3f} "
              f"{other['mean_reward'].mean():5.3f} | {e[:, 9][..., legs].mean():7.1f} "
              f"{e[:, -1][..., legs].mean():5.1f} {e[:, 9][..., arms].mean():7.1f} {e[:, -1][..., arms].mean():5.1f}",
              flush=True)
        if st["pairs"]:
            print(f"{'':44s}self pairs per step: {st['pairs']}")
    print(f"load average after: {os.getloadavg()[0]:.1f}; {time.perf_counter() - t_start:.0f} s")


if __name__ == "__main__":
    main()
