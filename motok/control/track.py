"""Kinematic motion in, physically simulated motion out (``motok control track``).

Any motion artifact (a dataset, decoded tokens, GPT samples) becomes the reference of the
imitation task; a controller (the expert, or a distilled prior's posterior and decoder)
tracks every clip from its first frame in MuJoCo until the clip ends or the tracking fails (the
controller's own failure test); the simulated bodies are written back as a ``motion`` artifact at
the motion's frame rate, so ``motok eval``, ``render`` and ``export bvh`` read it like any other.
Each written clip keeps its reference's labels and adds ``tracked_to_end`` and ``tracked_seconds``.

**Start state.** Generated motion starts wherever the generator put it: above the floor, or with
feet through it. Each clip is moved vertically, as a whole, so that its lowest joint over the
clip is at floor height: the floor of the feature pipeline (``extract_features``), so every
motion stands as the data the controller was trained on stood (a constant shift keeps its jumps
and crouches). Not the humanoid's geometry: in the data the feet's geometry reaches 0.5-3 cm
into the floor, and a prior lifted by that much fails on clips it tracks in place (on 12 test
clips: 12 of 12 played to the end in place, 0 of 12 lifted). The simulation starts at frame 0 of
the placed motion with the reference velocities, which the library differentiates from the
frames (``mj_differentiatePos``), so the character starts moving the way the motion does; a start
pose whose geometry dips below the floor is lifted as in training (``mdp.resets``).

**Output.** The simulated body positions are the skeleton's joint positions (one body per joint,
docs/sim.md), taken back to the data frame (Y up), resampled from the control rate to the
motion's frame rate, and put through the feature pipeline (``extract_features``: the uniform
skeleton of the input, floor, facing +Z), so features, joints, local rotations and root
translation all describe the simulated motion. A clip that fails keeps the part played.

**Sole slip.** Beside MPJPE, each clip's report has the sole slip of the simulated feet and of the
reference over the same states (``motok.sim.soles``), the artefact the simulation is meant to
remove; the joints' skating measure cannot see it on a foot that rocks on its sole.
"""

from __future__ import annotations

import json
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np

from motok.artifacts import Provenance, command_line, hash_inputs
from motok.atomic import write_json
from motok.control.priors.load import Controller
from motok.control.tasks.imitation import clip_slip, play, slip_report
from motok.data.dataset import TRACKED_TO_END, MotionFile
from motok.data.memory import MotionClips
from motok.errors import UserError
from motok.eval.metrics import mpjpe
from motok.sim.reference import ReferenceLibrary, build_library, simulated_clip
from motok.sim.soles import SlipSums, soles

MIN_FRAMES = 4  # frames a clip needs at the control rate: a step with one frame of goal ahead, and features


def place_on_floor(lib: ReferenceLibrary) -> tuple[ReferenceLibrary, np.ndarray]:
    """Each clip shifted vertically so its lowest joint over the clip is at height 0, as the feature
    pipeline places the data (a dataset's clips move by well under a millimetre, the resampling's);
    returns the placed library and the shift per clip (m, + up)."""
    shift = np.array([-lib.joints[a:b, :, 2].min() for a, b in zip(lib.starts[:-1], lib.starts[1:])])
    per_frame = np.repeat(shift, lib.lengths)
    qpos, body_pos, joints = lib.qpos.copy(), lib.body_pos.copy(), lib.joints.copy()
    qpos[:, 2] += per_frame
    body_pos[..., 2] += per_frame[:, None]
    joints[..., 2] += per_frame[:, None]
    return replace(lib, qpos=qpos, body_pos=body_pos, joints=joints, lowest=lib.lowest + per_frame), shift


@dataclass
class Tracked:
    """What :func:`track_clips` made: the simulated clips (those played for at least two frames
    at the motion's rate, in the input's order), the overall results and one report per clip."""

    motion: MotionClips
    summary: dict  # clips, written, tracked_to_end, mpjpe_mm, g_mpjpe_mm, sole_slip (and video)
    per_clip: dict[str, dict]  # tracked to the end, seconds, MPJPE, G-MPJPE, sole slip (or an error)


