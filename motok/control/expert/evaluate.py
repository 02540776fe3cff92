"""``motok control expert eval``: a trained expert on its clips, or on another split or glob."""

from __future__ import annotations

import json
from dataclasses import asdict
from pathlib import Path

from motok.artifacts import Provenance, command_line, hash_inputs
from motok.control import runs
from motok.control.expert.model import load_expert
from motok.control.tasks.imitation import by_group, evaluate
from motok.ranges import checked  # numbers in range for callers from Python too


@checked(distance="motok.control.tasks.imitation:ImitationTaskConfig.termination_distance")
def evaluate_run(run, *, data=None, clips: str | None = None, split: str | None = None, render=None,
                 termination: str | None = None, distance: float | None = None, device: str | None = None) -> dict:
    """``motok control expert eval``: :func:`evaluate` the checkpoint in ``run`` on its training
    clips (or the clips of ``data`` in ``split`` and/or matching the ``clips`` glob), with the
    summary per content and per style, and write ``RUN/eval.json`` (``RUN/eval_SPLIT.json``) with
    the checkpoint it measured (iteration, samples, training wall time, MJCF hash) and
    provenance, so a number quoted from it can be traced to the weights and data that made it."""
    run = Path(run)
    cfg, hum, ac, meta = load_expert(run)
    if termination is not None:
        cfg.task.termination = termination
    if distance is not None:
        cfg.task.termination_distance = distance
    cfg.env.on(device)
    src, lib = runs.run_library(run, meta, hum, cfg.env.control_hz, data, clips, split, hint="; pass --data")
    res = evaluate(hum, ac, lib, cfg.env, cfg.task, cfg.action, render, batch=cfg.sampling.eval_batch, feet=True)
    res["groups"] = by_group(res["clips"])
    res["checkpoint"] = runs.checkpoint_info(meta)
    prov = Provenance(command=command_line(), config={"run": str(run), "clips": clips, "split": split,
                                                        "task": asdict(cfg.task)},
                      inputs=hash_inputs([src]))
    res = {"kind": "control-expert-eval", "schema_version": 1, **res, "provenance": json.loads(prov.to_json())}
    runs.write_evaluation(run / (f"eval_{split}.json" if split else "eval.json"), res)
    return res
