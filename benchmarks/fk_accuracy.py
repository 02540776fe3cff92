"""How closely the humanoid's MuJoCo forward kinematics at the reference qpos reproduces the
dataset's canonical joints (docs/sim.md "Accuracy", docs/results.md "Physics world").

    .venv/bin/python benchmarks/fk_accuracy.py [--data runs/bandai2.h5] [--clips 'dataset-2_walk_normal*'] \\
        [--rates 20 30] [--humanoid humanoid.xml] [--json out.json]

For each rate the reference library is built from scratch (no cache): every clip resampled to
that rate, qpos from its local rotations, MuJoCo FK, then the distance between every body's
world position and the dataset joint it stands for, over every frame and body. The humanoid is
built from ``--data`` unless ``--humanoid`` is given. tests/test_sim.py checks the same numbers
on the same 24 clips.
"""

from __future__ import annotations

import argparse
import fnmatch
import json
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))


def fk_errors(hum, data: Path, clips: list[str], hz: float) -> np.ndarray:
    """Per frame and body, metres: MuJoCo FK at the reference qpos against the dataset's joints."""
    from motok.sim.reference import build_library

    lib = build_library(hum, data, control_hz=hz, clips=clips)
    return np.linalg.norm(lib.body_pos - lib.joints, axis=-1)


def main(argv=None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--data", type=Path, default=Path("runs/bandai2.h5"))
    ap.add_argument("--clips", default="dataset-2_walk_normal*", help="glob over clip names")
    ap.add_argument("--rates", type=float, nargs="+", default=[20.0, 30.0])
    ap.add_argument("--humanoid", type=Path, default=None, help="an MJCF from `motok sim build-humanoid`")
    ap.add_argument("--json", type=Path, default=None)
    args = ap.parse_args(argv)

    from motok.data.dataset import MotionFile
    from motok.sim.humanoid import load_humanoid
    from motok.sim.mjcf import build_humanoid

    with MotionFile(args.data) as mf:
        clips = [n for n in mf.names if fnmatch.fnmatchcase(n, args.clips)]
    if not clips:
        raise SystemExit(f"{args.data}: no clip matches {args.clips!r}")
    with tempfile.TemporaryDirectory() as tmp:
        path = args.humanoid or Path(tmp) / "humanoid.xml"
        if args.humanoid is None:
            build_humanoid(args.data, path)
        hum = load_humanoid(path)
        res = {"data": str(args.data), "clips": len(clips), "pattern": args.clips, "rates": {}}
        for hz in args.rates:
            t0 = time.perf_counter()
            err = fk_errors(hum, args.data, clips, hz)
            res["rates"][f"{hz:g}"] = {"frames": int(err.shape[0]), "bodies": int(err.shape[1]),
                                       "max_mm": float(err.max() * 1e3), "mean_mm": float(err.mean() * 1e3),
                                       "p99_mm": float(np.percentile(err, 99) * 1e3),
                                       "seconds": round(time.perf_counter() - t0, 1)}
    print(f"{len(clips)} clips ({args.clips}) of {args.data}")
    print(f"{'rate':>6}{'frames':>8}{'max mm':>9}{'mean mm':>9}{'p99 mm':>9}")
    for hz, r in res["rates"].items():
        print(f"{hz:>6}{r['frames']:>8}{r['max_mm']:>9.2f}{r['mean_mm']:>9.2f}{r['p99_mm']:>9.2f}")
    if args.json:
        args.json.write_text(json.dumps(res, indent=2) + "\n")
    return res


if __name__ == "__main__":
    main()
