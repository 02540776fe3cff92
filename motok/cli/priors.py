"""``motok control distill`` (the latent priors, distilled online from an expert), ``motok
control eval --task imitation --prior`` (how well a distilled prior imitates) and ``motok control
generate`` (what a prior does on its own). Arguments only; the work is in ``motok.control.priors.distill``,
``motok.control.priors.evaluate`` and ``motok.control.priors.generate``. :func:`register` adds the commands to
the ``motok control`` app."""

from __future__ import annotations

from pathlib import Path
from typing import Optional

import typer

from motok.cli.common import (Device, H5, JsonOut, Resume, Sets, clips_option, data_option, device_sets, fail,
                              input_option, number_option, output_option, recipe_option, report, results, run,
                              split_option, valid_device)
from motok.cli.conventions import examples, renamed
from motok.cli.outputs import Force, train_into
from motok.control.priors.kinds import KINDS
from motok.control.tasks import registry

# Config classes whose fields' ranges the options below share (motok.ranges.range_of).
TRACKING = "motok.control.tasks.imitation:ImitationTaskConfig"

PRIORS = " | ".join(KINDS)
EVAL_TASKS = (registry.IMITATION, *registry.names())  # a prior on imitation, or a task policy on its task


@renamed(prior="--kind")
def distill_cmd(
    expert: Path = input_option("--expert", help="A control-expert run folder (the frozen teacher)."),
    prior: str = typer.Option(..., "--kind", help=f"The prior's bottleneck: {PRIORS}."),
    out: Path = output_option(help="Prior folder (checkpoint bundle, metrics.jsonl).", folder=True),
    recipe: Optional[Path] = recipe_option("recipes/control/prior_*.yaml"),
    sets: list[str] = Sets,
    data: Optional[Path] = data_option("Dataset (default: the one the expert was trained on).", required=False),
    clips: Optional[str] = clips_option(help="Clip-name glob (default: the expert's clips)."),
    split: Optional[str] = split_option(help="Only the clips of this split."),
    resume: bool = Resume, force: bool = Force,
    until: Optional[int] = number_option(None, "--until", help="Stop after this iteration (the weight schedules "
                                         "still span the recipe's iterations; --resume continues).", within=">= 1"),
    device: Optional[str] = Device,
    as_json: bool = JsonOut,
):
    """Distil the expert into a latent prior: the student acts, the expert labels (DAgger), Eq. 6."""
    from motok.control.priors.distill import train_from_expert
    from motok.control.priors.model import KIND, DistillConfig
    from motok.resume import resolve_config

    cfg = run(resolve_config, DistillConfig, recipe, device_sets(device) + sets, out, KIND, resume)
    summary = train_into(out, lambda where: train_from_expert(cfg, expert, where, prior=prior, data=data,
                                           clips=clips, split=split, resume=resume, until=until),
                         resume=resume, force=force)
    report(summary, as_json, f"control distill {prior}")


@renamed(run="--policy")
def eval_cmd(
    prior: Optional[Path] = input_option("--prior", help="--task imitation: a control-prior folder (from `control "
                                         "distill`).", required=False),
    task: str = typer.Option(registry.IMITATION, "--task", help="imitation (a prior, --prior), or a trained task "
                             f"policy's task: {' | '.join(registry.names())} (--policy)."),
    run_dir: Optional[Path] = input_option("--policy", help="A task policy: a control-task run folder (from "
                                           "`control train`).", required=False),
    episodes: int = number_option(256, "-n", "--num-samples", help="Task policies: episodes to evaluate.",
                                  within=">= 1"),
    seed: int = number_option(0, "--seed", help="Task policies: seed of the start states and targets.", within=">= 0"),
    data: Optional[Path] = data_option("Dataset (default: the one it was distilled on).", required=False),
    clips: Optional[str] = clips_option(help="Clip-name glob (default: the distillation clips)."),
    split: Optional[str] = split_option(help="The clips of this split."),
    codebooks: Optional[int] = number_option(None, "--codebooks", "-m", help="Decode with the first M codebooks only "
                                             "(residual priors; default: all).", within=">= 1"),
    render: Optional[Path] = output_option("--render", help="Video of the first clip (.mp4/.gif).",
                                           suffixes=(".mp4", ".gif"), required=False),
    termination: Optional[str] = typer.Option(None, "--termination",
                                              help="Failure test: 'any' body or the 'mean' (default: the prior's)."),
    distance: Optional[float] = number_option(None, "--distance", help="Failure distance in m (default: the prior's).",
                                              within=f"{TRACKING}.termination_distance"),
    device: Optional[str] = Device,
    task_sets: list[str] = typer.Option([], "--set", metavar="tasks.NAME.KEY=VALUE",
                                        help="Task policies: evaluate under another task setting (repeatable), e.g. "
                                        "--set 'tasks.multitask.switch=[\"4s steering\"]'."),
    as_json: bool = JsonOut,
):
    """A prior on imitation (success, MPJPE, G-MPJPE, root errors) or a task policy on its task."""
    if task not in EVAL_TASKS:
        fail(f"--task must be one of {', '.join(EVAL_TASKS)}, not {task!r}")
    if task != registry.IMITATION:
        return _eval_task(task, run_dir, prior, episodes, seed, data, clips, split, render, as_json,
                          valid_device(device), task_sets)
    if task_sets:
        fail("--set changes a task policy's task settings (--policy); a prior's evaluation takes none")
    if prior is None:
        fail("--task imitation evaluates a prior: pass --prior PRIOR (a task policy: --task T --policy RUN)")
    from motok.control.priors.evaluate import evaluate_prior

    res = run(evaluate_prior, prior, task=task, data=data, clips=clips, split=split, codebooks=codebooks,
              render=render, termination=termination, distance=distance, device=valid_device(device))
    o = res["overall"]
    summary = {"prior": str(prior), "kind": res["checkpoint"]["prior"]["kind"], "codebooks": res["checkpoint"]["codebooks"],
               **{k: o[k] for k in ("clips", "success_rate", "success_rate_any_body", "seconds_played", "mpjpe_mm",
                                    "g_mpjpe_mm", "root_vel_err_mm", "root_acc_err_mm")}, "written": res["written"]}
    if as_json:
        res.pop("provenance")
    report(res if as_json else summary, as_json, f"control eval {task} ({o['termination']} ends a clip)")


