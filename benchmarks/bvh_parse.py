"""BVH parse rate on a motion archive: motok's vectorized ``parse_bvh`` against a naive
per-line Python parse of the same clips, measured in the same run.

Three numbers per parser, in source frames/s and MB/s of BVH text:
  * read: streaming the archive (xz decompression) alone;
  * parse: ``parse_bvh`` on bytes already in memory (Euler to quaternions included);
  * naive: the same bytes read line by line, ``float()`` per value, into the same (T, C) array
    of channel values; it does less than ``parse_bvh`` (no quaternions), so the speed-up is a
    lower bound. By default it runs on the first ``--naive-files`` clips only, as it is slow.

    .venv/bin/python benchmarks/bvh_parse.py [--data-root DIR] [--archive PATH] [--limit N]

``measure()`` returns the numbers as a dict for benchmarks/preprocess.py.
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

import numpy as np

from motok.data.bvh import parse_bvh
from motok.data.root import resolve_data_root
from motok.data.sources import iter_sources


def naive_parse(data: bytes) -> np.ndarray:
    """The motion block as a (T, C) array, the way a first attempt would read it."""
    lines = data.decode("utf-8").splitlines()
    k = next(i for i, ln in enumerate(lines) if ln.strip() == "MOTION")
    frames = int(lines[k + 1].split(":")[1])
    rows = []
    for ln in lines[k + 3:]:
        vals = ln.split()
        if vals:
            rows.append([float(v) for v in vals])
    if len(rows) != frames:
        raise ValueError(f"{len(rows)} rows for {frames} frames")
    return np.array(rows, dtype=np.float64)


def measure(archive, *, limit: int | None = None, naive_files: int | None = 300) -> dict:
    t0 = time.perf_counter()
    clips = []
    for src in iter_sources(archive, kinds=("bvh",)):
        clips.append((src.origin, src.data))
        if limit is not None and len(clips) >= limit:
            break
    read_s = time.perf_counter() - t0
    mb = sum(len(d) for _, d in clips) / 1e6

    t0 = time.perf_counter()
    frames = [parse_bvh(d, o).num_frames for o, d in clips]
    parse_s = time.perf_counter() - t0

    sample = clips if naive_files is None else clips[:naive_files]
    t0 = time.perf_counter()
    naive_frames = [len(naive_parse(d)) for _, d in sample]
    naive_s = time.perf_counter() - t0
    assert naive_frames == frames[:len(sample)]
    sample_mb = sum(len(d) for _, d in sample) / 1e6
    sample_frames = sum(naive_frames)
    # The fast parser's rate on the naive sample alone, so the speed-up compares like with like.
    t0 = time.perf_counter()
    for o, d in sample:
        parse_bvh(d, o)
    sample_parse_s = time.perf_counter() - t0

    total = sum(frames)
    return {
        "archive": str(archive), "clips": len(clips), "frames": total, "mb": mb,
        "read_s": read_s, "parse_s": parse_s,
        "read_parse_mb_s": mb / (read_s + parse_s), "read_parse_frames_s": total / (read_s + parse_s),
        "parse_mb_s": mb / parse_s, "parse_frames_s": total / parse_s,
        "naive_clips": len(sample), "naive_s": naive_s,
        "naive_mb_s": sample_mb / naive_s, "naive_frames_s": sample_frames / naive_s,
        "speedup": naive_s / sample_parse_s,
    }


def report(r: dict) -> str:
    return "\n".join([
        f"{r['archive']}: {r['clips']} clips, {r['frames']:,} frames, {r['mb']:.1f} MB of BVH text",
        f"{'':28}{'seconds':>9}{'MB/s':>9}{'frames/s':>12}",
        f"{'read (decompress) + parse':28}{r['read_s'] + r['parse_s']:>9.2f}{r['read_parse_mb_s']:>9.1f}"
        f"{r['read_parse_frames_s']:>12,.0f}",
        f"{'parse_bvh (in memory)':28}{r['parse_s']:>9.2f}{r['parse_mb_s']:>9.1f}{r['parse_frames_s']:>12,.0f}",
        f"{'naive per-line, ' + str(r['naive_clips']) + ' clips':28}{r['naive_s']:>9.2f}{r['naive_mb_s']:>9.1f}"
        f"{r['naive_frames_s']:>12,.0f}",
        f"parse_bvh is {r['speedup']:.1f}x the naive parse on the same clips",
    ])


def main(argv=None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--data-root", default=None)
    ap.add_argument("--archive", default=None, help="default: DATA/bandai-namco/bandai-namco-2.tar.xz")
    ap.add_argument("--limit", type=int, default=None, help="only the first N clips")
    ap.add_argument("--naive-files", type=int, default=300, help="clips for the naive parse (0: all)")
    args = ap.parse_args(argv)
    archive = Path(args.archive) if args.archive else \
        resolve_data_root(args.data_root) / "bandai-namco" / "bandai-namco-2.tar.xz"
    r = measure(archive, limit=args.limit, naive_files=args.naive_files or None)
    print(report(r))
    return r


if __name__ == "__main__":
    main()
