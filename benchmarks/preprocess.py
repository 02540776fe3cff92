"""Preprocessing speed: the whole Bandai-Namco set 2 at -j 1 and -j 2 (parsing and xz
decompression included), as source frames per second and as a factor over realtime
(30 fps), then the feature-extraction rate on the golden HumanML3D clip against an
unoptimized loop-per-joint baseline measured in the same run.

    .venv/bin/python benchmarks/preprocess.py [--data-root DIR] [--clips GLOB]
"""

from __future__ import annotations

import argparse
import sys
import tempfile
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))

from motok.data.preprocess import PreprocessConfig, preprocess  # noqa: E402
from motok.data.root import resolve_data_root  # noqa: E402


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--data-root", default=None)
    ap.add_argument("--clips", default="dataset-2_*")
    ap.add_argument("--jobs", type=int, nargs="*", default=[1, 2])
    args = ap.parse_args()
    root = resolve_data_root(args.data_root)
    src_fps = 30.0
    print(f"{'jobs':>4} {'clips':>6} {'src frames':>11} {'seconds':>8} {'src frames/s':>13} {'x realtime':>11}")
    for jobs in args.jobs:
        cfg = PreprocessConfig(data=[str(root / "bandai-namco/bandai-namco-2.tar.xz")],
                               annotations=str(root / "bandai-namco/annotations"), clips=args.clips,
                               skeleton="bandai21", jobs=jobs)
        with tempfile.TemporaryDirectory() as tmp:
            t0 = time.perf_counter()
            summary = preprocess(cfg, Path(tmp) / "bench.h5", command="benchmarks/preprocess.py")
            dt = time.perf_counter() - t0
        src_frames = summary["source_frames"]
        rate = src_frames / dt
        print(f"{jobs:>4} {summary['clips']:>6} {src_frames:>11,} {dt:>8.2f} {rate:>13,.0f} {rate / src_fps:>11,.0f}")

    import features_baseline
    features_baseline.main()


if __name__ == "__main__":
    main()
