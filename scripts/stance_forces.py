"""Contact forces under the sliding soles of one controller (docs/history.md, "Feet").

``motok.sim.soles`` finds the simulated soles sliding (about 60 cm/s while within 1 cm of the
floor). That measure judges contact by height; this one asks MuJoCo. The clips are played as
``control track`` plays them (``motok.control.tasks.imitation.play``, the rollout stepper, which starts
every control step from a zero warm start), every control step's state and PD targets are
recorded, and each step is replayed substep by substep in one ``MjData``; at every substep each
contact between a foot or toe geom and the floor gives its normal force, its friction force and
the slip velocity of the geom's material point at the contact
(``motok.sim.soles.floor_contacts``). The replay is checked against the recorded next state.

Printed: the share of contact substeps and of the feet's normal load by slip speed, the
load-weighted slip (the slip of the sole that bears the weight), the friction use |F_t| / (mu F_n)
of sliding and of sticking contacts, the feet's load against the body weight, the penetration,
and how long each foot or toe box stays in contact without a break (a planted stance of a walk
lasts about 0.6 s). And how much the PD targets move from one control step to the next against
how much the simulated joints and the reference's joints move (rad per step, root mean square, by
joint group): targets that jump far more than either are a controller chattering.

    python scripts/stance_forces.py --expert runs/expert_set2 -d runs/bandai2.h5 --split test \\
        --clips 'dataset-2_walk*' --max-clips 24
"""

from __future__ import annotations

import json
from dataclasses import replace

import mujoco
import numpy as np

from motok.control.tasks.imitation import play
from motok.control.priors.load import load_controller
from motok.control.track import place_on_floor
from motok.data.dataset import select_clips
from motok.sim.reference import load_library
from motok.sim.soles import BOX, contact_runs, floor_contacts
from sole_slip_variants import apply, clip_parser  # this folder's: scripts/ is the first path entry

SPEED_BINS = (0.0, 0.01, 0.05, 0.2, 0.5, np.inf)  # m/s


class Recorder:
    """Wraps a stepper: keeps every environment's (qpos, qvel) before each control step and the
    controls of its substeps as the stepper applied them (held or ramped: the last is the step's
    PD target either way)."""

    def __init__(self, stepper):
        self.inner, self.steps = stepper, []

    def __getattr__(self, name):
        return getattr(self.inner, name)

    def step(self, ctrl):
        qpos, qvel = self.inner.qpos.copy(), self.inner.qvel.copy()
        failed = self.inner.step(ctrl)
        self.steps.append((qpos, qvel, self.inner._ctrl.copy()))
        return failed


def median(x: np.ndarray) -> float:
    return float(np.median(x)) if len(x) else float("nan")  # a few clips may have no sticking contact at all


