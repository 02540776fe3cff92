"""How fast the stick-figure renderer draws, against realtime and a naive matplotlib-3D loop.

    python benchmarks/render.py [--size 480] [--repeat 3] [--frames N] [--json out.json]

The clip is the HumanML3D golden sample (170 frames of a tennis serve, 22 SMPL joints,
20 fps) when the data root is available, else a synthetic 22-joint figure of the same
length. The baseline is what a first attempt usually looks like (and what the original
HumanML3D ``plot_3d_motion`` does): one mplot3d figure, cleared and re-plotted every frame,
rasterised with Agg and read back as an array, at the same pixel size. Both are measured
in this run on this machine and the same way -- the same frames, after one untimed warm-up
call (imports, font caches, the first figure), best of ``--repeat`` -- so the ratio is
meaningful even where the absolute numbers are not.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from motok.render.stick import render_frames, render_motion  # noqa: E402


def load_clip() -> tuple[np.ndarray, np.ndarray, float, str]:
    from motok.skeleton import load_skeleton

    parents = np.asarray(load_skeleton("smpl22").parents)
    try:
        from motok.data.root import resolve_data_root

        joints = np.load(resolve_data_root() / "humanml3d-sample" / "new_joints_012314.npy")
        return joints.astype(np.float64), parents, 20.0, "humanml3d-sample/012314 (real)"
    except (OSError, ValueError):
        rng = np.random.default_rng(0)
        rest = rng.normal(0.0, 0.3, (22, 3)) + [0.0, 1.0, 0.0]
        t = np.arange(170)[:, None, None] / 20.0
        joints = rest[None] + 0.05 * np.sin(2 * np.pi * t + rest[None, :, :1]) + t * [0.0, 0.0, 1.0]
        return joints, parents, 20.0, "synthetic (data root not found)"


def naive_matplotlib(joints: np.ndarray, parents: np.ndarray, size: int) -> np.ndarray:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig = plt.figure(figsize=(size / 100, size / 100), dpi=100)
    ax = fig.add_subplot(projection="3d")
    lo, hi = joints.min((0, 1)) - 0.3, joints.max((0, 1)) + 0.3
    out = []
    for pose in joints:
        ax.cla()
        ax.set_xlim(lo[0], hi[0]), ax.set_ylim(lo[2], hi[2]), ax.set_zlim(0, hi[1])
        ax.set_box_aspect((hi[0] - lo[0], hi[2] - lo[2], hi[1]))  # metres equal on all axes
        ax.view_init(elev=20, azim=-60)
        gx, gz = np.meshgrid(np.linspace(lo[0], hi[0], 8), np.linspace(lo[2], hi[2], 8))
        ax.plot_wireframe(gx, gz, np.zeros_like(gx), color="0.8", linewidth=0.5)
        for j, p in enumerate(parents):
            if p >= 0:
                ax.plot(*pose[[p, j]][:, [0, 2, 1]].T, linewidth=3)
        ax.scatter(*pose[:, [0, 2, 1]].T, s=8, c="k")
        fig.canvas.draw()
        out.append(np.asarray(fig.canvas.buffer_rgba())[..., :3].copy())
    plt.close(fig)
    return np.stack(out)


def timed(fn, repeat: int) -> float:
    """Best of ``repeat`` timed calls after one untimed warm-up call."""
    fn()
    best = float("inf")
    for _ in range(repeat):
        t0 = time.perf_counter()
        fn()
        best = min(best, time.perf_counter() - t0)
    return best


def main(argv=None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--size", type=int, default=480)
    ap.add_argument("--repeat", type=int, default=3, help="best of N, for every renderer")
    ap.add_argument("--frames", type=int, default=None, help="frames drawn by every renderer (default: the clip)")
    ap.add_argument("--json", type=Path, default=None)
    args = ap.parse_args(argv)

    joints, parents, fps, source = load_clip()
    joints = joints[: args.frames]
    T, size = len(joints), (args.size, args.size)
    res: dict = {"clip": source, "frames": T, "motion_fps": fps, "size": list(size), "repeat": args.repeat,
                 "timing": "same frames, one warm-up call, best of repeat", "python": platform.python_version(),
                 "cpus": os.cpu_count()}

    dt = timed(lambda: render_frames(joints, parents, fps=fps, size=size, title="benchmark"), args.repeat)
    res["stick_frames_per_s"] = T / dt
    with tempfile.TemporaryDirectory() as tmp:
        for suffix in ("gif", "mp4"):
            path = Path(tmp) / f"clip.{suffix}"
            dt = timed(lambda: render_motion(joints, parents, path, fps=fps, size=size, title="benchmark"),
                       args.repeat)
            res[f"{suffix}_end_to_end_frames_per_s"] = T / dt
            res[f"{suffix}_bytes"] = path.stat().st_size
    dt = timed(lambda: naive_matplotlib(joints, parents, args.size), args.repeat)
    res["matplotlib3d_frames_per_s"] = T / dt
    res["speedup_vs_matplotlib3d"] = res["stick_frames_per_s"] / res["matplotlib3d_frames_per_s"]

    print(f"clip: {source}, {T} frames at {fps:g} fps, {size[0]}x{size[1]} px; every renderer: "
          f"warm, best of {args.repeat}")
    print(f"{'renderer':<34}{'frames/s':>10}{'x realtime':>12}")
    for name, key in (("stick, frames only", "stick_frames_per_s"),
                      ("stick -> GIF (incl. quantise)", "gif_end_to_end_frames_per_s"),
                      ("stick -> MP4 (incl. libx264)", "mp4_end_to_end_frames_per_s"),
                      ("naive matplotlib 3D", "matplotlib3d_frames_per_s")):
        print(f"{name:<34}{res[key]:>10.1f}{res[key] / fps:>12.1f}")
    print(f"stick is {res['speedup_vs_matplotlib3d']:.1f}x faster than the matplotlib-3D baseline")
    if args.json:
        args.json.write_text(json.dumps(res, indent=2) + "\n")
    return res


if __name__ == "__main__":
    main()
