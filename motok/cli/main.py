"""The ``motok`` command line: the root app, its global options and the commands of the data
stage; each other stage registers its own sub-app (``motok/cli/<stage>.py``). Commands parse
arguments, call one stage function through :func:`motok.cli.common.run` and print its result.
The conventions every command follows (options, aliases, ``--quiet``) are applied to the whole
tree by :class:`motok.cli.conventions.MotokGroup`."""

from __future__ import annotations

import json
import sys
from pathlib import Path
from typing import Optional

import typer

from motok import __version__, progress
from motok.cli.common import (DataRoot, H5, JsonOut, Sets, check_output, choose_mujoco_gl, clips_option, data_option,
                              existing, number_option, output_option, print_json, recipe_option, report, results, run,
                              wrote)
from motok.cli.control import app as control_app
from motok.cli.conventions import MotokGroup, examples, renamed
from motok.cli.eval import app as eval_app
from motok.cli.gpt import app as gpt_app
from motok.cli.sim import app as sim_app
from motok.cli.tokenize import app as tokenize_app
from motok.cli.view import register as register_view

# Config classes whose fields' ranges the options below share (motok.ranges.range_of).
PRE = "motok.data.preprocess:PreprocessConfig"

app = typer.Typer(help="motok: learned human motion, from mocap to tokens, text and physics.",
                  no_args_is_help=True, pretty_exceptions_enable=False, add_completion=False, cls=MotokGroup)
export_app = typer.Typer(help="Export motion to other formats.", no_args_is_help=True)
app.add_typer(export_app, name="export")
app.add_typer(tokenize_app, name="tokenize")
app.add_typer(gpt_app, name="gpt")
app.add_typer(sim_app, name="sim")
app.add_typer(eval_app, name="eval")
app.add_typer(control_app, name="control")
register_view(app)

MotionData = data_option("A motion or motion-dataset artifact (.h5).")
ClipName = typer.Option(..., "--clip", help="Clip name (or index).")


def _version(value: bool):
    if value:
        typer.echo(f"motok {__version__}")
        raise typer.Exit()


@app.callback()
def main(
    version: bool = typer.Option(False, "--version", callback=_version, is_eager=True, help="Show the version."),
    quiet: bool = typer.Option(False, "--quiet", "-q", help="No progress bars or chatter (results and errors are "
                               "still printed); also accepted after the subcommand."),
):
    progress.configure(quiet=quiet)
    # Before any command imports mujoco, which reads MUJOCO_GL once, at import.
    choose_mujoco_gl()


def _clip_key(clip: str):
    return int(clip) if clip.isdigit() else clip


@app.command(epilog=examples(
    "motok preprocess --recipe recipes/preprocess/bandai2.yaml -o runs/bandai2.h5",
    "motok preprocess -d my_take.bvh -d more_takes/ -o mine.h5   (no captions, split 'none')",
    "motok preprocess -d my_takes/ --annotations my_annotations/ -o mine.h5",
    "motok preprocess -d HumanML3D/ -o humanml3d.h5   (a new_joint_vecs/ folder: features, texts, splits, Mean/Std)"))
