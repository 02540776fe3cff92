"""``motok control train --task T --prior PRIOR`` (a high-level policy over a frozen prior) and
``motok control perturb`` (thrown balls at a trained policy). Arguments only; the work is in
``motok.control.highlevel.train`` and ``motok.control.highlevel.perturb``. :func:`register` adds the commands
to the ``motok control`` app; ``motok control eval --task T --policy RUN`` is in ``cli/priors.py``."""

from __future__ import annotations

from pathlib import Path
from typing import Optional

import typer

from motok.cli.common import (Device, JsonOut, Resume, Sets, clips_option, data_option, device_sets, input_option,
                              number_option, output_option, recipe_option, report, run, split_option)
from motok.cli.conventions import examples, renamed
from motok.cli.outputs import Force, train_into
from motok.control.tasks import registry

# Config classes whose fields' ranges the options below share (motok.ranges.range_of).
PERTURB = "motok.control.highlevel.perturb:PerturbConfig"
TASK = "motok.control.highlevel.policy:TaskTrainConfig"

TASK_NAMES = " | ".join(registry.names())


def train_cmd(
    task: Optional[str] = typer.Option(None, "--task", help=f"The task: {TASK_NAMES} (default: the recipe's)."),
    prior: Path = input_option("--prior", help="A control-prior folder (from `control distill`), kept frozen."),
    codebooks: Optional[int] = number_option(None, "--codebooks", "-m", help="Choose codes in the first M codebooks "
                                             "(residual priors; default: the recipe's, else the task's paper "
                                             "default: inbetween 1, hmd 2, navigation 1).",
                                             within=f"{TASK}.codebooks"),
    out: Path = output_option(help="Run folder (checkpoint bundle, metrics.jsonl).", folder=True),
    recipe: Optional[Path] = recipe_option("recipes/control/task_*.yaml"),
    sets: list[str] = Sets,
    data: Optional[Path] = data_option("Dataset of the start states and references (default: the prior's).",
                                       required=False),
    clips: Optional[str] = clips_option(help="Clip-name glob (default: the prior's clips)."),
    split: Optional[str] = split_option(help="Only the clips of this split."),
    resume: bool = Resume, force: bool = Force,
    until: Optional[int] = number_option(None, "--until", help="Stop after this iteration (--resume continues).",
                                         within=">= 1"),
    device: Optional[str] = Device,
    as_json: bool = JsonOut,
):
    """PPO over the prior's latent space: the policy picks codes (or an offset from the prior's mean)."""
    from motok.control.highlevel.policy import KIND, TaskTrainConfig
    from motok.control.highlevel.train import train_from_prior
    from motok.resume import resolve_config

    # --task and --codebooks are settings like any other: on resume they are compared with the run's
    flags = [f"task={task}"] * (task is not None) + [f"codebooks={codebooks}"] * (codebooks is not None)
    cfg = run(resolve_config, TaskTrainConfig, recipe, device_sets(device) + sets + flags, out, KIND, resume)
    summary = train_into(out, lambda where: train_from_prior(cfg, prior, where, data=data, clips=clips, split=split,
                                           resume=resume, until=until),
                         resume=resume, force=force)
    report(summary, as_json, f"control train {cfg.task}")


@renamed(run="--policy")
def perturb_cmd(
    run_dir: Path = input_option("--policy", help="A task policy: a control-task run folder (from `control train`), "
                                 "e.g. navigation."),
    episodes: int = number_option(64, "-n", "--num-samples", help="Episodes to run under fire.", within=">= 1"),
    seed: int = number_option(0, "--seed", help="Seed of the throws and of the task's starts and targets.",
                              within=">= 0"),
    period: float = number_option(0.3, "--period", help="Seconds between throws (the paper's 0.3; another "
                                  "period is written to RUN/perturb_periodP.json).", within=f"{PERTURB}.period"),
    render: Optional[Path] = output_option("--render", help="Video of the first episode with the balls "
                                           "(.mp4/.gif).", suffixes=(".mp4", ".gif"), required=False),
    as_json: bool = JsonOut,
):
    """Thrown balls (10 cm, 4.2 kg, 10-20 m/s from 1 m) at a trained policy, zero-shot: hits, falls, recoveries."""
    from motok.control.highlevel.perturb import PerturbConfig, perturb_run

    res = run(lambda: perturb_run(run_dir, episodes=episodes, seed=seed, render=render,
                                  cfg=PerturbConfig(period=period)))
    if as_json:
        res.pop("provenance")
        report(res, True, "")
        return
    report({k: v for k, v in res.items() if isinstance(v, (int, float, str)) and k not in ("kind", "schema_version")},
           False, f"control perturb {run_dir}")


def register(app: typer.Typer) -> None:
    app.command("perturb", epilog=examples(
        "motok control perturb --policy runs/nav_hybrid -n 64 --render nav_balls.mp4",
        "motok control perturb --policy runs/nav_hybrid --period 0.6 --json"))(perturb_cmd)
    app.command("train", epilog=examples(
        "motok control train --task navigation --prior runs/prior_hybrid --codebooks 1 "
        "--recipe recipes/control/task_navigation.yaml -o runs/nav_hybrid",
        "motok control train --task navigation --prior runs/prior_hybrid -o runs/nav_hybrid --resume --until 1000",
    ))(train_cmd)
