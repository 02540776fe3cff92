"""Rank the levers against sliding feet with short trainings (docs/sim.md "Feet").

Each lever is the 24-walk expert (``recipes/control/expert.yaml`` through ``env.target_filter`` 0.5,
the whole-dataset recipe's world) trained from scratch for ``--until`` iterations with one change,
to its world (a humanoid built with other contact or PD settings) or to its training (a recipe
field), then evaluated with ``motok control expert eval`` on its 24 walks from frame 0: played to
the end, MPJPE, and the feet (joint skating, sole slip, sole penetration, jitter) beside the
clips' own over the same frames. A lever's run is resumed, not redone, when the script runs again;
a finished evaluation is read back.

    python scripts/foot_levers.py --until 500 base feet1 filter0.3 kv2       # one training at a time
    python scripts/foot_levers.py --until 500 base action_rate amp_feet rate60 rate60s
    python scripts/foot_levers.py --until 500 set2+action_rate set2+amp_feet set2+rate60s  # on the chosen world
    python scripts/foot_levers.py --until 500 --table                        # the table of what exists
    python scripts/foot_levers.py --pd base kv2 noslip elliptic3 filter0.3   # plain PD tracking, no training

``--pd`` plays each lever's world with zero actions (PD servos on the reference's angles and velocity
lead, through the lever's target filter: what a residual policy starts from) on the fixed test set,
2 clips of every content x style group of the test split, from frame 0 until the mean body error
passes 0.5 m, and measures the feet over the frames played, beside the clips' own.

``MOTOK`` (environment) is the command that runs motok, e.g. a frozen copy of the code.
"""

from __future__ import annotations

import argparse
import json
import os
import shlex
import subprocess
import sys
from pathlib import Path

CLIPS = "dataset-2_walk_normal*"
BASE_SETS = ["env.target_filter=0.5"]
# name -> (humanoid --set items, expert --set items)
LEVERS = {
    "base": ([], []),
    "feet1": ([], ["task.reward.k_feet=1.0"]),  # foot-velocity term in the imitation reward
    "feet3": ([], ["task.reward.k_feet=3.0"]),
    "filter0.3": ([], ["env.target_filter=0.3"]),  # a stronger low-pass on the PD targets
    "filter0.2": ([], ["env.target_filter=0.2"]),
    "kv2": (["derivative_time=0.2"], []),  # twice the PD damping
    "ankle0.5": (["ankle_stiffness_scale=0.5"], []),  # compliant ankles (0.3 cannot stand)
    "filter0.3+ankle0.5": (["ankle_stiffness_scale=0.5"], ["env.target_filter=0.3"]),
    "elliptic": (["cone=elliptic", "impratio=10"], []),  # harder friction (1.7x the physics cost)
    "noslip": (["noslip_iterations=10"], []),
    "elliptic3": (["cone=elliptic", "impratio=3"], []),  # elliptic at impratio 10 diverges standing
    # an additive penalty on the change of the action between steps, -mean_j (a_t - a_(t-1))^2; at 1 a
    # residual chattering by 0.2 rad a step costs 0.04, a tenth of a typical step's weighted reward
    "action_rate": ([], ["w_action_rate=1.0"]),
    "amp_feet": ([], ["amp.feet=true"]),  # the discriminator also sees each foot's sole height and speed
    "rate60": ([], ["env.control_hz=60"]),  # 60 control steps a second (2 substeps), every per-step setting kept
    # 60 Hz with the per-step settings that keep their 30 Hz values per second: gamma 0.99^(1/2), lam
    # 0.95^(1/2), the target filter's decay 0.5 per 1/30 s (1 - 0.5^(1/2)); the horizon stays 32 steps
    "rate60s": ([], ["env.control_hz=60", "ppo.gamma=0.995", "ppo.lam=0.975", "env.target_filter=0.293"]),
}
# the same three on the chosen world (filter 0.3, ankles at half: expert_set2.yaml's), against
# filter0.3+ankle0.5; at 60 Hz the filter's decay 0.7 per 1/30 s is 1 - 0.7^(1/2) per step
_SET2_HUM, _SET2 = LEVERS["filter0.3+ankle0.5"]
LEVERS |= {
    "set2+action_rate": (_SET2_HUM, [*_SET2, "w_action_rate=1.0"]),
    "set2+amp_feet": (_SET2_HUM, [*_SET2, "amp.feet=true"]),
    "set2+rate60s": (_SET2_HUM, ["env.control_hz=60", "ppo.gamma=0.995", "ppo.lam=0.975", "env.target_filter=0.163"]),
}


def sh(cmd: list[str], log: Path) -> None:
    print("+", shlex.join(cmd), flush=True)
    with open(log, "a") as f:
        r = subprocess.run(cmd, stdout=f, stderr=subprocess.STDOUT)
    if r.returncode:
        sys.exit(f"failed ({r.returncode}): {shlex.join(cmd)}; see {log}")


def run_lever(name: str, a, motok: list[str]) -> None:
    sets = LEVERS[name][1]
    out = a.runs / name
    log = a.runs / f"{name}.log"
    a.runs.mkdir(parents=True, exist_ok=True)
    xml = humanoid_of(name, a, motok)
    hum = ["--humanoid", str(xml)] if xml else []
    done = out / "bundle.json"
    iteration = json.loads(done.read_text())["extra"]["iteration"] if done.exists() else 0
    if iteration < a.until:
        resume = ["--resume"] if done.exists() else hum
        sh([*motok, "control", "expert", "train", "-d", str(a.data), "--clips", CLIPS, "--recipe",
            "recipes/control/expert.yaml", *[x for s in BASE_SETS + sets for x in ("--set", s)], "--set",
            "eval_every=0", "--until", str(a.until), *resume, "-o", str(out)], log)
    ev = out / "eval.json"
    if not ev.exists() or json.loads(ev.read_text())["checkpoint"].get("iteration") != a.until:
        sh([*motok, "control", "expert", "eval", "--expert", str(out), "--json"], log)