@renamed(i="--data", input="--data", pattern="--clips")
def preprocess(
    out: Path = output_option(help="Output motion-dataset (.h5).", suffixes=H5),
    inputs: list[Path] = typer.Option([], "--data", "-d", metavar="PATH",
                                     help="Mocap to read: a .bvh or .npy file, a folder or a .zip/.tar.* archive "
                                          "(repeatable), or one HumanML3D folder (new_joint_vecs/, read as it is). "
                                          "Default: Bandai-Namco set 2 in the data root."),
    annotations: Optional[str] = typer.Option(None, "--annotations", metavar="DIR|none",
                                              help="HumanML3D-layout captions and splits. Default: the "
                                                   "Bandai-Namco annotations for the Bandai-Namco archives only; "
                                                   "any other input gets no captions and the split 'none'."),
    clips: Optional[str] = clips_option(help="Only clips whose name matches, e.g. 'dataset-2_walk_*'."),
    skeleton: Optional[str] = typer.Option(None, "--skeleton", help="smpl22, bandai21 or a YAML path "
                                           "(default: detected from the joint names)."),
    fps: Optional[float] = number_option(None, "--fps", help="Target frame rate, > 0 (default 20).",
                                         within=f"{PRE}.fps"),
    npy_fps: Optional[float] = number_option(None, "--npy-fps", help="Frame rate of .npy joint arrays, which store "
                                             "none (default 20, HumanML3D's).", within=f"{PRE}.npy_fps"),
    legacy: bool = typer.Option(False, "--legacy", help="Reproduce the official HumanML3D quirks."),
    skip_bad: bool = typer.Option(False, "--skip-bad", help="Skip bad inputs instead of stopping (each is "
                                  "listed, with why, in the summary and the provenance)."),
    jobs: Optional[int] = number_option(None, "-j", "--jobs", help="Worker processes.", within=f"{PRE}.jobs"),
    limit: Optional[int] = number_option(None, "--limit", help="Only the first N clips (smoke runs).",
                                         within=f"{PRE}.limit"),
    recipe: Optional[Path] = recipe_option("recipes/preprocess/"), sets: list[str] = Sets,
    data_root: Optional[Path] = DataRoot, as_json: bool = JsonOut,
):
    """Mocap (BVH or joint arrays) to HumanML3D-style features with captions, splits and statistics."""
    from motok.config import load_config
    from motok.data.preprocess import PreprocessConfig
    from motok.data.preprocess import preprocess as _preprocess

    flags = {"data": [str(p) for p in inputs] or None, "annotations": annotations, "clips": clips, "skeleton": skeleton,
             "fps": fps, "npy_fps": npy_fps, "jobs": jobs, "limit": limit}
    overrides = list(sets) + [f"{k}={json.dumps(v)}" for k, v in flags.items() if v is not None]
    overrides += ["legacy=true"] * legacy + ["skip_bad=true"] * skip_bad
    cfg = run(load_config, PreprocessConfig, recipe, overrides)
    summary = run(_preprocess, cfg, out, data_root)
    report(summary, as_json, "preprocess", cells={"skipped": _skipped})


def _skipped(skipped: list[dict]) -> str:
    more = f"\n  ... and {len(skipped) - 10} more (all in the provenance)" if len(skipped) > 10 else ""
    return f"{len(skipped)}" + "".join(f"\n  {s['input']}: {s['error']}" for s in skipped[:10]) + more


@app.command(epilog=examples("motok info runs/bandai2.h5 --max-captions 5",
                             "motok info runs/gpt/   (a checkpoint bundle)"))
@renamed(captions="--max-captions")
def info(path: Path = typer.Argument(..., help="Any motok artifact (.h5) or checkpoint folder.", callback=existing),
         as_json: bool = JsonOut,
         captions: int = number_option(3, "--max-captions", help="How many captions to show.", within=">= 0")):
    """Print what a file holds: kind, version, provenance; datasets, splits and captions of an
    artifact; config, references and tensors (shapes, parameters, verified hash) of a bundle."""
    from motok.info import describe, print_description
    d = run(describe, path, captions)
    if as_json:
        print_json(d)
    else:
        print_description(d, results)


@app.command(epilog=examples(
    "motok render -d runs/bandai2.h5 --clip dataset-2_walk_normal_001 -o walk.gif",
    "motok render -d walk_generated.h5 --clip 0 -o sheet.png --max-frames 40"))
@renamed(positional="--data")
def render(
    data: Path = MotionData, clip: str = ClipName,
    out: Path = output_option(help="Output .gif, .mp4 or .png (a contact sheet).", suffixes=(".gif", ".mp4", ".png")),
    max_frames: Optional[int] = number_option(None, "--max-frames", help="Only the first N frames.", within=">= 1"),
    as_json: bool = JsonOut,
):
    """Render a clip as a 3D stick figure with floor grid, root trajectory and caption."""
    from motok.render.clip import render_artifact_clip
    written = run(render_artifact_clip, data, _clip_key(clip), out, max_frames)
    wrote({"output": str(written), "data": str(data), "clip": clip}, as_json)


@export_app.command("bvh", epilog=examples(
    "motok export bvh -d runs/bandai2.h5 --clip dataset-2_walk_normal_001 -o walk.bvh",
    "motok export bvh -d walk_generated.h5 --clip 0 -o walk.bvh --order XYZ"))
@renamed(positional="--data")
def export_bvh_cmd(
    data: Path = MotionData, clip: str = ClipName,
    out: Path = output_option(help="Output .bvh (centimetres, Y up).", suffixes=(".bvh",)),
    order: str = typer.Option("ZXY", "--order", help="Euler order of the rotation channels (ZXY or XYZ, ...)."),
    as_json: bool = JsonOut,
):
    """Export a clip as BVH (centimetres, Y up) for Blender and game engines."""
    from motok.data.export import export_clip
    written = run(export_clip, data, _clip_key(clip), out, order)
    wrote({"output": str(written), "data": str(data), "clip": clip, "order": order}, as_json)


