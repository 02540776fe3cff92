"""Text to physics in a closed loop (``motok gpt sample --prior PRIOR --closed-loop``).

The open loop (:mod:`motok.control.text_to_physics`) samples a whole motion and tracks it: once
the character drifts from it, nothing brings the plan back, and a sample the controller cannot
follow is kept only to its failure. Here the plan is re-made from the simulated character every
``--replan-every`` seconds, at every ``--then`` prompt switch, and before a plan runs out
(:mod:`motok.control.closed_loop.timeline`): the simulated motion of the last window is encoded by the
tokenizer and the GPT continues from those tokens, on the prompt of that moment, instead of from
its own earlier plan; the plan is anchored at the character's root position and heading, and the
controller goes on tracking from the state the physics reached (:mod:`motok.control.closed_loop.replan`).
This is CLoSD's closed loop (Tevet et al. 2025: a planner fed back the simulated frames) over a
discrete-token planner and a distilled latent prior, on a CPU.

Without re-plans (no ``--replan-every``, no ``--then``, a motion the GPT holds whole) the loop is
the open loop, to the bit: the first plan is ``gpt sample``'s sample (the same seeds and draws),
placed and tracked as ``control track`` does.

**Output layout.** ``OUT.h5``: the simulated motion, as the open loop writes it (labels
``tracked_to_end``, ``tracked_seconds``, and ``replans_s``, the times of the re-plans);
``OUT.kinematic.h5``: the reference the controller was given, plan after plan (each plan until the
next was made), through the feature pipeline; ``OUT.plans.h5``: every plan whole, clip
``NAME.planKK``, labelled with the motion, when and why it was made, the tokens it continued and
the ones it added, where it was anchored and how much it changed the reference;
``OUT.closed-loop.json``: the report (:func:`report_path`).
"""

from __future__ import annotations

import json
import time
from dataclasses import replace
from pathlib import Path

import numpy as np

from motok.control.closed_loop.files import REPORT_KIND, plans_path, report_path, write_outputs
from motok.control.closed_loop.replan import Loop, Planner
from motok.control.closed_loop.timeline import Clock, Row, parse_then, timeline_rows
from motok.errors import UserError

REPLAN_EVERY = 1.0  # s, --closed-loop's default: 5 tokens of 0.2 s, CLoSD's order of magnitude
CHANGE_MM = 100.0  # a re-plan that moves the reference by more than this (mean joint, world) changed the plan


def clock_of(gpt, tokenizer=None, control_hz: float = 30.0) -> Clock:
    """The token grid of a GPT run, from its bundle descriptions alone (no weights are read)."""
    from motok.checkpoint import bundle_ref, read_meta
    from motok.config import from_dict
    from motok.gpt.model import TrainConfig

    meta = read_meta(gpt, "gpt")
    tok = Path(tokenizer) if tokenizer is not None else bundle_ref(gpt, meta, "tokenizer", hint="; pass --tokenizer")
    block = from_dict(TrainConfig, meta["config"]).model.block_size
    return Clock(float(read_meta(tok)["extra"]["fps"]), int(meta["extra"]["rate"]), float(control_hz), block - 1)


def rows_from_motion(path, clock: Clock, seed: int = 0, clips: str | None = None) -> list[Row]:
    """The motions of a generated motion artifact (``eval t2m --save-generated``, ``gpt sample``),
    to be made again in the closed loop: each clip's text (label ``text``, else its first caption),
    length in tokens, seed (label ``seed``, else ``seed`` + its index in the file, so that a subset
    chosen by the glob ``clips`` keeps each clip's seed), labels, captions, split."""
    from motok.artifacts import read_strings
    from motok.data.dataset import MotionFile, select_clips

    rows = []
    with MotionFile(path) as mf:
        labels = read_strings(mf.h5["clips/labels"])
        frames = np.diff(mf.frame_offsets)
        chosen = set(select_clips(mf, clips)) if clips else None
        for k, name in enumerate(mf.names):
            if chosen is not None and name not in chosen:
                continue
            lab = json.loads(labels[k]) if labels[k] else {}
            caps = mf.captions(k, tokens=True)
            text = lab.get("text") or (caps[0][0] if caps else "")
            tokens = int(frames[k] * clock.fps / mf.fps) // clock.rate
            if not str(text).strip():
                raise UserError(f"--data {path}: clip {name} has no text to generate from (no `text` label, "
                                f"no caption)")
            if tokens < 1:
                raise UserError(f"--data {path}: clip {name} is shorter than one token ({clock.rate} frames)")
            rows.append(Row(name, [(0, str(text))], tokens, int(lab.get("seed", seed + k)), lab,
                            caps or [(str(text), "", 0.0, 0.0)], split=mf.splits[k]))
    return rows


