"""``motok control track``: any motion artifact tracked in MuJoCo by a physics controller, written
back as a motion artifact. Arguments only; the work is in ``motok.control.track``.
:func:`register` adds the command to the ``motok control`` app."""

from __future__ import annotations

from pathlib import Path
from typing import Optional

import typer

from motok.cli.common import (JsonOut, clips_option, data_option, input_option, number_option, output_option, report,
                              results, run, split_option)
from motok.cli.conventions import examples


def track_cmd(
    motion: Path = data_option("The motion to track: a dataset, decoded tokens, GPT samples (any motion artifact)."),
    expert: Optional[Path] = input_option("--expert", help="The controller: a control-expert run folder.",
                                          required=False),
    prior: Optional[Path] = input_option("--prior", help="The controller: a distilled prior (its posterior and "
                                         "decoder), instead of --expert.", required=False),
    codebooks: Optional[int] = number_option(None, "--codebooks", "-m", help="With --prior: decode with the first M "
                                             "codebooks only (default: all).", within=">= 1"),
    out: Path = output_option(help="The simulated motion (.h5).", suffixes=(".h5",)),
    clips: Optional[str] = clips_option(help="Clip-name glob (default: all)."),
    split: Optional[str] = split_option(help="Only the clips of this split, e.g. real test motion tracked, "
                                             "for `motok eval t2m --motions`."),
    render: Optional[Path] = output_option("--render", help="Video of the first clip, the kinematic motion as a "
                                           "ghost (.mp4/.gif).", suffixes=(".mp4", ".gif"), required=False),
    as_json: bool = JsonOut,
):
    """Track every clip from its first frame; write the simulated bodies at the motion's frame rate."""
    from motok.control.priors.load import load_controller
    from motok.cli.output_files import refuse_foreign
    from motok.control.track import report_path, track

    run(refuse_foreign, report_path(out), "-o")  # the report written beside the motion
    res = run(lambda: track(load_controller(expert, prior, codebooks), motion, out, clips=clips, split=split,
                               render=render))
    per = res.pop("per_clip")
    report(res, as_json, "control track")
    if not as_json:
        for name, r in per.items():
            if "error" in r:
                results.print(f"{name}: {r['error']}", soft_wrap=True, highlight=False)


def register(app: typer.Typer) -> None:
    app.command("track", epilog=examples(
        "motok control track -d walk.h5 --expert runs/expert -o walk_sim.h5 --render walk_sim.mp4",
        "motok control track -d runs/bandai2.h5 --clips 'dataset-2_run_*' --prior runs/prior_hybrid -o run_sim.h5",
        "motok control track -d runs/bandai2.h5 --split test --prior runs/prior_hybrid -o test_sim.h5",
    ))(track_cmd)
