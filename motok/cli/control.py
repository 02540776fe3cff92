"""``motok control``: physics-based controllers. ``expert train`` / ``expert eval`` parse
arguments only; the work is in ``motok.control.expert``."""

from __future__ import annotations

import json
import os
from pathlib import Path
from typing import Optional

import typer

from motok import progress as _progress

app = typer.Typer(help="Physics-based control: the imitation expert (PPO + AMP).", no_args_is_help=True)
expert_app = typer.Typer(help="The hybrid-latent paper's expert policy (appendix B.2).", no_args_is_help=True)
app.add_typer(expert_app, name="expert")


def _run(fn, *args, **kwargs):
    """User errors become one line and exit code 2 (the root CLI's convention)."""
    from motok.checkpoint import CheckpointError
    from motok.sim.humanoid import HumanoidError
    from motok.cli.main import run
    return run(fn, *args, catch=(CheckpointError, HumanoidError, ValueError), **kwargs)


@expert_app.command("train")
def train_cmd(
    data: Path = typer.Option(..., "--data", help="A motion-dataset artifact (.h5)."),
    out: Path = typer.Option(..., "-o", "--out", help="Run folder (checkpoint bundle, metrics.jsonl)."),
    clips: Optional[str] = typer.Option(None, "--clips", help="Clip-name glob, e.g. 'dataset-2_walk_normal*'."),
    recipe: Optional[Path] = typer.Option(None, "--recipe", help="YAML recipe (recipes/control/)."),
    sets: list[str] = typer.Option([], "--set", help="Override a config key: --set ppo.lr=1e-4 (repeatable)."),
    humanoid: Optional[Path] = typer.Option(None, "--humanoid", help="MJCF (default: built from --data, cached)."),
    resume: bool = typer.Option(False, "--resume", help="Continue the run in -o exactly where it stopped."),
    until: Optional[int] = typer.Option(None, "--until", help="Stop after this iteration (the LR schedule still "
                                        "spans the recipe's iterations; --resume continues)."),
    as_json: bool = typer.Option(False, "--json", help="Print the summary as JSON."),
):
    """Train the expert with PPO on r = 0.5 r_im + 0.5 r_style."""
    from motok.cli.main import _report
    from motok.config import load_config
    from motok.control.expert import ExpertConfig, select_clips, train

    cfg = _run(load_config, ExpertConfig, recipe, sets)

    def go():
        from motok.sim.humanoid import load_humanoid
        from motok.sim.reference import humanoid_for, load_library
        hum = load_humanoid(out / "humanoid.xml") if resume and (out / "humanoid.xml").exists() else (
            load_humanoid(humanoid) if humanoid else humanoid_for(data))
        lib = load_library(hum, data, control_hz=cfg.env.control_hz, clips=select_clips(data, clips))
        return train(cfg, out, hum, lib, resume=resume, until=until, data=data)

    _report(_run(go), as_json, title="control expert train")


@expert_app.command("eval")
def eval_cmd(
    run_dir: Path = typer.Option(..., "--run", help="A control-expert run folder."),
    data: Optional[Path] = typer.Option(None, "--data", help="Dataset (default: the one it was trained on)."),
    clips: Optional[str] = typer.Option(None, "--clips", help="Clip-name glob (default: the training clips)."),
    render: Optional[Path] = typer.Option(None, "--render", help="Video of the first clip (.mp4/.gif)."),
    termination: Optional[str] = typer.Option(None, "--termination",
                                              help="Failure test: 'any' body or the 'mean' (default: the run's)."),
    distance: Optional[float] = typer.Option(None, "--distance", help="Failure distance in m (default: the run's)."),
    as_json: bool = typer.Option(False, "--json", help="Print the full results as JSON."),
):
    """Success rate, MPJPE, G-MPJPE, root velocity/acceleration errors per clip and overall."""
    from motok.control.evaluate import evaluate_run

    res = _run(evaluate_run, run_dir, data=data, clips=clips, render=render, termination=termination,
               distance=distance)
    if as_json:
        typer.echo(json.dumps(res, indent=2))
        return
    from rich.table import Table
    cols = {"success": "ok", "seconds": "time s", "mpjpe_mm": "MPJPE", "g_mpjpe_mm": "G-MPJPE",
            "root_vel_err_mm": "vel err", "root_acc_err_mm": "acc err"}
    names = list(res["clips"])
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
    _progress.console.print(t)
    _progress.info(f"success: {o['termination']} ends a clip; {o['success_rate_any_body']:.0%} also kept every "
                   "single body within that distance")
    if "video" in res:
        _progress.info(f"wrote {res['video']}")
