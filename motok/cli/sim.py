"""``motok sim``: the MuJoCo humanoid, reference replays and the plain-PD tracking baseline.

Argument parsing only; the work is in ``motok.sim``.
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Optional

import typer

from motok import progress as _progress

app = typer.Typer(help="Physics: the MuJoCo humanoid built from a dataset's skeleton, and its reference motions.",
                  no_args_is_help=True)

Data = typer.Option(..., "--data", help="A motion-dataset artifact (.h5).")
HumanoidOpt = typer.Option(None, "--humanoid", help="Humanoid MJCF (default: built from --data once and cached).")
Hz = typer.Option(None, "--hz", help="Control rate in Hz (default: the humanoid's, 30).")
Sets = typer.Option([], "--set", help="Override a HumanoidConfig key: --set key=value (repeatable).")


def _run(fn, *args, **kwargs):
    """User errors become one line and exit code 2 (the root CLI's convention)."""
    from motok.sim.humanoid import HumanoidError
    from motok.cli.main import run
    return run(fn, *args, catch=(HumanoidError, ValueError), **kwargs)


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
    from motok.cli.main import _report
    from motok.config import load_config
    from motok.sim.humanoid import HumanoidConfig, build_humanoid

    flags = {"total_mass": mass, "timestep": timestep}
    cfg = _run(load_config, HumanoidConfig, None, list(sets) + [f"{k}={v}" for k, v in flags.items() if v is not None])
    summary = _run(build_humanoid, data, out, cfg)
    _report(summary, as_json, title="build-humanoid")


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

    path, backend = _run(go)
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
    from motok.cli.main import fail

    clips = None if clip == "all" else [int(clip) if clip.isdigit() else clip]
    if clips is None and out is not None:
        fail("-o renders one clip: pass --clip NAME")

    def go():
        import numpy as np

        from motok.sim.env import pd_track
        hum, lib = _setup(data, humanoid, hz, clips)
        res = pd_track(hum, lib, range(len(lib)), seconds)
        written = None
        if out is not None:
            from motok.sim.render import render_trajectory
            written = render_trajectory(hum, res["qpos"][0], out, lib.fps, ghost=res["ref_qpos"][0],
                                        title=f"PD tracking {lib.names[0]}", backend="stick" if stick else "auto")
        s = res["survival_s"]
        return {"clips": len(s), "tracked_s": round(res["seconds"], 2), "survival_mean_s": round(float(s.mean()), 3),
                "survival_median_s": round(float(np.median(s)), 3), "survival_max_s": round(float(s.max()), 3),
                "per_clip": dict(zip(res["clips"], [round(float(x), 3) for x in s])),
                **({"video": f"{written[0]} ({written[1]})"} if written else {})}

    summary = _run(go)
    if as_json:
        typer.echo(json.dumps(summary, indent=2))
        return
    from motok.cli.main import _report
    short = {k: v for k, v in summary.items() if k != "per_clip"}
    if len(summary["per_clip"]) <= 5:
        short.update({f"survival {k}": f"{v} s" for k, v in summary["per_clip"].items()})
    _report(short, False, title="pd-track")
