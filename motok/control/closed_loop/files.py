"""What the closed loop writes (:mod:`motok.control.closed_loop.loop`): the simulated motion, the
reference it was given plan after plan, every plan, a video of the first motion with the prompt of
each moment drawn on it, and the report's numbers per motion and overall.

Every motion file goes through the feature pipeline (``simulated_clip``), so the three hold clips
every motok reader takes, each in its own canonical frame (the pipeline puts a clip's first frame
at the origin, facing +Z); the world placement of each plan is in its labels (``sim_root_m``,
``sim_heading_deg``: where the character was when it was made).
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from motok.artifacts import Provenance, command_line
from motok.control.closed_loop.replan import Plan
from motok.control.tasks.imitation import clip_slip, slip_report
from motok.data.dataset import TRACKED_TO_END, write_motion
from motok.eval.metrics import mpjpe
from motok.sim.humanoid import to_mj
from motok.sim.reference import simulated_clip
from motok.sim.soles import SlipSums


REPORT_KIND = "closed-loop"


def report_path(out) -> Path:
    """``walk_sim.h5`` -> ``walk_sim.closed-loop.json``: the report."""
    out = Path(out)
    return out.with_name(out.stem + ".closed-loop.json")


def plans_path(out) -> Path:
    """``walk_sim.h5`` -> ``walk_sim.plans.h5``: every plan of every motion."""
    out = Path(out)
    return out.with_name(f"{out.stem}.plans{out.suffix}")


def executed(plans: list[Plan], rate: int) -> np.ndarray:
    """The reference the controller was given ``(T, J, 3)``: each plan until the next was made,
    the last one whole."""
    parts = [p.joints[:(q.start - p.start) * rate] for p, q in zip(plans, plans[1:])]
    return np.concatenate(parts + [plans[-1].joints])


def replan_records(plans: list[Plan], token_seconds: float) -> list[dict]:
    """The re-plans of one motion (its plans after the first), as the report lists them."""
    return [{"at_s": round(p.start * token_seconds, 4), "token": p.start, "reason": p.reason, "text": p.text,
             "context": p.context, "codes": p.codes, **p.info} for p in plans[1:]]


def titles(plans: list[Plan], text_at, spt: int, hz: float, steps: int) -> list[str]:
    """One title per control step: the time, the prompt of that moment, and ``[re-plan]`` for a
    token's worth of steps after each re-plan."""
    starts = [p.start * spt for p in plans[1:]]
    return [f"{t / hz:4.1f} s  {text_at(t // spt)}" + ("   [re-plan]" if any(0 <= t - s < spt for s in starts) else "")
            for t in range(steps)]


