"""``motok sim``: the MuJoCo humanoid, reference replays and the plain-PD tracking baseline.

Argument parsing only; the work is in ``motok.sim``.
"""

from __future__ import annotations

from pathlib import Path
from typing import Optional

import typer

from motok.cli.common import (JsonOut, clips_option, data_option, existing, fail, number_option, output_option,
                              print_json, report, run, wrote)
from motok.cli.conventions import examples, renamed

# Config classes whose fields' ranges the options below share (motok.ranges.range_of).
HUMANOID = "motok.sim.humanoid:HumanoidConfig"
SIM = "motok.sim.env:SimConfig"

app = typer.Typer(help="Physics: the MuJoCo humanoid built from a dataset's skeleton, and its reference motions.",
                  no_args_is_help=True)

VIDEO = (".mp4", ".gif")
Data = data_option("A motion-dataset artifact (.h5).")
HumanoidOpt = typer.Option(None, "--humanoid", help="Humanoid MJCF (default: built from --data once and cached).",
                           callback=existing)
Hz = number_option(None, "--hz", help="Control rate in Hz (default: the humanoid's, 30).", within=f"{SIM}.control_hz")
Sets = typer.Option([], "--set", metavar="KEY=VALUE", help="Override a HumanoidConfig key (repeatable).")
Stick = typer.Option(False, "--stick", help="Draw the stick figure instead of MuJoCo's renderer.")


def _key(clip: str):
    return int(clip) if clip.isdigit() else clip


def _setup(data: Path, humanoid: Optional[Path], hz: Optional[float], clips):
    from motok.sim.humanoid import load_humanoid
    from motok.sim.reference import humanoid_for, load_library

    hum = load_humanoid(humanoid) if humanoid else humanoid_for(data)
    return hum, load_library(hum, data, control_hz=hz, clips=clips)


@app.command("build-humanoid", epilog=examples("motok sim build-humanoid -d runs/bandai2.h5 -o humanoid.xml",
                                               "motok sim build-humanoid -d runs/bandai2.h5 --total-mass 70 -o heavy.xml"))
@renamed(mass="--total-mass")
def build_humanoid_cmd(
    data: Path = Data,
    out: Path = output_option(help="Output MJCF (.xml).", suffixes=(".xml",)),
    mass: Optional[float] = number_option(None, "--total-mass", help="Total mass in kg (default 65).",
                                          within=f"{HUMANOID}.total_mass"),
    timestep: Optional[float] = number_option(None, "--timestep", help="Physics timestep in s (default 1/120).",
                                              within=f"{HUMANOID}.timestep"),
    sets: list[str] = Sets,
    as_json: bool = JsonOut,
):
    """An MJCF humanoid from the dataset's skeleton: capsules, box feet, ranges from the data, PD actuators."""
    from motok.config import load_config
    from motok.sim.humanoid import HumanoidConfig
    from motok.sim.mjcf import build_humanoid

    flags = {"total_mass": mass, "timestep": timestep}
    cfg = run(load_config, HumanoidConfig, None, list(sets) + [f"{k}={v}" for k, v in flags.items() if v is not None])
    summary = run(build_humanoid, data, out, cfg)
    report(summary, as_json, "build-humanoid")


@app.command(epilog=examples("motok sim replay -d runs/bandai2.h5 --clip dataset-2_walk_normal_001 -o walk.mp4",
                             "motok sim replay -d runs/bandai2.h5 --clip 3 -o walk.gif --stick --max-frames 60"))
def replay(
    data: Path = Data,
    clip: str = typer.Option(..., "--clip", help="Clip name (or index)."),
    out: Path = output_option(help="Output .mp4 or .gif.", suffixes=VIDEO),
    humanoid: Optional[Path] = HumanoidOpt,
    hz: Optional[float] = Hz,
    max_frames: Optional[int] = number_option(None, "--max-frames", help="Only the first N frames.", within=">= 1"),
    stick: bool = Stick,
    as_json: bool = JsonOut,
):
    """Play a reference clip kinematically in MuJoCo and render it offscreen."""
    def go():
        from motok.sim.render import render_trajectory
        hum, lib = _setup(data, humanoid, hz, [_key(clip)])
        qpos = lib.clip(0)["qpos"][:max_frames]
        path, backend = render_trajectory(hum, qpos, out, lib.fps, title=lib.names[0],
                                          backend="stick" if stick else "auto")
        return {"output": str(path), "renderer": backend, "clip": lib.names[0], "frames": len(qpos)}

    summary = run(go)
    wrote(summary, as_json, f"{summary['output']} ({summary['renderer']} renderer)")


@app.command("pd-track", epilog=examples(
    "motok sim pd-track -d runs/bandai2.h5 --clips 'dataset-2_walk_*'",
    "motok sim pd-track -d runs/bandai2.h5 --clip dataset-2_walk_normal_001 --render pd.mp4 --seconds 5"))
@renamed(o="--render", out="--render")
def pd_track_cmd(
    data: Path = Data,
    clip: Optional[str] = typer.Option(None, "--clip", help="One clip (name or index); needed for --render."),
    clips: Optional[str] = clips_option(help="A clip-name glob (default: every clip)."),
    render: Optional[Path] = output_option("--render", help="Video of the tracking, its reference as a ghost "
                                           "(.mp4/.gif); one clip only.", suffixes=VIDEO, required=False),
    humanoid: Optional[Path] = HumanoidOpt,
    hz: Optional[float] = Hz,
    seconds: Optional[float] = number_option(None, "--seconds", help="Track at most this long, > 0 (default: whole "
                                             "clip).", within="> 0"),
    stick: bool = Stick,
    as_json: bool = JsonOut,
):
    """Track a reference with plain PD (no policy) and report how long the humanoid stays up."""
    if clip == "all":  # the old spelling of "every clip"
        clip = None
    if clip is not None and clips is not None:
        fail("give --clip (one clip) or --clips (a glob), not both")
    if render is not None and clip is None:
        fail("--render draws one clip: pass --clip NAME")
    if seconds is not None and not seconds > 0:
        fail(f"--seconds {seconds} must be > 0")

    def go():
        from motok.control.expert.baselines import pd_track_run
        from motok.data.dataset import select_clips
        chosen = [_key(clip)] if clip is not None else (select_clips(data, clips) if clips else None)
        return pd_track_run(*_setup(data, humanoid, hz, chosen), seconds, render, stick)

    summary = run(go)
    if as_json:
        print_json(summary)
        return
    short = {k: v for k, v in summary.items() if k != "per_clip"}
    if len(summary["per_clip"]) <= 5:
        short.update({f"survival {k}": f"{v} s" for k, v in summary["per_clip"].items()})
    report(short, False, "pd-track")