def load_planner(gpt, texts: list[str], clock: Clock, *, tokenizer=None, allow_mismatch: bool = False,
                 snap: int | None = None, **sampling) -> Planner:
    """The :class:`Planner` of a GPT run, with the embeddings of ``texts``."""
    import torch

    from motok.gpt.sample import check_guidance, load_for_sampling
    from motok.skeleton import Skeleton

    model, meta, tok, tok_meta, tok_run, cache = load_for_sampling(gpt, tokenizer, allow_mismatch, snap=snap)
    sampling["guidance"] = float(model.default_guidance if sampling.get("guidance") is None else sampling["guidance"])
    check_guidance(model, sampling["guidance"])
    unique = list(dict.fromkeys(texts))
    emb = torch.from_numpy(cache.embed(unique, meta["extra"]["text_encoder"], write=False))
    tex = tok_meta["extra"]
    return Planner(model, tok, Skeleton.from_dict(tex["skeleton"], source=f"{tok_run}/bundle.json"),
                   np.asarray(tex["offsets"], dtype=np.float32), bool(tex["legacy"]), clock,
                   {t: emb[k] for k, t in enumerate(unique)}, sampling,
                   {str(Path(gpt) / "model.safetensors"): meta["model_sha256"],
                    str(Path(tok_run) / "model.safetensors"): tok_meta["model_sha256"]})


def run(planner: Planner, controller, rows: list[Row], every: int | None, *, push=None, keep_qpos: bool = False,
        batch: int = 64) -> list[tuple[Loop, dict, list[int]]]:
    """Generate and simulate ``rows`` in the closed loop, ``batch`` at a time (longest first, so a
    batch ends together): per batch, its :class:`~motok.control.closed_loop.replan.Loop` (plans, re-plans,
    simulated positions), :func:`~motok.control.tasks.imitation.play`'s result and the rows' indices.
    ``keep_qpos``: the first row's states and references, for a video. Nothing is written."""
    from motok.control.tasks.imitation import play
    from motok.sim.soles import soles

    cfg, hum = controller.cfg, controller.humanoid
    task = replace(cfg.task, max_episode_seconds=1e9)
    order = [0] + sorted(range(1, len(rows)), key=lambda i: -rows[i].tokens)
    sole, out = soles(hum), []
    for a in range(0, len(order), batch):
        ids = order[a:a + batch]
        loop = Loop(planner, hum, [rows[i] for i in ids], every, push)
        lib = loop.start(batch)
        res = play(hum, controller.policy, lib, np.arange(len(ids)), cfg.env, task, cfg.action,
                   keep_qpos=keep_qpos and a == 0, sole=sole, replan=loop)
        out.append((loop, res, ids))
    return out


def check_options(*, texts, then, data, replan_every, closed_loop: bool, simulated: bool, clips=None) -> None:
    """The option errors that need no file: one line each, before any work."""
    if clips is not None and data is None:
        raise UserError("--clips chooses clips of --data (a generated set made again in the closed loop): add --data")
    if not closed_loop and replan_every is not None:
        raise UserError("--replan-every goes with --closed-loop")
    if (then or data is not None or closed_loop) and not simulated:
        what = "--then" if then else "--data" if data is not None else "--closed-loop"
        raise UserError(f"{what} re-plans from the simulated character: add --prior PRIOR (or --expert RUN)")
    if data is not None and not closed_loop:
        raise UserError("--data makes a generated set again in the closed loop: add --closed-loop (the open loop "
                        "of a generated set is `motok control track -d FILE`)")
    if data is not None and (texts or then):
        raise UserError("--data brings its own texts: leave out --text, --texts-file and --then")
    if then:
        parse_then(then)