def write_outputs(out, batches, planner, controller, config: dict, *, render=None, bvh=None) -> dict:
    """Write ``out``, ``OUT.kinematic.h5``, ``OUT.plans.h5``, the video and the BVHs of the run's
    ``batches`` (:func:`motok.control.closed_loop.loop.run`); returns the report (summary and ``per_clip``)."""
    from motok.control.text_to_physics import export_bvhs, kinematic_path

    clock, cfg = planner.clock, controller.cfg
    hz, fps, rate, spt, K = clock.control_hz, clock.fps, clock.rate, clock.steps_per_token, cfg.task.goal_frames
    tok_s = clock.token_seconds
    sk, offsets, legacy, source = planner.skeleton, planner.offsets, planner.legacy, str(config["gpt"])
    found = {}  # row index -> (record, simulated clip or None, kinematic clip, plan clips)
    slip_sim, slip_ref, video = SlipSums(), SlipSums(), None
    for loop, res, ids in batches:
        for k, i in enumerate(ids):
            row, plans = loop.rows[k], loop.plans[k]
            alive = res["alive"][k]
            p, r = res["pos"][k, alive], res["ref"][k, alive]
            frames = int(np.floor((row.tokens * rate - 1) * hz / fps + 1e-9)) + 1
            to_end, played = bool(res["success"][k]), float(res["played"][k] / hz)
            rec = {"text": row.prompts[0][1], **({"prompts": row.labels["prompts"]} if "prompts" in row.labels else {}),
                   "tokens": row.tokens, "tracked_to_end": to_end, "seconds": played,
                   "clip_seconds": float((frames - 1 - K) / hz), "failed_at_s": None if to_end else played,
                   "mpjpe_mm": float(mpjpe(p, r).mean()), "g_mpjpe_mm": float(mpjpe(p, r, root_relative=False).mean())}
            s_sim, s_ref = clip_slip(res, k)
            slip_sim.add(s_sim), slip_ref.add(s_ref)
            rec.update(sole_slip_cm_s=s_sim.result()["sole_slip_cm_s"],
                       reference_sole_slip_cm_s=s_ref.result()["sole_slip_cm_s"],
                       plans=len(plans), replans=replan_records(plans, tok_s))
            at = [x["at_s"] for x in rec["replans"]]
            labels = {**row.labels, TRACKED_TO_END: to_end, "tracked_seconds": round(played, 4), "replans_s": at}
            sim = None
            if len(p) * fps / hz >= 2:
                sim = simulated_clip(row.name, p, hz, fps, sk, offsets, legacy, source, split=row.split, labels=labels,
                                     captions=row.captions)
            else:
                rec["error"] = "failed before two frames at the motion's rate were simulated: nothing written"
            kin = simulated_clip(row.name, to_mj(executed(plans, rate)), fps, fps, sk, offsets, legacy, source,
                                 split=row.split, labels={**row.labels, "replans_s": at}, captions=row.captions)
            pcs = [simulated_clip(f"{row.name}.plan{n:02d}", to_mj(pl.joints), fps, fps, sk, offsets, legacy, source,
                                  labels={"clip": row.name, "plan": n, "start_s": round(pl.start * tok_s, 4),
                                          "reason": pl.reason, "text": pl.text, "context": pl.context,
                                          "codes": pl.codes, **pl.info},
                                  captions=[(pl.text, "", 0.0, 0.0)]) for n, pl in enumerate(plans)]
            found[i] = (rec, sim, kin, pcs)
        if "ref_qpos" in res:
            n = int(res["played"][0]) + 1
            video = (res["qpos"][:n], res["ref_qpos"][:n], titles(loop.plans[0], loop.rows[0].text_at, spt, hz, n))
    order = sorted(found)
    per = {found[i][2].name: found[i][0] for i in order}
    sims = [found[i][1] for i in order if found[i][1] is not None]
    if not sims:
        from motok.errors import UserError
        raise UserError(f"no motion could be tracked ({next(iter(per.values())).get('error', '')})")
    inputs = {**planner.provenance, "controller#weights": controller.meta.get("model_sha256")}
    prov = Provenance(command=command_line(), config=config, inputs=inputs)
    off32 = np.asarray(offsets, dtype=np.float32)
    write_motion(out, "motion", prov, sims, sk, off32, fps, legacy)
    write_motion(kinematic_path(out), "motion", prov, [found[i][2] for i in order], sk, off32, fps, legacy)
    write_motion(plans_path(out), "motion", prov, [c for i in order for c in found[i][3]], sk, off32, fps, legacy)
    replans = [x for r in per.values() for x in r["replans"]]
    changed = [x["change_mm"] > config["change_threshold_mm"] for x in replans]
    ok = [v for v in per.values() if "error" not in v]
    summary = {"output": str(out), "kinematic": str(kinematic_path(out)), "plans": str(plans_path(out)),
               "controller": config["controller"], "controller_kind": config["controller_kind"],
               "closed_loop": True, "replan_every_s": config["replan_every_s"],
               "token_seconds": clock.token_seconds, "clips": len(per), "written": len(sims),
               "tracked_to_end": float(np.mean([v["tracked_to_end"] for v in per.values()])),
               "mpjpe_mm": float(np.mean([v["mpjpe_mm"] for v in ok])) if ok else float("nan"),
               "g_mpjpe_mm": float(np.mean([v["g_mpjpe_mm"] for v in ok])) if ok else float("nan"),
               "sole_slip": slip_report(slip_sim, slip_ref), "replans": len(replans),
               "replans_changed": float(np.mean(changed)) if changed else None,
               "change_threshold_mm": config["change_threshold_mm"],
               "change_mm_mean": float(np.mean([x["change_mm"] for x in replans])) if replans else None,
               "seconds_simulated": round(float(sum(v["seconds"] for v in per.values())), 4)}
    if render is not None and video is not None:
        from motok.sim.render import render_trajectory
        qpos, ghost, names = video
        path, backend = render_trajectory(controller.humanoid, qpos, render, hz, ghost=ghost, title=names)
        summary["video"] = f"{path} ({backend})"
    summary["bvh"] = export_bvhs(out, bvh) if bvh is not None else []
    summary["provenance"] = json.loads(prov.to_json())
    return {**summary, "per_clip": per}
