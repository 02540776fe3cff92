"""One to three experts side by side on the same clips, to see what their feet do: each plays the clip from
its first frame (the most likely action, as ``motok control expert eval``), the reference drawn as a
translucent ghost, and the sole corners that touch the floor marked: green while they hold, red
while they slide faster than ``motok.sim.soles.SLIP_SPEED``. Each panel's caption carries its
running sole slip (cm/s over the contact steps so far), so a still frame already says which slides.

    .venv/bin/python scripts/feet_videos.py --expert runs/levers/base --expert runs/levers/filter0.3+ankle0.5 \\
        --label "filter 0.5" --label "filter 0.3 + ankles 0.5" -d runs/bandai2.h5 \\
        --clip 'dataset-2_walk_normal_001' -o runs/videos/feet_walk.mp4

Each expert plays on its own humanoid (its run's ``humanoid.xml``: contact model and ankle gains
differ between runs, the bodies do not), so the ghost and the camera are the same for both.
"""

from __future__ import annotations

import argparse
import os
from pathlib import Path

import numpy as np

os.environ.setdefault("MUJOCO_GL", "egl")

from motok.checkpoint import read_meta  # noqa: E402
from motok.control.expert.model import KIND, load_expert  # noqa: E402
from motok.control.tasks.imitation import play  # noqa: E402
from motok.data.dataset import select_clips  # noqa: E402
from motok.errors import UserError  # noqa: E402
from motok.render.video import write_video  # noqa: E402
from motok.sim.reference import load_library  # noqa: E402
from motok.sim.render import trajectory_frames  # noqa: E402
from motok.sim.soles import contact_markers, soles  # noqa: E402

def panel(run: Path, label: str, data, clip: str, size) -> tuple[list[np.ndarray], float]:
    cfg, hum, ac, _ = load_expert(run)
    lib = load_library(hum, data, control_hz=cfg.env.control_hz, clips=[clip])
    out = play(hum, ac, lib, np.array([0]), cfg.env, cfg.task, cfg.action, keep_qpos=True, sole=soles(hum))
    n = int(out["played"][0]) + 1
    pos, rgba, running = contact_markers(out["sole_sim"][0, :n].astype(np.float64), out["dt"])
    ended = "to the end" if out["success"][0] else f"fell at {n * out['dt']:.1f} s"
    titles = [f"{label}: sole slip {running[t]:.1f} cm/s ({ended})" for t in range(n)]
    frames = list(trajectory_frames(hum, out["qpos"][:n], size=size, ghost=out["ref_qpos"][:n], title=titles,
                                    markers=pos, marker_rgba=rgba, marker_radius=0.025))
    return frames, 1.0 / out["dt"]


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--expert", action="append", required=True, type=Path, help="an expert run (1-3 times)")
    ap.add_argument("--label", action="append", help="a caption per expert (default: the run's name)")
    ap.add_argument("-d", "--data", required=True, help="the dataset the clips come from")
    ap.add_argument("--clip", action="append", required=True, help="a clip name or glob (repeatable)")
    ap.add_argument("-o", "--out", required=True, type=Path, help="the video (.mp4/.gif); one per clip when "
                    "several: NAME_CLIP.mp4")
    ap.add_argument("--size", default="480x400", help="each panel's WIDTHxHEIGHT")
    a = ap.parse_args(argv)
    if not 1 <= len(a.expert) <= 3:
        raise SystemExit(f"error: --expert 1 to 3 times (got {len(a.expert)}): the runs to put side by side")
    labels = a.label or [r.name for r in a.expert]
    if len(labels) != len(a.expert):
        raise SystemExit("error: --label once per --expert, or not at all")
    rates = [float(read_meta(r, KIND)["extra"]["control_hz"]) for r in a.expert]
    if len(set(rates)) > 1:  # the panels are joined frame by frame: one would play at another speed
        raise SystemExit(f"error: the experts act at {', '.join(f'{h:g} Hz' for h in rates)}; side by side they "
                         "must share one control rate")
    size = tuple(int(x) for x in a.size.split("x"))
    names = [n for c in a.clip for n in select_clips(a.data, c, None)]
    if not names:
        raise UserError(f"no clip of {a.data} matches {a.clip}")
    for name in names:
        out = a.out if len(names) == 1 else a.out.with_name(f"{a.out.stem}_{name}{a.out.suffix}")
        panels = [panel(r, lab, a.data, name, size) for r, lab in zip(a.expert, labels)]
        fps = panels[0][1]
        n = max(len(f) for f, _ in panels)  # one that fell holds its last frame
        frames = (np.concatenate([f[min(t, len(f) - 1)] for f, _ in panels], 1) for t in range(n))
        write_video(frames, out, fps)
        print(f"{out}: {name}, {n} frames")


if __name__ == "__main__":
    main()