@export_app.command("humanml3d", epilog=examples(
    "motok export humanml3d -d runs/bandai2.h5 -o runs/bandai2_humanml3d",
    "motok export humanml3d -d runs/bandai2.h5 --clips 'dataset-2_walk_*' --stats all -o walks/",
    "motok preprocess -d runs/bandai2_humanml3d -o back.h5   (and back into motok)"))
def export_humanml3d_cmd(
    data: Path = MotionData,
    out: Path = output_option(help="Output folder, new or empty: new_joint_vecs/, new_joints/, texts/, split "
                              "files, Mean.npy, Std.npy.", folder=True),
    clips: Optional[str] = clips_option(help="Only clips whose name matches."),
    stats: str = typer.Option("train", "--stats", metavar="train|all", help="Mean.npy/Std.npy over the train split "
                              "(default) or over every exported clip (as HumanML3D's own script)."),
    as_json: bool = JsonOut,
):
    """Export a data set as a HumanML3D folder, for T2M-GPT, MoMask and Guo et al.'s evaluator."""
    from motok.data.humanml3d_folder import export_humanml3d
    summary = run(export_humanml3d, data, out, clips=clips, stats=stats)
    report(summary, as_json, "export humanml3d")


@app.command(epilog=examples("motok plot runs/gpt", "motok plot runs/expert --keys success,mpjpe_mm --x samples "
                             "--x2 wall_s --smooth 0.9 -o expert.png",
                             "motok plot runs/prior_hybrid runs/prior_continuous --keys eval_success,action_loss "
                             "--x samples --log action_loss -o priors.png",
                             "motok plot runs/gpt --tensorboard runs/tb   (then: tensorboard --logdir runs/tb)"))
def plot(ctx: typer.Context,
         metrics: list[Path] = typer.Argument(..., help="A run folder or its metrics.jsonl; several are drawn "
                                                          "on the same subplots.", callback=existing),
         out: Optional[Path] = output_option(help="Output .png (default RUN/curves.png; required for several runs).",
                                             suffixes=(".png",), required=False),
         label: Optional[list[str]] = typer.Option(None, "--label", help="Legend name of each run, in order "
                                                                         "(default: the folder names)."),
         keys: Optional[str] = typer.Option(None, "--keys", help="Comma-separated metrics (default: all)."),
         x: str = typer.Option("iteration", "--x", help="Field on the x axis, e.g. samples."),
         x2: Optional[str] = typer.Option(None, "--x2", help="Second x axis on top, e.g. wall_s."),
         smooth: float = number_option(0.0, "--smooth", help="EMA weight in [0, 1) for a smoothed curve.",
                                       within="[0, 1)"),
         log: Optional[str] = typer.Option(None, "--log", help="Comma-separated metrics drawn on a log y axis "
                                           "(losses, errors)."),
         missing_ok: bool = typer.Option(False, "--missing-ok", help="Leave out, with a warning, --keys that no "
                                         "run has logged yet (at least one must be there)."),
         tensorboard: Optional[Path] = output_option("--tensorboard", help="Also write the metrics as TensorBoard "
                                                     "event files into DIR/RUN_NAME/ (pip install "
                                                     "'motok\\[tensorboard]').", folder=True, required=False),
         as_json: bool = JsonOut):
    """Plot training curves from metrics JSONL to PNG: one labelled panel per quantity, its training,
    validation and evaluation values overlaid; several runs on the same subplots to compare them."""
    from motok.render.plot import default_output, plot_run
    if out is None and len(metrics) == 1:  # the default output gets the checks of -o, before any work
        out = run(default_output, metrics[0])
        check_output(ctx, out, "-o/--out (default RUN/curves.png)", suffixes=(".png",))
    names = [k.strip() for k in keys.split(",") if k.strip()] if keys else None
    logy = [k.strip() for k in log.split(",") if k.strip()] if log else False
    dst = run(plot_run, list(metrics), out, names, x, label or None, smooth=smooth, x2=x2, missing_ok=missing_ok,
              logy=logy)
    src = [str(m) for m in metrics]
    summary = {"output": str(dst), "metrics": src[0] if len(src) == 1 else src, "keys": names, "x": x, "x2": x2}
    if tensorboard is not None:
        from motok.render.plot import run_sources
        from motok.render.tensorboard import write_events
        events = run(write_events, run(run_sources, list(metrics), label or None), tensorboard, x)
        summary["tensorboard"] = [str(p) for p in events]
    wrote(summary, as_json, dst, *summary.get("tensorboard", []))


if __name__ == "__main__":  # pragma: no cover
    sys.exit(app())
