"""``motok control``: physics-based controllers. ``expert train`` / ``expert eval`` parse
arguments only; the work is in ``motok.control.expert.train``."""

from __future__ import annotations

import os
from pathlib import Path
from typing import Optional

import typer

from motok.cli.common import (Device, Resume, clips_option, data_option, device_sets, existing, number_option,
                              output_option, print_json, recipe_option, report, results, run, split_option,
                              valid_device)
from motok.cli.conventions import examples, renamed
from motok.cli.outputs import Force, train_into

# Config classes whose fields' ranges the options below share (motok.ranges.range_of).
TRACKING = "motok.control.tasks.imitation:ImitationTaskConfig"

JsonOut = typer.Option(False, "--json", help="Print the result as JSON (on stdout; progress and notes go to stderr).")

app = typer.Typer(help="Physics-based control: the imitation expert (PPO + AMP), latent priors, task policies.",
                  no_args_is_help=True)
expert_app = typer.Typer(help="The hybrid-latent paper's expert policy (appendix B.2).", no_args_is_help=True)
app.add_typer(expert_app, name="expert")


@expert_app.command("train", epilog=examples(
    "motok control expert train -d runs/bandai2.h5 --clips 'dataset-2_walk_normal*' "
    "--recipe recipes/control/expert.yaml -o runs/expert",
    "motok control expert train -d runs/bandai2.h5 -o runs/expert --resume --until 2000",
    "motok control expert train -d runs/bandai2.h5 --split train --init runs/expert_walk -o runs/expert_all"))
def train_cmd(
    data: Path = data_option("A motion-dataset artifact (.h5)."),
    out: Path = output_option(help="Run folder (checkpoint bundle, metrics.jsonl).", folder=True),
    clips: Optional[str] = clips_option(help="Clip-name glob, e.g. 'dataset-2_walk_normal*'."),
    split: Optional[str] = split_option(help="Only the clips of this split."),
    recipe: Optional[Path] = recipe_option("recipes/control/"),
    sets: list[str] = typer.Option([], "--set", metavar="KEY=VALUE",
                                   help="Override a config key: --set ppo.lr=1e-4 (repeatable)."),
    humanoid: Optional[Path] = typer.Option(None, "--humanoid", help="MJCF (default: built from --data, cached).",
                                            callback=existing),
    resume: bool = Resume, force: bool = Force,
    until: Optional[int] = number_option(None, "--until", help="Stop after this iteration (the LR schedule still "
                                         "spans the recipe's iterations; --resume continues).", within=">= 1"),
    init: Optional[Path] = typer.Option(None, "--init", help="Start from this expert run's weights (fresh "
                                        "optimisers and counters; its humanoid), e.g. one trained on a subset.",
                                        callback=existing),
    device: Optional[str] = Device,
    as_json: bool = JsonOut,
):
    """Train the expert with PPO on r = 0.5 r_im + 0.5 r_style."""
    from motok.control.expert.model import KIND, ExpertConfig
    from motok.control.expert.train import train_from_data
    from motok.resume import resolve_config

    cfg = run(resolve_config, ExpertConfig, recipe, device_sets(device) + sets, out, KIND, resume)
    summary = train_into(out, lambda where: train_from_data(cfg, data, where, clips=clips, split=split,
                                           humanoid=humanoid, resume=resume, until=until, init=init),
                         resume=resume, force=force)
    report(summary, as_json, "control expert train")


@expert_app.command("eval", epilog=examples(
    "motok control expert eval --expert runs/expert --render expert.mp4",
    "motok control expert eval --expert runs/expert -d runs/bandai2.h5 --split test --json"))
