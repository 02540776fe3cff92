"""Evaluation of a distilled prior on the imitation task (``motok control eval --task imitation
--prior PRIOR``; the paper's Fig. 4): the student's posterior reads the goal and its decoder acts,
every clip from frame 0 with the most likely latent (``motok.control.tasks.imitation``), optionally
with only the first M codebooks of a residual prior."""

from __future__ import annotations

import json
from dataclasses import asdict
from pathlib import Path

from motok.artifacts import Provenance, command_line, hash_inputs
from motok.control import runs
from motok.control.priors.load import StudentPolicy, check_codebooks
from motok.control.priors.model import load_prior
from motok.control.tasks.imitation import by_group, evaluate
from motok.control.tasks.registry import IMITATION
from motok.errors import UserError
from motok.ranges import checked  # numbers in range for callers from Python too



@checked(distance="motok.control.tasks.imitation:ImitationTaskConfig.termination_distance", codebooks=">= 1")
def evaluate_prior(run, *, task: str = "imitation", data=None, clips: str | None = None, split: str | None = None,
                   codebooks: int | None = None, render=None, termination: str | None = None,
                   distance: float | None = None, device: str | None = None) -> dict:
    """Success, MPJPE, G-MPJPE, root velocity and acceleration errors of the prior in ``run`` on
    its distillation clips (or the clips of ``data`` in ``split`` / matching ``clips``), per clip,
    per content and style, and overall; written to ``PRIOR/eval[_SPLIT][_mM].json`` with the
    checkpoint it measured and provenance."""
    if task != IMITATION:
        raise UserError(f"--task must be {IMITATION} for a prior, not {task!r}")
    run = Path(run)
    cfg, hum, model, meta = load_prior(run)
    if codebooks is not None:
        check_codebooks(model, codebooks, prior_alone=False)
    if termination is not None:
        cfg.task.termination = termination
    if distance is not None:
        cfg.task.termination_distance = distance
    cfg.env.on(device)
    src, lib = runs.run_library(run, meta, hum, cfg.env.control_hz, data, clips, split)
    res = evaluate(hum, StudentPolicy(model, codebooks), lib, cfg.env, cfg.task, cfg.action, render,
                   batch=cfg.eval_batch)
    res["groups"] = by_group(res["clips"])
    res["checkpoint"] = {**runs.checkpoint_info(meta), "prior": meta["extra"]["prior"],
                         "codebooks": codebooks or model.num_codebooks}
    prov = Provenance(command=command_line(), config={"prior": str(run), "task": task, "clips": clips, "split": split,
                                                        "codebooks": codebooks, "imitation": asdict(cfg.task)},
                      inputs=hash_inputs([src]))
    res = {"kind": "control-prior-eval", "schema_version": 1, **res, "provenance": json.loads(prov.to_json())}
    name = "eval" + (f"_{split}" if split else "") + (f"_m{codebooks}" if codebooks else "") + ".json"
    runs.write_evaluation(run / name, res)
    res["written"] = str(run / name)
    return res
