"""``motok sim``: the MuJoCo humanoid, reference replays and the plain-PD tracking baseline.

Argument parsing only; the work is in ``motok.sim``.
"""

from __future__ import annotations

from pathlib import Path
from typing import Optional

import typer

from motok import progress as _progress
from motok.cli.common import fail, input_option, print_json, report, run

app = typer.Typer(help="Physics: the MuJoCo humanoid built from a dataset's skeleton, and its reference motions.",
                  no_args_is_help=True)

Data = input_option("--data", help="A motion-dataset artifact (.h5).")
HumanoidOpt = typer.Option(None, "--humanoid", help="Humanoid MJCF (default: built from --data once and cached).")
Hz = typer.Option(None, "--hz", help="Control rate in Hz (default: the humanoid's, 30).")
Sets = typer.Option([], "--set", help="Override a HumanoidConfig key: --set key=value (repeatable).")


def _setup(data: Path, humanoid: Optional[Path], hz: Optional[float], clips):
    from motok.sim.humanoid import load_humanoid
    from motok.sim.reference import humanoid_for, load_library

    hum = load_humanoid(humanoid) if humanoid else humanoid_for(data)
    return hum, load_library(hum, data, control_hz=hz, clips=clips)


@app.command("build-humanoid")
def build_humanoid_cmd(
    data: Path = Data,
    out: Path = typer.Option(..., "-o", "--out", help="Output MJCF (.xml)."),
    mass: Optional[float] = typer.Option(None, "--mass", help="Total mass in kg (default 65)."),
    timestep: Optional[float] = typer.Option(None, "--timestep", help="Physics timestep in s (default 1/120)."),
    sets: list[str] = Sets,
    as_json: bool = typer.Option(False, "--json", help="Print the summary as JSON."),
):
    """An MJCF humanoid from the dataset's skeleton: capsules, box feet, ranges from the data, PD actuators."""
    from motok.config import load_config
    from motok.sim.humanoid import HumanoidConfig
    from motok.sim.mjcf import build_humanoid

    flags = {"total_mass": mass, "timestep": timestep}
    cfg = run(load_config, HumanoidConfig, None, list(sets) + [f"{k}={v}" for k, v in flags.items() if v is not None])
    summary = run(build_humanoid, data, out, cfg)
    report(summary, as_json, "build-humanoid")


@app.command()
def replay(
    data: Path = Data,
    clip: str = typer.Option(..., "--clip", help="Clip name (or index)."),
    out: Path = typer.Option(..., "-o", "--out", help="Output .mp4 or .gif."),
    humanoid: Optional[Path] = HumanoidOpt,
    hz: Optional[float] = Hz,
    max_frames: Optional[int] = typer.Option(None, "--max-frames"),
    stick: bool = typer.Option(False, "--stick", help="Draw the stick figure instead of MuJoCo's renderer."),
):
    """Play a reference clip kinematically in MuJoCo and render it offscreen."""
    key = int(clip) if clip.isdigit() else clip

    def go():
        from motok.sim.render import render_trajectory
        hum, lib = _setup(data, humanoid, hz, [key])
        qpos = lib.clip(0)["qpos"][:max_frames]
        return render_trajectory(hum, qpos, out, lib.fps, title=lib.names[0], backend="stick" if stick else "auto")

    path, backend = run(go)
    _progress.info(f"wrote {path} ({backend} renderer)")


@app.command("pd-track")
def pd_track_cmd(
    data: Path = Data,
    clip: str = typer.Option("all", "--clip", help="Clip name or index, or 'all' (no video then)."),
    out: Optional[Path] = typer.Option(None, "-o", "--out", help="Video of the tracking (.mp4/.gif), one clip only."),
    humanoid: Optional[Path] = HumanoidOpt,
    hz: Optional[float] = Hz,
    seconds: Optional[float] = typer.Option(None, "--seconds", help="Track at most this long (default: whole clip)."),
    stick: bool = typer.Option(False, "--stick", help="Draw the stick figure instead of MuJoCo's renderer."),
    as_json: bool = typer.Option(False, "--json", help="Print the results as JSON."),
):
    """Track a reference with plain PD (no policy) and report how long the humanoid stays up."""
    clips = None if clip == "all" else [int(clip) if clip.isdigit() else clip]
    if clips is None and out is not None:
        fail("-o renders one clip: pass --clip NAME")

    def go():
        from motok.control.baselines import pd_track_run
        return pd_track_run(*_setup(data, humanoid, hz, clips), seconds, out, stick)

    summary = run(go)
    if as_json:
        print_json(summary)
        return
    short = {k: v for k, v in summary.items() if k != "per_clip"}
    if len(summary["per_clip"]) <= 5:
        short.update({f"survival {k}": f"{v} s" for k, v in summary["per_clip"].items()})
    report(short, False, "pd-track")