@renamed(run="--expert")
def eval_cmd(
    run_dir: Path = typer.Option(..., "--expert", help="A control-expert run folder (from `control expert train`).",
                                 callback=existing),
    data: Optional[Path] = data_option("Dataset (default: the one it was trained on).", required=False),
    clips: Optional[str] = clips_option(help="Clip-name glob (default: the training clips)."),
    split: Optional[str] = split_option(help="The clips of this split of the dataset, with a table per "
                                             "content and per style."),
    render: Optional[Path] = output_option("--render", help="Video of the first clip (.mp4/.gif).",
                                           suffixes=(".mp4", ".gif"), required=False),
    termination: Optional[str] = typer.Option(None, "--termination",
                                              help="Failure test: 'any' body or the 'mean' (default: the run's)."),
    distance: Optional[float] = number_option(None, "--distance", help="Failure distance in m (default: the run's).",
                                              within=f"{TRACKING}.termination_distance"),
    device: Optional[str] = Device,
    as_json: bool = JsonOut,
):
    """Success rate, MPJPE, G-MPJPE, root velocity/acceleration errors per clip and overall; the feet's
    skating, sole slip, sole penetration and jitter beside the clips' own."""
    from motok.control.expert.evaluate import evaluate_run

    res = run(evaluate_run, run_dir, data=data, clips=clips, split=split, render=render, termination=termination,
              distance=distance, device=valid_device(device))
    if as_json:
        print_json(res)
        return
    from rich.table import Table
    cols = {"success": "ok", "seconds": "time s", "mpjpe_mm": "MPJPE", "g_mpjpe_mm": "G-MPJPE",
            "root_vel_err_mm": "vel err", "root_acc_err_mm": "acc err"}
    names = list(res["clips"])
    groups = res["groups"]
    if len(names) > 40:  # a split: one row per content and per style instead of per clip
        for kind in ("content", "style"):
            t = Table(title=f"expert eval of {run_dir} per {kind}" + (f" ({split} split)" if split else "")
                      + "; errors in mm, mm/frame, mm/frame^2")
            t.add_column(kind, no_wrap=True)
            for header in ["clips", *cols.values()]:
                t.add_column(header, justify="right", no_wrap=True, min_width=len(header))
            for g, r in groups[kind].items():
                t.add_row(g, str(r["clips"]), f"{r['success_rate']:.0%}", f"{r['seconds_played']:.0f}",
                          *[f"{r[c]:.1f}" for c in list(cols)[2:]])
            results.print(t)
        _summary_line(res)
        return
    # Clip names share a long prefix (dataset-2_walk_normal_...): print it once, in the header.
    prefix = os.path.commonprefix(names) if len(names) > 1 else ""
    prefix = prefix[: max(prefix.rfind("_"), prefix.rfind("-")) + 1]
    t = Table(title=f"expert eval of {run_dir} on {prefix}*; errors in mm, mm/frame, mm/frame^2" if prefix
              else f"expert eval of {run_dir}; errors in mm, mm/frame, mm/frame^2")
    t.add_column("clip", no_wrap=True, overflow="ellipsis")
    for header in cols.values():
        t.add_column(header, justify="right", no_wrap=True, min_width=len(header))
    fmt = lambda v: ("yes" if v else "no") if isinstance(v, bool) else f"{v:.1f}"  # noqa: E731
    for name, r in res["clips"].items():
        t.add_row(name[len(prefix):], *[fmt(r[c]) for c in cols])
    o = res["overall"]
    t.add_row("[bold]overall", f"{o['success_rate']:.0%}", f"{o['seconds_played']:.1f}",
              *[f"{o[c]:.1f}" for c in list(cols)[2:]])
    results.print(t)
    _summary_line(res)


def _summary_line(res: dict) -> None:
    o = res["overall"]
    results.print(f"{o['clips']} clips, {o['success_rate']:.1%} played to the end ({o['termination']} ends a "
                   f"clip); {o['success_rate_any_body']:.1%} also kept every single body within that distance; "
                   f"MPJPE {o['mpjpe_mm']:.1f} mm, G-MPJPE {o['g_mpjpe_mm']:.1f} mm")
    if "feet" in res:
        f = res["feet"]
        line = lambda w: (f"skating {f[w]['skate_cm_s']:.2f} cm/s, sole slip {f[w]['sole_slip_cm_s']:.1f} cm/s, "  # noqa: E731
                          f"sole penetration {f[w]['sole_penetration_mm']:.1f} mm, jitter {f[w]['jitter_m_s3']:.0f} m/s^3")
        results.print(f"feet, simulated: {line('simulated')}\nfeet, the clips: {line('reference')} "
                      f"(same frames, at the control rate)", soft_wrap=True, highlight=False)
    if "video" in res:
        results.print(f"wrote {res['video']}", soft_wrap=True, highlight=False)


from motok.cli.priors import register  # noqa: E402  (motok control distill)
register(app)

from motok.cli.track import register as register_track  # noqa: E402  (motok control track)
register_track(app)

from motok.cli.tasks import register as register_tasks  # noqa: E402  (motok control train, perturb)
register_tasks(app)