def main() -> None:
    ap = clip_parser(__doc__)
    ap.add_argument("--max-clips", type=int, default=24)
    ap.add_argument("--world", default="base", help="a change to the world, zero-shot (scripts/sole_slip_variants.py)")
    a = ap.parse_args()
    ctl = load_controller(expert=a.expert, prior=a.prior)
    cfg, hum, ac = ctl.cfg, ctl.humanoid, ctl.policy
    apply(ctl, a.world)
    names = select_clips(a.data, a.clips, a.split)[:a.max_clips]
    lib, _ = place_on_floor(load_library(hum, a.data, control_hz=hum.control_hz, clips=names, use_cache=False))
    sim = replace(cfg.env, stepper="rollout", nthread=1)
    task = replace(cfg.task, max_episode_seconds=1e9)

    import motok.control.tasks.imitation as ev
    made = []
    real = ev.HumanoidEnv

    def env_with_recorder(h, c):
        env = real(h, c)
        env.stepper = Recorder(env.stepper)
        made.append(env)
        return env

    ev.HumanoidEnv = env_with_recorder
    try:
        out = play(hum, ac, lib, np.arange(len(lib)), sim, task, cfg.action)
    finally:
        ev.HumanoidEnv = real
    if not made:
        raise SystemExit("play() no longer builds its environment through motok.control.tasks.imitation.HumanoidEnv: "
                         "nothing was recorded; update this script")
    env = made[0]
    m = hum.model
    d = mujoco.MjData(m)
    feet = np.zeros(m.ngeom, bool)
    feet[(m.geom_type == BOX) & (m.geom_bodyid > 0)] = True
    weight = float(m.body_subtreemass[1] * -m.opt.gravity[2])
    foot_geoms = np.flatnonzero(feet)
    rows, load, replay_err, substeps = [], [], 0.0, 0
    touching = {}  # env -> per substep, which foot geoms touch the floor
    alive = out["alive"]
    steps = env.stepper.steps
    for t, (qpos, qvel, sub) in enumerate(steps):
        for k in np.flatnonzero(alive[:, t + 1] & alive[:, t]):
            d.qpos[:], d.qvel[:], d.ctrl[:] = qpos[k], qvel[k], sub[k, 0]
            d.qacc_warmstart[:] = 0
            mujoco.mj_forward(m, d)
            for s in range(env.substeps):
                d.ctrl[:] = sub[k, s]
                mujoco.mj_step(m, d)
                cs = floor_contacts(m, d, feet)
                rows.append(cs)
                load.append(cs[:, 0].sum())
                touching.setdefault(k, []).append(np.isin(foot_geoms, cs[:, 4]))
                substeps += 1
            if t + 1 < len(steps):
                replay_err = max(replay_err, float(np.abs(d.qpos - steps[t + 1][0][k]).max()))
    r = np.concatenate(rows)
    fn, ft, v, dist, g = r.T
    mu = m.geom_friction[g.astype(int), 0]  # the floor's and the feet's are equal in this humanoid
    runs = np.concatenate([contact_runs(np.asarray(f)) for f in touching.values()]) * m.opt.timestep
    idx = np.digitize(v, SPEED_BINS[1:-1])
    bins = [f"{SPEED_BINS[i] * 100:g}-{SPEED_BINS[i + 1] * 100:g} cm/s" for i in range(len(SPEED_BINS) - 1)]
    use = ft / np.maximum(mu * fn, 1e-9)
    report = {
        "world": a.world, "clips": len(lib), "tracked_to_end": float(out["success"].mean()), "replay_max_qpos_err": replay_err,
        "contact_substeps": int(len(r)), "substeps": substeps,
        "share_of_contacts": {b: float((idx == i).mean()) for i, b in enumerate(bins)},
        "share_of_load": {b: float(fn[idx == i].sum() / fn.sum()) for i, b in enumerate(bins)},
        "slip_cm_s": {"median": float(100 * np.median(v)), "mean": float(100 * v.mean()),
                      "load_weighted": float(100 * (fn * v).sum() / fn.sum())},
        "friction_use": {"sliding_over_5cm_s": median(use[v > 0.05]), "sticking_under_1cm_s": median(use[v < 0.01])},
        "feet_load_over_weight": {"mean": float(np.mean(load) / weight), "p95": float(np.percentile(load, 95) / weight),
                                  "share_of_substeps_unloaded": float(np.mean(np.asarray(load) < 1e-6))},
        "penetration_mm": {"median": float(-1000 * np.median(dist)), "p95": float(-1000 * np.percentile(dist, 5))},
        "contact_duration_ms": {"median": float(1000 * np.median(runs)), "mean": float(1000 * runs.mean()),
                                "share_of_contact_time_in_runs_under_50ms": float(runs[runs < 0.05].sum() / runs.sum())},
    }
    report["step_rms_rad"] = chatter(m, lib, steps, alive)
    print(json.dumps(report, indent=1))


def chatter(m, lib, steps, alive) -> dict:
    """Root-mean-square change per control step of the PD targets, the simulated joints and the
    reference's joints, by joint group (over the steps where the clip is still tracked)."""
    names = [mujoco.mj_id2name(m, mujoco.mjtObj.mjOBJ_ACTUATOR, i) for i in range(m.nu)]
    driven = m.jnt_qposadr[m.actuator_trnid[:, 0]]
    target = np.stack([s[2][:, -1] for s in steps])  # (T, N, nu): the last substep's control
    q = np.stack([s[0] for s in steps])[..., driven]
    T = len(steps)
    ok = (alive[:, :T - 1] & alive[:, 1:T] & alive[:, 2:T + 1]).T  # (T-1, N): both steps still tracked
    d_target, d_q = np.diff(target, axis=0)[ok], np.diff(q, axis=0)[ok]
    inside = np.ones(len(lib.qpos) - 1, bool)
    inside[lib.starts[1:-1] - 1] = False  # no step across two clips
    d_ref = np.diff(lib.qpos[:, driven], axis=0)[inside]
    groups = {"ankles": ("Foot_",), "knees": ("LowerLeg_",), "hips": ("UpperLeg_",),
              "trunk": ("Spine", "Chest", "Neck"), "arms": ("Shoulder", "UpperArm", "LowerArm")}
    out = {}
    for g, prefixes in {"all": ("",), **groups}.items():
        cols = [i for i, n in enumerate(names) if n.startswith(prefixes)]
        if cols:
            out[g] = {k: float(np.sqrt(np.mean(v[:, cols] ** 2)))
                      for k, v in (("targets", d_target), ("simulated", d_q), ("reference", d_ref))}
    return out


if __name__ == "__main__":
    main()
