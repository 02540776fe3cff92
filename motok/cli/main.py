"""The ``motok`` command line: the root app, its global options and the commands of the data
stage; each other stage registers its own sub-app (``motok/cli/<stage>.py``). Commands parse
arguments, call one stage function through :func:`motok.cli.common.run` and print its result."""

from __future__ import annotations

import json
import sys
from pathlib import Path
from typing import Optional

import typer

from motok import __version__, progress
from motok.cli.common import DataRoot, JsonOut, Sets, choose_mujoco_gl, existing, recipe_option, report, run
from motok.cli.control import app as control_app
from motok.cli.eval import app as eval_app
from motok.cli.gpt import app as gpt_app
from motok.cli.sim import app as sim_app
from motok.cli.tokenize import app as tokenize_app

app = typer.Typer(help="motok: learned human motion, from mocap to tokens, text and physics.",
                  no_args_is_help=True, pretty_exceptions_enable=False, add_completion=False)
export_app = typer.Typer(help="Export motion to other formats.", no_args_is_help=True)
app.add_typer(export_app, name="export")
app.add_typer(tokenize_app, name="tokenize")
app.add_typer(gpt_app, name="gpt")
app.add_typer(sim_app, name="sim")
app.add_typer(eval_app, name="eval")
app.add_typer(control_app, name="control")

Artifact = typer.Argument(..., help="A motion or motion-dataset artifact.", callback=existing)
ClipName = typer.Option(..., "--clip", help="Clip name (or index).")


def _version(value: bool):
    if value:
        typer.echo(f"motok {__version__}")
        raise typer.Exit()


@app.callback()
def main(
    version: bool = typer.Option(False, "--version", callback=_version, is_eager=True, help="Show the version."),
    quiet: bool = typer.Option(False, "--quiet", "-q", help="No progress bars or chatter."),
):
    progress.configure(quiet=quiet)
    # Before any command imports mujoco, which reads MUJOCO_GL once, at import.
    choose_mujoco_gl()


def _clip_key(clip: str):
    return int(clip) if clip.isdigit() else clip


@app.command()
def preprocess(
    out: Path = typer.Option(..., "-o", "--out", help="Output motion-dataset (.h5)."),
    inputs: list[str] = typer.Option([], "--input", "-i", help="BVH/npy file, folder or archive (repeatable)."),
    annotations: Optional[str] = typer.Option(None, "--annotations", help="HumanML3D-layout captions and splits."),
    pattern: Optional[str] = typer.Option(None, "--pattern", help="Clip-name glob, e.g. 'dataset-2_walk_*'."),
    skeleton: Optional[str] = typer.Option(None, "--skeleton", help="smpl22, bandai21 or a YAML path."),
    fps: Optional[float] = typer.Option(None, "--fps", help="Target frame rate (default 20)."),
    legacy: bool = typer.Option(False, "--legacy", help="Reproduce the official HumanML3D quirks."),
    skip_bad: bool = typer.Option(False, "--skip-bad", help="Skip bad inputs (listed in provenance)."),
    jobs: Optional[int] = typer.Option(None, "-j", "--jobs", help="Worker processes."),
    limit: Optional[int] = typer.Option(None, "--limit", help="Only the first N clips (smoke runs)."),
    recipe: Optional[Path] = recipe_option("recipes/preprocess/"), sets: list[str] = Sets,
    data_root: Optional[Path] = DataRoot, as_json: bool = JsonOut,
):
    """Mocap (BVH or joint arrays) to HumanML3D-style features with captions, splits and statistics."""
    from motok.config import load_config
    from motok.data.preprocess import PreprocessConfig
    from motok.data.preprocess import preprocess as _preprocess

    flags = {"inputs": inputs or None, "annotations": annotations, "pattern": pattern, "skeleton": skeleton,
             "fps": fps, "jobs": jobs, "limit": limit}
    overrides = list(sets) + [f"{k}={json.dumps(v)}" for k, v in flags.items() if v is not None]
    overrides += ["legacy=true"] * legacy + ["skip_bad=true"] * skip_bad
    cfg = run(load_config, PreprocessConfig, recipe, overrides)
    summary = run(_preprocess, cfg, out, data_root)
    report(summary, as_json, "preprocess", cells={"skipped": _skipped})


def _skipped(skipped: list[dict]) -> str:
    return f"{len(skipped)}" + "".join(f"\n  {s['input']}: {s['error']}" for s in skipped[:10])


@app.command()
def info(path: Path = typer.Argument(..., help="Any motok artifact.", callback=existing), as_json: bool = JsonOut,
         captions: int = typer.Option(3, "--captions", help="How many captions to show.")):
    """Print an artifact: kind, version, provenance, datasets, split sizes, a few captions."""
    from motok.info import describe, print_description
    d = run(describe, path, captions)
    if as_json:
        typer.echo(json.dumps(d, indent=2, default=str))
    else:
        print_description(d, progress.console)


@app.command()
def render(
    path: Path = Artifact, clip: str = ClipName,
    out: Path = typer.Option(..., "-o", "--out", help="Output .gif, .mp4 or .png (contact sheet)."),
    max_frames: Optional[int] = typer.Option(None, "--max-frames", min=1),
):
    """Render a clip as a 3D stick figure with floor grid, root trajectory and caption."""
    from motok.render.clip import render_artifact_clip
    written = run(render_artifact_clip, path, _clip_key(clip), out, max_frames)
    progress.info(f"wrote {written}")


@export_app.command("bvh")
def export_bvh_cmd(
    path: Path = Artifact, clip: str = ClipName,
    out: Path = typer.Option(..., "-o", "--out", help="Output .bvh"),
    order: str = typer.Option("ZXY", "--order", help="Euler order of the rotation channels (ZXY or XYZ, ...)."),
):
    """Export a clip as BVH (centimetres, Y up) for Blender and game engines."""
    from motok.data.export import export_clip
    written = run(export_clip, path, _clip_key(clip), out, order)
    progress.info(f"wrote {written}")


@app.command()
def plot(metrics: Path = typer.Argument(..., help="A run folder or its metrics.jsonl.", callback=existing),
         out: Optional[Path] = typer.Option(None, "-o", "--out", help="PNG (default RUN/curves.png)."),
         keys: Optional[str] = typer.Option(None, "--keys", help="Comma-separated metrics (default: all)."),
         x: str = typer.Option("iteration", "--x", help="Field on the x axis, e.g. samples."),
         x2: Optional[str] = typer.Option(None, "--x2", help="Second x axis on top, e.g. wall_s."),
         smooth: float = typer.Option(0.0, "--smooth", help="EMA weight in [0, 1) for a smoothed curve.")):
    """Plot training curves from a metrics JSONL to PNG."""
    from motok.render.plot import plot_run
    names = [k.strip() for k in keys.split(",") if k.strip()] if keys else None
    dst = run(plot_run, metrics, out, names, x, smooth=smooth, x2=x2)
    progress.info(f"wrote {dst}")


if __name__ == "__main__":  # pragma: no cover
    sys.exit(app())