def closed_loop(gpt, out, *, texts=(), then=(), data=None, seconds: float | None = None, num_samples: int = 1,
                seed: int = 0, replan_every: float | None = REPLAN_EVERY, prior=None, expert=None, codebooks=None,
                render=None, bvh=None, tokenizer=None, allow_mismatch: bool = False, snap=None,
                temperature: float = 1.0, top_k=None, top_p=None, argmax: bool = False, guidance=None,
                change_mm: float = CHANGE_MM, batch: int = 64, push=None, clips: str | None = None) -> dict:
    """Generate and simulate in the closed loop and write ``out``, ``OUT.kinematic.h5``,
    ``OUT.plans.h5`` and the report (module docstring): ``texts`` (``num_samples`` each; one text
    with ``then``, ``[(time, text)]``, is a timeline) or the clips of the generated set ``data`` (those
    matching the glob ``clips``, if given);
    ``replan_every`` seconds (None: only at prompt switches and when a plan runs out). Every
    option is checked before anything is loaded. Returns the report."""
    from motok.atomic import check_writable, write_json
    from motok.control.text_to_physics import H5, VIDEO, kinematic_path, load_physics_controller
    from motok.gpt.sample import check_sampling

    check_options(texts=texts, then=then, data=data, replan_every=None, closed_loop=True, simulated=True, clips=clips)
    out = check_writable(out, suffixes=H5)
    for path, what in ((kinematic_path(out), "the kinematic motion"), (plans_path(out), "the plans")):
        check_writable(path, what=what)
    if render is not None:
        check_writable(render, suffixes=VIDEO, what="--render (with --prior or --expert)")
    if bvh is not None:
        check_writable(bvh, suffixes=(".bvh",), what="--bvh")
    sampling = dict(temperature=temperature, top_k=top_k, top_p=top_p, argmax=argmax)
    if data is None:
        check_sampling(list(texts), num_samples=num_samples, seconds=seconds, **sampling)
    clock = clock_of(gpt, tokenizer)
    every = clock.tokens(replan_every, "--replan-every") if replan_every is not None else None
    rows = rows_from_motion(data, clock, seed, clips) if data is not None else \
        timeline_rows(list(texts), parse_then(list(then)), clock, seconds, num_samples, seed)
    controller = load_physics_controller(prior, expert, codebooks)
    hum = controller.humanoid
    clock = replace(clock, control_hz=float(controller.cfg.env.control_hz or hum.control_hz))
    clock.steps_per_token  # noqa: B018 - refuses a control rate off the token grid, before any work
    t0 = time.perf_counter()
    planner = load_planner(gpt, [t for r in rows for _, t in r.prompts], clock, tokenizer=tokenizer,
                           allow_mismatch=allow_mismatch, snap=snap, guidance=guidance, **sampling)
    if list(planner.skeleton.joints) != list(hum.skeleton.joints):
        raise UserError(f"{gpt} generates the {planner.skeleton.num_joints}-joint skeleton of its tokenizer, which "
                        f"is not the controller's humanoid ({hum.skeleton.num_joints} joints, "
                        f"{hum.skeleton.name!r}): use a controller trained on the GPT's data")
    t_load = time.perf_counter()
    batches = run(planner, controller, rows, every, push=push, keep_qpos=render is not None, batch=batch)
    t_run = time.perf_counter()
    config = {"gpt": str(gpt), "controller": str(prior if prior is not None else expert),
              "controller_kind": controller.meta.get("kind"), "codebooks": codebooks, "closed_loop": True,
              "replan_every_s": replan_every, "token_seconds": clock.token_seconds, "seconds": seconds,
              "texts": list(texts), "then": [list(x) for x in parse_then(list(then))] if then else [],
              "data": None if data is None else str(data), "clips": clips, "seed": seed, "num_samples": num_samples,
              "change_threshold_mm": change_mm, **sampling, "guidance": planner.sampling["guidance"]}
    report = write_outputs(out, batches, planner, controller, config, render=render, bvh=bvh)
    report.update(time_load_s=round(t_load - t0, 2), time_run_s=round(t_run - t_load, 2),
                  time_plan_s=round(planner.seconds, 2), time_write_s=round(time.perf_counter() - t_run, 2))
    report["realtime_factor"] = round(report["seconds_simulated"] / max(t_run - t_load, 1e-9), 3)
    per = report.pop("per_clip")
    write_json(report_path(out), {"kind": REPORT_KIND, "schema_version": 1, **report, "per_clip": per})
    return {**report, "per_clip": per}
