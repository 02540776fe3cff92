"""Which motions a tracking fails on, and how (docs/results.md, "Text to physics").

Reads the ``.track.json`` reports that ``motok control track`` wrote for the real split and for
GPT samples of it (``motok eval t2m --save-generated``), or the ``.closed-loop.json`` of those
samples made again in the closed loop (``motok gpt sample -d ... --closed-loop``), groups every clip by the ``content``
label of its dataset clip (a GPT sample through its ``source`` clip, the caption it was made
from) and prints, per group, the share tracked to the end and, before the end or the failure,
the median MPJPE and G-MPJPE. With ``--replay N``, up to N failed clips per group of the first
report are played again with the same controller (the same trajectories: the tracking is
deterministic) to say how they failed: the simulated head's height at the last step against the
reference's, and how far the root is from the reference's in the plane (a character still
upright but far off its path drifted; one whose head dropped fell).

    python scripts/track_failures.py -d runs/bandai2.h5 --split test \\
        --report runs/kinematic/generated_sim.track.json --report runs/kinematic/real_test_sim.track.json \\
        --prior runs/prior_hybrid --replay 64
"""

from __future__ import annotations

import argparse
import json
from collections import defaultdict
from dataclasses import replace

import numpy as np

from motok.data.dataset import MotionFile
from motok.eval.evaluator import load_split


def content_of(report: dict, data: str, split: str) -> dict[str, str]:
    """Clip name -> content label of its dataset clip, for a tracked split or tracked GPT samples."""
    with MotionFile(data) as mf:
        sd = load_split(mf, split)  # the captioned clips, in the order `eval t2m` numbers its sources
        content = [json.loads(lab).get("content", "?") if lab else "?" for lab in sd.labels]
        by_name = dict(zip(sd.names, content))
    cfg = report["provenance"]["config"]
    motion = cfg.get("motion") or cfg["data"]  # what was tracked; a closed loop's: the generated set it made again
    if all(n in by_name for n in report["per_clip"]):
        return {n: by_name[n] for n in report["per_clip"]}
    with MotionFile(motion) as mf:  # GPT samples: labels role, sample, source, text
        labels = {n: json.loads(lab) for n, lab in zip(mf.names, mf.h5["clips/labels"][()].astype(str))}
    # MModality samples (role mm) come from 100 captions, not the split's: left out
    return {n: content[lab["source"]] for n, lab in labels.items()
            if n in report["per_clip"] and lab.get("role") != "mm" and "source" in lab}


def summary(report: dict, content: dict[str, str]) -> dict[str, dict]:
    """Per content group: clips, share tracked to the end, median MPJPE and G-MPJPE, the failed clips."""
    rows = defaultdict(list)
    for name, c in content.items():
        rows[c].append((name, report["per_clip"][name]))
    out = {}
    for c, clips in sorted(rows.items(), key=lambda kv: -len(kv[1])):
        played = [v for _, v in clips if "mpjpe_mm" in v]  # a clip too short to track has no error
        failed = [(n, v) for n, v in clips if not v["tracked_to_end"] and "mpjpe_mm" in v]
        out[c] = {"clips": len(clips), "tracked_to_end": float(np.mean([v["tracked_to_end"] for _, v in clips])),
                  "mpjpe_mm": float(np.median([v["mpjpe_mm"] for v in played])) if played else float("nan"),
                  "g_mpjpe_mm": float(np.median([v["g_mpjpe_mm"] for v in played])) if played else float("nan"),
                  "failed": [n for n, _ in failed],
                  # the share of its clip a failed clip was played for
                  "failed_at": float(np.median([v["seconds"] / v["clip_seconds"] for _, v in failed])) if failed
                  else float("nan")}
    return out


def how_they_failed(controller, motion: str, names: list[str]) -> dict:
    """The failed clips played again by ``controller`` (a ``motok.control.priors.load.Controller``):
    head height and planar root distance at the last step, and the seconds played."""
    from motok.control.tasks.imitation import play
    from motok.control.track import place_on_floor
    from motok.sim.reference import load_library
    cfg, hum, policy = controller.cfg, controller.humanoid, controller.policy
    hz = float(cfg.env.control_hz or hum.control_hz)
    lib, _ = place_on_floor(load_library(hum, motion, control_hz=hz, clips=names, use_cache=False))
    ids = np.arange(len(lib))
    res = play(hum, policy, lib, ids, cfg.env, replace(cfg.task, max_episode_seconds=1e9), cfg.action)
    last = np.array([np.flatnonzero(res["alive"][k])[-1] for k in ids])
    sim, ref = res["pos"][ids, last], res["ref"][ids, last]  # (clips, bodies, 3), MuJoCo frame: z up
    head = int(hum.skeleton.head)
    off = np.linalg.norm(sim[:, 0, :2] - ref[:, 0, :2], axis=-1)
    return {"clips": len(ids), "head_m": float(np.median(sim[:, head, 2])), "ref_head_m": float(np.median(ref[:, head, 2])),
            "head_below_0.8": float(np.mean(sim[:, head, 2] < 0.8)), "root_off_m": float(np.median(off)),
            "root_off_over_0.4": float(np.mean(off > 0.4)), "seconds": dict(zip(lib.names, (last / hz).tolist()))}


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("-d", "--data", required=True, help="The motion-dataset the motions came from.")
    ap.add_argument("--split", default="test")
    ap.add_argument("--report", action="append", required=True, help="A .track.json or .closed-loop.json (repeatable).")
    ap.add_argument("--prior", help="The prior that tracked the first report (for --replay).")
    ap.add_argument("--replay", type=int, default=0, help="Failed clips per group to play again (first report).")
    args = ap.parse_args()
    sums = []
    for path in args.report:
        rep = json.loads(open(path).read())
        sums.append((path, rep, summary(rep, content_of(rep, args.data, args.split))))
    groups = list(sums[0][2])
    print("| content | " + " | ".join(f"{p}: clips, to the end, MPJPE / G-MPJPE mm, failed at (share of the clip)"
                                      for p, _, _ in sums) + " |")
    print("|---|" + "---|" * len(sums))
    for c in groups:
        cells = [f"{s[c]['clips']}, {s[c]['tracked_to_end']:.1%}, {s[c]['mpjpe_mm']:.0f} / {s[c]['g_mpjpe_mm']:.0f}, "
                 + ("-" if np.isnan(s[c]["failed_at"]) else f"{s[c]['failed_at']:.2f}") if c in s else ""
                 for _, _, s in sums]
        print(f"| {c} | " + " | ".join(cells) + " |")
    if args.replay:
        if not args.prior:
            ap.error("--replay needs --prior")
        from motok.control.priors.load import load_controller
        controller = load_controller(prior=args.prior)
        path, rep, s = sums[0]
        print(f"\nAt the failure ({path}; up to {args.replay} failed clips per group, played again):")
        print("| content | failed clips played | head, median (reference's) | head below 0.8 m | root off in the plane, "
              "median | root off > 0.4 m |")
        print("|---|---|---|---|---|---|")
        for c in groups:
            names = s[c]["failed"][:args.replay]
            if not names:
                continue
            f = how_they_failed(controller, rep["provenance"]["config"]["motion"], names)
            print(f"| {c} | {f['clips']} | {f['head_m']:.2f} m ({f['ref_head_m']:.2f}) | {f['head_below_0.8']:.0%} | "
                  f"{f['root_off_m']:.2f} m | {f['root_off_over_0.4']:.0%} |")


if __name__ == "__main__":
    main()
