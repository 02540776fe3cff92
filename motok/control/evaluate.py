"""Evaluation of an imitation expert: every clip played from its first frame with the mean action
(``motok control expert eval``, and the ``eval_*`` metrics logged during training)."""

from __future__ import annotations

import json
from dataclasses import asdict, replace
from pathlib import Path

import numpy as np

from motok.artifacts import Provenance, command_line, hash_inputs
from motok.atomic import atomic_path
from motok.control.expert import ExpertConfig, _t, load_expert, select_clips
from motok.control.networks import ActorCritic
from motok.sim.env import HumanoidEnv
from motok.sim.humanoid import Humanoid
from motok.sim.reference import ReferenceLibrary


def eval_metrics(res: dict) -> dict:
    """The overall numbers of :func:`evaluate` as ``eval_*`` training metrics."""
    o = res["overall"]
    return {"eval_success": o["success_rate"], "eval_success_any_body": o["success_rate_any_body"],
            "eval_seconds": o["seconds_played"] / max(o["clips"], 1), "eval_mpjpe_mm": o["mpjpe_mm"],
            "eval_g_mpjpe_mm": o["g_mpjpe_mm"]}


def evaluate(cfg: ExpertConfig, hum: Humanoid, ac: ActorCritic, lib: ReferenceLibrary, render=None) -> dict:
    """Every clip from its first frame with the mean action, until the clip's end (success) or early
    termination (the env's criterion; ``success_rate_any_body`` also requires every single body to
    have stayed within the distance, the stricter test). Errors over the frames played: MPJPE
    (root-relative) and G-MPJPE (global) in mm, root velocity (mm/frame) and acceleration
    (mm/frame^2) errors from finite differences."""
    N = len(lib)
    env = HumanoidEnv(hum, lib, replace(cfg.env, num_envs=N, max_episode_seconds=1e9, seed=cfg.seed))
    obs, goal = env.reset(clips=np.arange(N), frames=0)
    g0 = lib.starts[:-1]
    pos, ref, qpos = [env.bodies.pos.copy()], [lib.body_pos[g0]], [env.qpos[0].copy()]
    alive, played = [np.ones(N, bool)], np.zeros(N, dtype=np.int64)
    active, success = np.ones(N, bool), np.zeros(N, bool)
    worst = np.zeros(N)  # largest single-body error over the frames played
    while active.any():
        _, a, _, _ = ac.act(_t(np.concatenate([obs, goal], 1)), deterministic=True)
        obs, goal, _, term, trunc, info = env.step(a.numpy())
        worst = np.where(active, np.maximum(worst, info["max_body_error"]), worst)
        g = np.minimum(lib.starts[env.clip] + env.frame, lib.starts[env.clip + 1] - 1)
        pos.append(env.bodies.pos.copy()), ref.append(lib.body_pos[g]), alive.append(active.copy())
        qpos.append(env.qpos[0].copy())
        played += active
        success |= active & trunc
        active &= ~(term | trunc)
    P, R, A = np.stack(pos, 1), np.stack(ref, 1), np.stack(alive, 1)
    per = {}
    for i, name in enumerate(lib.names):
        p, r = P[i, A[i]], R[i, A[i]]
        rel = (p - p[:, :1]) - (r - r[:, :1])
        v, vr = np.diff(p[:, 0], axis=0), np.diff(r[:, 0], axis=0)
        per[name] = {"success": bool(success[i]), "max_body_error_m": float(worst[i]),
                     "seconds": float(played[i] * env.dt),
                     "clip_seconds": float((lib.lengths[i] - 1 - env.cfg.goal_frames) * env.dt),
                     "mpjpe_mm": 1e3 * float(np.linalg.norm(rel, axis=-1).mean()),
                     "g_mpjpe_mm": 1e3 * float(np.linalg.norm(p - r, axis=-1).mean()),
                     "root_vel_err_mm": 1e3 * float(np.linalg.norm(v - vr, axis=-1).mean()) if len(v) else float("nan"),
                     "root_acc_err_mm": 1e3 * float(np.linalg.norm(np.diff(v - vr, axis=0), axis=-1).mean())
                     if len(v) > 1 else float("nan")}
    w = np.array([v["seconds"] for v in per.values()])
    strict = success & (worst <= env.cfg.termination_distance)
    overall = {"clips": N, "termination": f"{env.cfg.termination} body error > {env.cfg.termination_distance:g} m",
               "success_rate": float(success.mean()), "success_rate_any_body": float(strict.mean()),
               "seconds_played": float(w.sum())}
    for k in ("mpjpe_mm", "g_mpjpe_mm", "root_vel_err_mm", "root_acc_err_mm"):
        vals = np.array([v[k] for v in per.values()])
        ok = np.isfinite(vals)
        overall[k] = float(np.average(vals[ok], weights=np.maximum(w[ok], 1e-9))) if ok.any() else float("nan")
    out = {"overall": overall, "clips": per}
    if render is not None:
        from motok.sim.render import render_trajectory
        n = int(played[0]) + 1
        ghost = lib.qpos[lib.starts[0]:lib.starts[0] + n]
        path, backend = render_trajectory(hum, np.stack(qpos)[:n], render, lib.fps, ghost=ghost,
                                          title=f"expert {lib.names[0]}")
        out["video"] = f"{path} ({backend})"
    return out


def evaluate_run(run, *, data=None, clips: str | None = None, render=None, termination: str | None = None,
                 distance: float | None = None) -> dict:
    """``motok control expert eval``: :func:`evaluate` the checkpoint in ``run`` on its training
    clips (or the ``clips`` glob of ``data``) and write ``RUN/eval.json`` with the checkpoint it
    measured (iteration, samples, training wall time, MJCF hash) and provenance, so a number
    quoted from it can be traced to the weights and data that made it."""
    from motok.sim.reference import load_library

    run = Path(run)
    cfg, hum, ac, meta = load_expert(run)
    if termination is not None:
        cfg.env.termination = termination
    if distance is not None:
        cfg.env.termination_distance = distance
    src = data or meta["extra"].get("data")
    if not src:
        raise ValueError(f"{run} does not record its dataset: pass --data")
    names = select_clips(src, clips) if clips else meta["extra"]["clips"]
    res = evaluate(cfg, hum, ac, load_library(hum, src, control_hz=cfg.env.control_hz, clips=names), render)
    ex = meta["extra"]
    res["checkpoint"] = {"iteration": ex["iteration"], "samples": ex["samples"],
                         "wall_s": ex.get("last_metrics", {}).get("wall_s"), "mjcf_sha256": ex["mjcf_sha256"]}
    prov = Provenance(command=command_line(), config={"run": str(run), "clips": clips, "env": asdict(cfg.env)},
                      inputs=hash_inputs([src]))
    res = {"kind": "control-expert-eval", "schema_version": 1, **res, "provenance": json.loads(prov.to_json())}
    with atomic_path(run / "eval.json") as tmp:
        tmp.write_text(json.dumps(res, indent=2))
    return res