def track_clips(controller: Controller, motion, *, clips: str | None = None, split: str | None = None,
                render=None, batch: int = 256, chunk: int = 2048) -> Tracked:
    """Track the clips of the open motion ``motion`` (a :class:`MotionFile` or
    :class:`~motok.data.memory.MotionClips`: all, or those of ``split`` and/or the ``clips``
    glob) with ``controller`` (:func:`motok.control.priors.load.load_controller`), in memory;
    ``render``: a video of the first clip over its kinematic ghost.

    ``batch`` clips are simulated at once, longest first; their reference library is built for
    ``chunk`` clips at a time (a GPT evaluation's 11,000 samples at the control rate in float64
    would fill this machine's memory), never cached (each motion is tracked once)."""
    from motok.data.dataset import select_clips

    cfg, hum, ac = controller.cfg, controller.humanoid, controller.policy
    mf = motion  # open: a MotionFile or MotionClips
    names = select_clips(mf, clips, split) if clips or split else list(mf.names)
    fps, skeleton, legacy = mf.fps, mf.skeleton, mf.legacy
    offsets = np.asarray(mf.offsets, dtype=np.float64)
    frames = np.diff(mf.frame_offsets)
    lengths = {n: int(frames[mf.index(n)]) for n in names}
    hz = float(cfg.env.control_hz or hum.control_hz)
    short = [n for n in names if int(lengths[n] * hz / fps) < MIN_FRAMES]
    kept = [n for n in names if n not in short]
    if not kept:
        raise UserError(f"{mf.path}: no clip is long enough to track (at least {MIN_FRAMES} frames at {hz:g} Hz)")
    # Longest first, so that a batch's clips end together; the first clip leads, for the video.
    order = kept[:1] + sorted(kept[1:], key=lambda n: -lengths[n])
    task = replace(cfg.task, max_episode_seconds=1e9)
    per, written, video = {}, [], None
    sole, slip_sim, slip_ref = soles(hum), SlipSums(), SlipSums()
    for c0 in range(0, len(order), chunk):
        lib, shift = place_on_floor(build_library(hum, mf, hz, order[c0:c0 + chunk]))
        for start in range(0, len(lib), batch):
            ids = np.arange(start, min(start + batch, len(lib)))
            first = render is not None and c0 == 0 and start == 0
            res = play(hum, ac, lib, ids, cfg.env, task, cfg.action, keep_qpos=first, sole=sole)
            if first:
                played = int(res["played"][0])
                video = (res["qpos"][:played + 1], lib.qpos[lib.starts[0]:lib.starts[0] + played + 1], lib.names[0])
            for k, i in enumerate(ids):
                alive = res["alive"][k]
                p, r = res["pos"][k, alive], res["ref"][k, alive]
                name = lib.names[i]
                per[name] = {"tracked_to_end": bool(res["success"][k]), "seconds": float(res["played"][k] / hz),
                             "clip_seconds": float((lib.lengths[i] - 1 - task.goal_frames) / hz),
                             "floor_shift_m": float(shift[i]), "mpjpe_mm": float(mpjpe(p, r).mean()),
                             "g_mpjpe_mm": float(mpjpe(p, r, root_relative=False).mean())}
                s_sim, s_ref = clip_slip(res, k)
                slip_sim.add(s_sim), slip_ref.add(s_ref)
                per[name].update(sole_slip_cm_s=s_sim.result()["sole_slip_cm_s"],
                                 reference_sole_slip_cm_s=s_ref.result()["sole_slip_cm_s"])
                if len(p) * fps / hz >= 2:
                    ref = mf.clip(name)  # its split, labels and captions, so text metrics apply to the result
                    # the outcome travels with the clip, so `eval t2m --tracked-to-end` can keep the clips played through
                    labels = {**ref.labels, TRACKED_TO_END: per[name]["tracked_to_end"],
                              "tracked_seconds": round(per[name]["seconds"], 4)}
                    written.append(simulated_clip(name, p, hz, fps, skeleton, offsets, legacy, str(mf.path),
                                                  split=ref.split, labels=labels, captions=ref.captions))
                else:
                    per[name]["error"] = "failed before two frames at the motion's rate were simulated: nothing written"
        del lib  # the next chunk's library replaces it, not beside it
    for n in short:
        per[n] = {"tracked_to_end": False, "error": f"{lengths[n]} frames at {fps:g} fps: too short to track "
                                                     f"(at least {MIN_FRAMES} frames at {hz:g} Hz)"}
    if not written:
        raise UserError(f"{mf.path}: no clip could be tracked ({next(iter(per.values())).get('error', '')})")
    ordered = {n: per[n] for n in names}
    position = {n: k for k, n in enumerate(names)}
    written.sort(key=lambda c: position[c.name])
    ok = [v for v in ordered.values() if "mpjpe_mm" in v]
    summary = {"clips": len(names), "written": len(written),
               "tracked_to_end": float(np.mean([v["tracked_to_end"] for v in ordered.values()])),
               "mpjpe_mm": float(np.mean([v["mpjpe_mm"] for v in ok])) if ok else float("nan"),
               "g_mpjpe_mm": float(np.mean([v["g_mpjpe_mm"] for v in ok])) if ok else float("nan"),
               "sole_slip": slip_report(slip_sim, slip_ref)}
    if render is not None and video is not None:
        from motok.sim.render import render_trajectory
        qpos, ghost, name = video
        path, backend = render_trajectory(hum, qpos, render, hz, ghost=ghost, title=f"tracked {name}")
        summary["video"] = f"{path} ({backend})"
    sim = MotionClips(written, skeleton, offsets.astype(np.float32), fps, legacy, path=f"{mf.path}, tracked")
    return Tracked(sim, summary, ordered)


def track(controller: Controller, motion, out, *, clips: str | None = None, split: str | None = None,
          render=None, batch: int = 256, chunk: int = 2048) -> dict:
    """Track the clips of the motion artifact ``motion`` (:func:`track_clips`), write the
    simulated clips to ``out``, and the per-clip and overall results beside it
    (:func:`report_path`, kind ``control-track``), which it also returns."""
    motion, out = Path(motion), Path(out)
    with MotionFile(motion) as mf:
        done = track_clips(controller, mf, clips=clips, split=split, render=render, batch=batch, chunk=chunk)
    task = controller.cfg.task
    prov = Provenance(command=command_line(), config={"motion": str(motion), "clips": clips,
                                                      "controller": controller.meta.get("kind"),
                                                      "termination": task.termination,
                                                      "termination_distance": task.termination_distance},
                      inputs={**hash_inputs([motion]), "controller#weights": controller.meta.get("model_sha256")})
    done.motion.write(out, prov)
    summary = {"output": str(out), **done.summary}
    write_json(report_path(out), {"kind": REPORT_KIND, "schema_version": 1, **summary, "per_clip": done.per_clip,
                                  "provenance": json.loads(prov.to_json())})
    return {**summary, "per_clip": done.per_clip}


REPORT_KIND = "control-track"


def report_path(out) -> Path:
    """Where :func:`track` writes its results for the simulated motion ``out``: ``walk_sim.h5`` ->
    ``walk_sim.track.json`` (tracked to the end, seconds, MPJPE and G-MPJPE per clip and overall)."""
    out = Path(out)
    return out.with_name(out.stem + ".track.json")
