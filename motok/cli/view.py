"""``motok view``: a live window on a motion file or a control run. Arguments only; the work is
in ``motok.view``. :func:`register` adds the command to the root app."""

from __future__ import annotations

from pathlib import Path
from typing import Optional

import typer

from motok.cli.common import JsonOut, clips_option, fail, input_option, number_option, report, run
from motok.cli.conventions import examples


def view_cmd(
    data: Optional[Path] = input_option("--data", "-d", help="A motion or motion-dataset artifact (.h5) to play on "
                                        "the humanoid; with --expert/--prior, the motion to track instead of the "
                                        "run's own clips.", required=False),
    expert: Optional[Path] = input_option("--expert", help="A control-expert run: the policy tracks each clip in "
                                          "the physics, the reference as a ghost.", required=False),
    prior: Optional[Path] = input_option("--prior", help="A distilled prior (its posterior and decoder) tracking "
                                         "each clip, instead of --expert.", required=False),
    codebooks: Optional[int] = number_option(None, "--codebooks", "-m", help="With --prior: decode with the first M "
                                             "codebooks only (default: all).", within=">= 1"),
    clip: Optional[str] = typer.Option(None, "--clip", help="The clip to start with (name or index; default: the "
                                       "first)."),
    clips: Optional[str] = clips_option(help="Only the clips whose name matches (N and P step through them)."),
    humanoid: Optional[Path] = input_option("--humanoid", help="MJCF for a motion file (default: built from --data "
                                            "once and cached, as motok sim does).", required=False),
    seconds: Optional[float] = number_option(None, "--seconds", help="Close the window after this many seconds "
                                             "(scripted smoke tests; default: when you close it).", within="> 0"),
    as_json: bool = JsonOut,
):
    """Watch motion live in MuJoCo's viewer: a motion file's clips, or a controller tracking them."""
    if expert is not None and prior is not None:
        fail("view one controller: --expert RUN or --prior PRIOR, not both")
    if data is None and expert is None and prior is None:
        fail("give something to view: -d MOTION.h5, --expert RUN or --prior PRIOR")
    if codebooks is not None and prior is None:
        fail("--codebooks decodes a prior: pass --prior PRIOR")
    if humanoid is not None and (expert or prior):
        fail("--humanoid is for a motion file: a control run brings its own humanoid")

    def go():
        from motok.view.sources import ControlSource, MotionSource
        from motok.view.window import check_display, view

        check_display()  # before loading anything: no display means no window, whatever the input
        if expert is not None or prior is not None:
            source = ControlSource(expert, prior, codebooks, data, clips)
        else:
            source = MotionSource(data, humanoid, clips)
        return view(source, source.index(clip) if clip is not None else 0, seconds)

    report(run(go), as_json, "view")


def register(app: typer.Typer) -> None:
    app.command("view", epilog=examples(
        "motok view -d runs/bandai2.h5 --clips 'dataset-2_walk_*'",
        "motok view --expert runs/expert --clip dataset-2_walk_normal_003",
        "motok view --prior runs/prior_hybrid --codebooks 1 -d walk_generated.h5",
        "xvfb-run -a motok view -d walk.h5 --seconds 5   (no display: a virtual one)",
    ))(view_cmd)
