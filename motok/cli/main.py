"""The ``motok`` command line: parses arguments and calls into the stages, nothing more."""

from __future__ import annotations

import json
import sys
from pathlib import Path
from typing import Optional

import typer

from motok import __version__
from motok import progress as _progress

app = typer.Typer(help="motok: learned human motion, from mocap to tokens, text and physics.",
                  no_args_is_help=True, pretty_exceptions_enable=False, add_completion=False)
export_app = typer.Typer(help="Export motion to other formats.", no_args_is_help=True)
app.add_typer(export_app, name="export")
from motok.cli.tokenize import app as tokenize_app
app.add_typer(tokenize_app, name="tokenize")
from motok.cli.gpt import app as gpt_app
app.add_typer(gpt_app, name="gpt")
from motok.cli.sim import app as sim_app
app.add_typer(sim_app, name="sim")
from motok.cli.eval import app as eval_app
app.add_typer(eval_app, name="eval")
from motok.cli.control import app as control_app
app.add_typer(control_app, name="control")

DataRoot = typer.Option(None, "--data-root", help="Data folder (else $MOTOK_DATA, else ../shared/datasets).")
Recipe = typer.Option(None, "--recipe", help="YAML recipe (see recipes/).")
Sets = typer.Option([], "--set", help="Override a config key: --set key=value (repeatable).")
JsonOut = typer.Option(False, "--json", help="Print the result as JSON.")


def _version(value: bool):
    if value:
        typer.echo(f"motok {__version__}")
        raise typer.Exit()


@app.callback()
def main(
    version: bool = typer.Option(False, "--version", callback=_version, is_eager=True, help="Show the version."),
    quiet: bool = typer.Option(False, "--quiet", "-q", help="No progress bars or chatter."),
):
    _progress.QUIET = quiet


def fail(msg: str, code: int = 2):
    from rich.markup import escape
    _progress.console.print(f"[bold red]error:[/] {escape(msg)}", highlight=False, soft_wrap=True)
    raise typer.Exit(code)


def run(fn, *args, catch: tuple[type[BaseException], ...] = (), **kwargs):
    """Call into a stage, turning the errors users cause into one clear line and exit code 2.
    A stage's own CLI adds its error types with ``catch``."""
    from motok.artifacts import ArtifactError
    from motok.config import ConfigError
    from motok.data.bvh import MotionFormatError
    from motok.data.root import DataRootError
    from motok.data.skeleton import SkeletonError
    try:
        return fn(*args, **kwargs)
    except (ArtifactError, ConfigError, MotionFormatError, DataRootError, SkeletonError, FileNotFoundError,
            KeyError, *catch) as e:
        fail(str(e.args[0]) if isinstance(e, KeyError) and e.args else str(e))


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
    recipe: Optional[Path] = Recipe, sets: list[str] = Sets, data_root: Optional[Path] = DataRoot,
    as_json: bool = JsonOut,
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
    _report(summary, as_json, title="preprocess")


def _report(summary: dict, as_json: bool, title: str):
    if as_json:
        typer.echo(json.dumps(summary, indent=2, default=str))
        return
    from rich.table import Table
    t = Table(title=title, show_header=False)
    for k, v in summary.items():
        if k == "skipped":
            v = f"{len(v)}" + "".join(f"\n  {s['input']}: {s['error']}" for s in v[:10])
        t.add_row(k, str(v))
    _progress.console.print(t)


@app.command()
def info(path: Path = typer.Argument(..., help="Any motok artifact."), as_json: bool = JsonOut,
         captions: int = typer.Option(3, "--captions", help="How many captions to show.")):
    """Print an artifact: kind, version, provenance, datasets, split sizes, a few captions."""
    from motok.info import describe
    d = run(describe, path, captions)
    if as_json:
        typer.echo(json.dumps(d, indent=2, default=str))
    else:
        from motok.info import print_description
        print_description(d, _progress.console)


@app.command()
def render(
    path: Path = typer.Argument(..., help="A motion or motion-dataset artifact."),
    clip: str = typer.Option(..., "--clip", help="Clip name (or index)."),
    out: Path = typer.Option(..., "-o", "--out", help="Output .gif, .mp4 or .png (contact sheet)."),
    max_frames: Optional[int] = typer.Option(None, "--max-frames"),
):
    """Render a clip as a 3D stick figure with floor grid, root trajectory and caption."""
    from motok.data.dataset import MotionFile
    from motok.render.stick import render_motion

    def go():
        with MotionFile(path) as mf:
            key = int(clip) if clip.isdigit() else clip
            c = mf.clip(key)
            sk = mf.skeleton
            title = c.captions[0][0] if c.captions else c.name
            contacts = c.features[:, -4:]
            feet = list(sk.feet_left) + list(sk.feet_right)
            return render_motion(c.joints, sk.parents, out, fps=mf.fps, title=title, contacts=contacts,
                                 foot_joints=feet, max_frames=max_frames)
    written = run(go)
    _progress.info(f"wrote {written}")


@export_app.command("bvh")
def export_bvh_cmd(
    path: Path = typer.Argument(..., help="A motion or motion-dataset artifact."),
    clip: str = typer.Option(..., "--clip", help="Clip name (or index)."),
    out: Path = typer.Option(..., "-o", "--out", help="Output .bvh"),
    order: str = typer.Option("ZXY", "--order", help="Euler order of the rotation channels (ZXY or XYZ, ...)."),
):
    """Export a clip as BVH (centimetres, Y up) for Blender and game engines."""
    from motok.data.dataset import MotionFile
    from motok.data.export import export_bvh

    if sorted(order.upper()) != ["X", "Y", "Z"]:
        fail(f"--order {order!r} must be a permutation of XYZ")

    def go():
        with MotionFile(path) as mf:
            key = int(clip) if clip.isdigit() else clip
            c = mf.clip(key)
            return export_bvh(out, c.joints, mf.skeleton, mf.offsets, mf.fps, order=order.upper())
    written = run(go)
    _progress.info(f"wrote {written}")


@app.command()
def plot(metrics: Path = typer.Argument(..., help="A run folder or its metrics.jsonl."),
         out: Optional[Path] = typer.Option(None, "-o", "--out", help="PNG (default RUN/curves.png)."),
         keys: Optional[str] = typer.Option(None, "--keys", help="Comma-separated metrics (default: all)."),
         x: str = typer.Option("iteration", "--x", help="Field on the x axis, e.g. samples."),
         x2: Optional[str] = typer.Option(None, "--x2", help="Second x axis on top, e.g. wall_s."),
         smooth: float = typer.Option(0.0, "--smooth", help="EMA weight in [0, 1) for a smoothed curve.")):
    """Plot training curves from a metrics JSONL to PNG."""
    from motok.render.plot import plot_curves
    src = metrics / "metrics.jsonl" if metrics.is_dir() else metrics
    dst = out or src.with_name("curves.png")
    names = [k.strip() for k in keys.split(",") if k.strip()] if keys else None
    run(plot_curves, src, dst, names, x, smooth=smooth, x2=x2)
    _progress.info(f"wrote {dst}")


if __name__ == "__main__":  # pragma: no cover
    sys.exit(app())