def humanoid_of(name: str, a, motok: list[str]) -> Path | None:
    hum_sets = LEVERS[name][0]
    if not hum_sets:
        return None
    xml = a.runs / f"{name}.xml"
    if not xml.exists():
        a.runs.mkdir(parents=True, exist_ok=True)
        sh([*motok, "sim", "build-humanoid", "-d", str(a.data), "-o", str(xml),
            *[x for s in hum_sets for x in ("--set", s)]], a.runs / f"{name}.log")
    return xml


class ZeroPolicy:
    """Zero residual actions: the PD servos alone."""

    def __init__(self, n: int):
        self.n = n

    def act(self, x, deterministic=True):
        import torch
        return None, torch.zeros(len(x), self.n, dtype=torch.float64), None, None


def pd_feet(name: str, a, motok: list[str]) -> dict:
    from motok.config import load_config
    from motok.control.tasks.imitation import evaluate, subset
    from motok.control.expert.model import ExpertConfig
    from motok.data.dataset import select_clips
    from motok.sim.humanoid import load_humanoid
    from motok.sim.reference import humanoid_for, load_library

    xml = humanoid_of(name, a, motok)
    hum = load_humanoid(xml) if xml else humanoid_for(a.data)
    cfg = load_config(ExpertConfig, "recipes/control/expert.yaml", BASE_SETS + LEVERS[name][1])
    cfg.env.num_envs = 140
    lib = load_library(hum, a.data, control_hz=cfg.env.control_hz, clips=subset(select_clips(a.data, None, "test"), 2))
    res = evaluate(hum, ZeroPolicy(hum.model.nu), lib, cfg.env, cfg.task, cfg.action, feet=True)
    return {"success": res["overall"]["success_rate"], "seconds": res["overall"]["seconds_played"] / len(lib),
            **res["feet"]}


def pd_table(rows: dict) -> str:
    out = ["| world (PD tracking, zero actions) | seconds played per clip | skating cm/s (clips) | sole slip cm/s "
           "(clips) | sole penetration mm (clips) | jitter m/s³ (clips) |", "|---|---|---|---|---|---|"]
    for name, r in rows.items():
        s, c = r["simulated"], r["reference"]
        out.append(f"| {name} | {r['seconds']:.2f} | {s['skate_cm_s']:.2f} ({c['skate_cm_s']:.2f}) | "
                   f"{s['sole_slip_cm_s']:.1f} ({c['sole_slip_cm_s']:.1f}) | {s['sole_penetration_mm']:.1f} "
                   f"({c['sole_penetration_mm']:.1f}) | {s['jitter_m_s3']:.0f} ({c['jitter_m_s3']:.0f}) |")
    return "\n".join(out)


def table(a) -> str:
    rows = ["| lever | walks to the end | MPJPE mm | skating cm/s (clips) | sole slip cm/s (clips) | "
            "sole penetration mm (clips) | jitter m/s³ (clips) |", "|---|---|---|---|---|---|---|"]
    for name in LEVERS:
        ev = a.runs / name / "eval.json"
        if not ev.exists():
            continue
        r = json.loads(ev.read_text())
        o, f = r["overall"], r["feet"]
        s, c = f["simulated"], f["reference"]
        rows.append(f"| {name} (it {r['checkpoint'].get('iteration')}) | {o['success_rate']:.0%} | {o['mpjpe_mm']:.1f} | "
                    f"{s['skate_cm_s']:.2f} ({c['skate_cm_s']:.2f}) | {s['sole_slip_cm_s']:.1f} ({c['sole_slip_cm_s']:.1f}) | "
                    f"{s['sole_penetration_mm']:.1f} ({c['sole_penetration_mm']:.1f}) | "
                    f"{s['jitter_m_s3']:.0f} ({c['jitter_m_s3']:.0f}) |")
    return "\n".join(rows)


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("levers", nargs="*", help=f"some of: {', '.join(LEVERS)}")
    p.add_argument("--until", type=int, default=500)
    p.add_argument("--data", type=Path, default=Path("runs/bandai2.h5"))
    p.add_argument("--runs", type=Path, default=Path("runs/levers"))
    p.add_argument("--table", action="store_true", help="print the table of the evaluated levers")
    p.add_argument("--pd", action="store_true", help="PD tracking of each lever's world on the fixed test set")
    a = p.parse_args()
    motok = shlex.split(os.environ.get("MOTOK", ".venv/bin/motok"))
    unknown = [n for n in a.levers if n not in LEVERS]
    if unknown:
        p.error(f"unknown lever {unknown[0]!r} (expected some of: {', '.join(LEVERS)})")
    if a.pd:
        path = a.runs / "pd.json"
        rows = json.loads(path.read_text()) if path.exists() else {}
        rows.update({name: pd_feet(name, a, motok) for name in a.levers})
        path.write_text(json.dumps(rows, indent=1))
        print(pd_table(rows))
        return
    for name in a.levers:
        run_lever(name, a, motok)
    print(table(a))


if __name__ == "__main__":
    main()