def _eval_task(task, run_dir, prior, episodes, seed, data, clips, split, render, as_json, device=None,
               sets=()) -> None:
    if run_dir is None or prior is not None:
        fail(f"--task {task} evaluates a trained task policy: pass --policy RUN (from `motok control train`), not --prior")
    from motok.control.highlevel.evaluate import evaluate_run

    res = run(evaluate_run, run_dir, episodes=episodes, seed=seed, data=data, clips=clips, split=split, render=render,
              device=device, task=task, sets=list(sets))
    if as_json:
        res.pop("provenance")
        report(res, True, "")
        return
    scalars = {k: v for k, v in res.items() if isinstance(v, (int, float, str)) and k not in ("kind", "schema_version")}
    report(scalars, False, f"control eval {task} of {run_dir}")


def generate_cmd(
    prior: Path = input_option("--prior", help="A control-prior folder (from `control distill`)."),
    out: Path = output_option(help="The generated motion (.h5, a motion artifact).", suffixes=H5),
    codebooks: Optional[int] = number_option(None, "--codebooks", "-m", help="Sample codes from the first M codebooks "
                                             "(default: all; 0: hybrid's prior z_p alone; not for the continuous "
                                             "prior).", within=">= 0"),
    seconds: float = number_option(30.0, "--seconds", help="Length of each sample in seconds (a fall ends it "
                                   "sooner).", within="> 0"),
    num: int = number_option(10, "-n", "--num-samples", help="Number of samples.", within=">= 1"),
    seed: int = number_option(0, "--seed", help="Seed of the start states and of the code draws.", within=">= 0"),
    data: Optional[Path] = data_option("Dataset of the start states (default: the one it was distilled on).",
                                       required=False),
    clips: Optional[str] = clips_option(help="Start from these clips (default: the distillation clips)."),
    split: Optional[str] = split_option(help="Start from the clips of this split."),
    render: Optional[Path] = output_option("--render", help="Video of the first sample (.mp4/.gif).",
                                           suffixes=(".mp4", ".gif"), required=False),
    as_json: bool = JsonOut,
):
    """Unconditional generation: random codes (or prior draws) at every step from reference start states."""
    from motok.control.priors.generate import generate

    res = run(generate, prior, out, codebooks=codebooks, seconds=seconds, num_samples=num, seed=seed, data=data,
              clips=clips, split=split, render=render)
    per = res.pop("per_sample")
    if as_json:
        report({**res, "per_sample": per}, True, "")
        return
    report(res, False, "control generate")
    for name, r in per.items():
        if r["stopped"]:
            results.print(f"{name}: {r['stopped']} after {r['seconds']:.2f} s (from {r['start_clip']} frame "
                          f"{r['start_frame']})" + (f"; {r['error']}" if "error" in r else ""),
                          soft_wrap=True, highlight=False)


def register(app: typer.Typer) -> None:
    app.command("distill", epilog=examples(
        "motok control distill --expert runs/expert --kind hybrid --recipe recipes/control/prior_hybrid.yaml "
        "-o runs/prior_hybrid",
        "motok control distill --expert runs/expert --kind hybrid --recipe recipes/control/prior_hybrid.yaml "
        "-o runs/prior_hybrid --resume --until 1000"))(distill_cmd)
    app.command("eval", epilog=examples(
        "motok control eval --task imitation --prior runs/prior_hybrid --split test",
        "motok control eval --task imitation --prior runs/prior_hybrid --codebooks 1 --json",
        "motok control eval --task navigation --policy runs/nav_hybrid -n 256 --render nav.mp4"))(eval_cmd)
    app.command("generate", epilog=examples(
        "motok control generate --prior runs/prior_hybrid --codebooks 1 --seconds 30 -n 10 -o gen_hybrid_m1.h5 "
        "--render gen.mp4",
        "motok control generate --prior runs/prior_continuous -n 100 --seed 1 -o gen_cont.h5 --json"))(generate_cmd)
