"""The Markdown tables of docs/results.md from what scripts/physics_results.sh wrote, so every number
there is read from an output file, not copied by hand:

    .venv/bin/python scripts/physics_tables.py [--runs runs]    # prints the tables that have data
    .venv/bin/python scripts/physics_tables.py --status         # where every run of the queue stands

Priors: the imitation table (Fig. 4: train and test clips from frame 0), code usage,
samples/s and wall time; Table 1 (motion matching); the paper's orderings, each said to hold or
not. Tasks (task_tables.py): in-betweening (Table 2), head tracking (Table 3), navigation and
Fig. 13 as mean ± 95 % interval over seeds, each of the paper's claims with its verdict
(motok/eval/seeds.py), and thrown balls per run. Text to physics: the t2m rows. `--status` adds
the wall time of each stage from the queue's logs/times.tsv.
"""

from __future__ import annotations

import argparse
import json
import statistics
from pathlib import Path

from task_tables import claims, seeded_tables, stage_times  # beside this script

PRIORS = ("hybrid", "continuous", "discrete+", "discrete", "hybrid-vq")


def load(path: Path) -> dict | None:
    return json.loads(path.read_text()) if path.exists() else None


def metrics(run: Path) -> list[dict]:
    f = run / "metrics.jsonl"
    return [json.loads(x) for x in f.read_text().splitlines()] if f.exists() else []


def table(head: list[str], rows: list[list]) -> str:
    out = ["| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
    out += ["| " + " | ".join(str(c) for c in r) + " |" for r in rows]
    return "\n".join(out)


def pct(x) -> str:
    return "" if x is None else f"{100 * x:.1f} %"


def num(x, fmt="{:.1f}") -> str:
    return "" if x is None else fmt.format(x)


def priors(R: Path) -> str:
    rows = []
    for k in PRIORS:
        run = R / f"prior_{k}"
        m = metrics(run)
        if not m:
            continue
        tr, te = load(run / "eval.json"), load(run / "eval_test.json")
        last = m[-20:]
        usage = [r["code_usage"] for r in last if "code_usage" in r]
        o, t = (tr or {}).get("overall", {}), (te or {}).get("overall", {})
        rows.append([k, m[-1]["iteration"], f"{m[-1]['samples'] / 1e6:.1f} M", f"{m[-1]['wall_s'] / 60:.0f} min",
                     f"{statistics.median(r['samples_per_s'] for r in m):,.0f}",
                     pct(o.get("success_rate")), pct(t.get("success_rate")), pct(t.get("success_rate_any_body")),
                     num(t.get("mpjpe_mm")), num(t.get("g_mpjpe_mm")), num(t.get("root_vel_err_mm"), "{:.2f}"),
                     num(t.get("root_acc_err_mm"), "{:.2f}"),
                     num(statistics.mean(usage), "{:.2f}") if usage else "-"])
    if not rows:
        return ""
    return "Imitation from frame 0 (the expert's test: mean body error > 0.5 m):\n\n" + table(
        ["prior", "iterations", "samples", "wall", "samples/s (median)", "train played", "test played",
         "test any body", "test MPJPE mm", "test G-MPJPE mm", "root vel. err.", "root acc. err.",
         "code usage (last 20 it.)"], rows)


def falls(gen: Path) -> str:
    """'fell / samples' of one `control generate` output, from the labels each sample carries."""
    if not gen.exists():
        return ""
    import h5py  # only here: the other tables need nothing but json

    with h5py.File(gen, "r") as f:
        labels = [json.loads(x) for x in f["clips"]["labels"][:]]
    return f"{sum(x.get('fell_at_s') is not None for x in labels)} / {len(labels)}"


def curves(R: Path) -> str:
    """Each prior's eval-subset success (played to the end) at every evaluation of its run."""
    runs = {k: [r for r in metrics(R / f"prior_{k}") if "eval_success" in r] for k in PRIORS}
    runs = {k: v for k, v in runs.items() if v}
    if not runs:
        return ""
    its = sorted({r["iteration"] for v in runs.values() for r in v})
    rows = [[k] + [pct({r["iteration"]: r["eval_success"] for r in v}.get(i)) for i in its] for k, v in runs.items()]
    return "Eval subset during distillation, played to the end, at iteration:\n\n" + table(
        ["prior"] + [f"{i:,}" for i in its], rows)


def table1(R: Path) -> str:
    rep = load(R / "table1" / "table1.json")
    if rep is None:
        return ""
    # distance: Eq. 8 over the valid transitions, with its std where the report has it (Tables 1 and 4:
    # mean +- std); falls: the report's own count, else (older reports) the generation's labels
    rows = [[Path(r["motion"]).stem, r["transitions"],
             f"{r['distance_mean']:.3f}" + (f" ± {r['distance_std']:.3f}" if r.get("distance_std") is not None else ""),
             pct(r["filtered_rate"]), pct(r["coverage"]), pct(r["coverage_within_threshold"]),
             pct(r.get("coverage_equal_n")), f"{r['jitter_m_s3']:.1f}",
             f"{r['fell']} / {r['episodes']}" if "fell" in r else falls(R / "table1" / Path(r["motion"]).name)]
            for r in rep["rows"]]
    d = rep["dataset"]
    rows.append(["dataset", d["transitions"], "", "", "", "", "", f"{d['jitter_m_s3']:.1f}", ""])
    n = rep["rows"][0].get("coverage_n") if rep["rows"] else None
    return (f"Table 1 (threshold {rep['threshold']['value']:.3f}: {rep['threshold']['definition']}):\n\n"
            + table(["motion", "transitions", "distance", "filtered", "coverage", "coverage <= thr",
                     f"coverage, equal n ({n:,})" if n else "coverage, equal n", "jitter m/s^3",
                     "fell (head < 0.5 m)"], rows))


def orderings(R: Path) -> str:
    """The paper's orderings the priors' results are about, each read from the outputs and said to hold or
    not by a strict comparison; whether a difference is beyond noise (a few points on 427 test clips
    are not) is for the discussion in docs/results.md."""
    rep = load(R / "table1" / "table1.json")
    t1 = {Path(r["motion"]).stem: r for r in rep["rows"]} if rep else {}
    test = {k: (load(R / f"prior_{k}" / "eval_test.json") or {}).get("overall", {}) for k in PRIORS}
    rows = []

    def claim(text, a, b, key, higher, fmt):
        """`a` above (higher=True) or below `b` in `key`; a and b are (name, record) pairs."""
        (na, ra), (nb, rb) = a, b
        if ra.get(key) is None or rb.get(key) is None:
            return
        holds = ra[key] > rb[key] if higher else ra[key] < rb[key]
        rows.append([text, f"{na} {fmt(ra[key])}, {nb} {fmt(rb[key])}", "holds" if holds else "does not hold"])

    def t1row(tag):
        return tag, t1.get(tag, {})

    def im(kind):
        return kind, test[kind]

    claim("hybrid(1) distance below discrete+(1) (Table 1)", t1row("hybrid-m1"), t1row("discrete+-m1"),
          "distance_mean", False, "{:.3f}".format)
    # at equal size where the report has it: a row that falls sooner has fewer transitions to cover with
    cov = "coverage_equal_n" if "coverage_equal_n" in t1.get("hybrid-m1", {}) else "coverage"
    claim(f"hybrid(1) {cov.replace('_', ' ')} above discrete+(1) (Table 1)", t1row("hybrid-m1"),
          t1row("discrete+-m1"), cov, True, pct)
    for a, b, what in (("discrete+", "discrete", "RVQ above single VQ"), ("hybrid", "hybrid-vq", "hybrid-vq below hybrid"),
                       ("hybrid", "continuous", "hybrid vs continuous (Fig. 4)")):
        claim(f"{what}: {a} above {b}, test clips played to the end", im(a), im(b), "success_rate", True, pct)
        claim(f"{what}: {a} below {b}, test MPJPE", im(a), im(b), "mpjpe_mm", False, "{:.1f} mm".format)
    if not rows:
        return ""
    return "The paper's orderings on these outputs:\n\n" + table(["claim", "ours", ""], rows)


def tasks(R: Path) -> str:
    """The task tables over seeds, the paper's claims with their verdicts, and the thrown balls."""
    return "\n\n".join(x for x in (seeded_tables(R), claims(R), balls_table(R)) if x)


def balls_table(R: Path) -> str:
    """Thrown balls (section 6.3.3), one row per navigation run and period, the paper's 0.3 s first.
    Recoveries count over the hits whose 3 s window was played (`hits_resolved`): a hit too near an
    episode's end is censored whatever follows it."""
    rows = []
    for run in sorted((R / "tasks").glob("navigation_*")):
        # each result names its own period (`perturb.json` holds the paper's, others their own files)
        found = sorted((load(f) for f in run.glob("perturb*.json")), key=lambda p: p["config"]["period"])
        for p in found:
            period = p["config"]["period"]
            fell = round(p["terminated_share"] * p["episodes"])
            rows.append([run.name, "never in 8 s" if period >= 8 else f"{period:g} s", p["hits"],
                         f"{fell} / {p['episodes']}", f"{p['recoveries']} / {p['hits_resolved']}",
                         pct(p["recovery_rate"]) if p["hits_resolved"] else "", p["hits_censored"],
                         pct(p.get("reached_share")), pct(p["success"])])
    if not rows:
        return ""
    return table(["run", "one ball every", "hits", "episodes that fell", "recovered / resolved hits", "recovered",
                  "censored hits", "targets reached", "episodes to the end"], rows)


def t2p(R: Path) -> str:
    K = R / "kinematic"
    md = K / "t2m-physics.md"
    out = [md.read_text().rstrip()] if md.exists() else []
    rows = []
    for name in ("generated_sim", "real_test_sim"):  # what `motok control track` wrote beside each
        t = load(K / f"{name}.track.json")
        if t is not None:
            slip = t.get("sole_slip", {})  # reports before the sole slip have none
            rows.append([name, t["clips"], t["written"], pct(t["tracked_to_end"]), num(t["mpjpe_mm"]),
                         num(t["g_mpjpe_mm"])] + [num(slip.get(k, {}).get("sole_slip_cm_s"))
                                                  for k in ("simulated", "reference")])
    if rows:
        out.append(table(["tracked motion", "clips", "written", "tracked to the end", "MPJPE mm", "G-MPJPE mm",
                          "sole slip cm/s", "its reference's"], rows))
    return "\n\n".join(out)


# The latest evaluation each kind of run logs while training, for the status lines.
PROGRESS_KEYS = ("eval_success", "eval_success_rate", "eval_reached_share", "eval_approach_share", "eval_mpjpe_mm",
                 "eval_mpjpe_mm_mean", "eval_head_error_mm_mean")


def target(run: Path) -> int | None:
    """The iteration a training stops at: ``--until N`` of the command that last wrote its bundle,
    else its config's ``iterations`` (None without a bundle)."""
    meta = load(run / "bundle.json")
    if not meta:
        return None
    words = str(meta.get("provenance", {}).get("command", "")).split()
    if "--until" in words[:-1]:
        return int(words[words.index("--until") + 1])
    it = meta.get("config", {}).get("iterations")
    return int(it) if it else None


def eta(last: dict, recent: list[dict], goal: int | None) -> str:
    """``it / goal``, and the wall time left at the pace of ``recent`` records, for a status line."""
    it = last.get("iteration")
    if goal is None or it is None:
        return str(it or "")
    if it >= goal:
        return f"{it} / {goal} (done)"
    first = recent[0]
    if last.get("wall_s") is None or first.get("wall_s") is None or it <= first.get("iteration", it):
        return f"{it} / {goal}"
    per_it = (last["wall_s"] - first["wall_s"]) / (it - first["iteration"])
    return f"{it} / {goal} ({(goal - it) * per_it / 3600:.1f} h left)"


def status(R: Path) -> str:
    """One line per run folder: iteration of its goal and the time left at its recent pace, samples,
    logged wall time, recent samples/s, the latest evaluation logged while training, and the
    evaluation files already written; then the last line of the queue's log (what runs, or why it
    stopped)."""
    rows = []
    for run in sorted(p for p in R.glob("**/metrics.jsonl") if "logs" not in p.parts):
        m = metrics(run.parent)
        if not m:
            continue
        last = m[-1]
        rate = [r["samples_per_s"] for r in m[-50:] if "samples_per_s" in r]
        evals = {k: r[k] for r in m for k in PROGRESS_KEYS if r.get(k) is not None}
        seen = ", ".join(f"{k.removeprefix('eval_')} {v:.3g} (it {next(r['iteration'] for r in reversed(m) if k in r)})"
                         for k, v in evals.items())
        files = ", ".join(sorted(p.name for p in run.parent.glob("*.json") if p.name != "bundle.json"))
        # the pace over 500 records: one that ends at an evaluation (its time is in wall_s) would skew 50
        rows.append([str(run.parent.relative_to(R)), eta(last, m[-500:], target(run.parent)),
                     f"{last.get('samples', 0) / 1e6:.1f} M",
                     f"{last.get('wall_s', 0) / 3600:.2f} h", f"{statistics.median(rate):,.0f}" if rate else "",
                     seen, files])
    out = [table(["run", "iteration", "samples", "wall", "samples/s (last 50)", "latest evaluation", "evaluated"],
                 rows)] if rows else []
    if stage_times(R):
        out.append(stage_times(R))
    log = R / "logs" / "queue.log"
    if log.exists() and log.read_text().strip():
        out.append("queue: " + log.read_text().strip().splitlines()[-1])
    return "\n\n".join(out)


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--runs", type=Path, default=Path("runs"))
    ap.add_argument("--status", action="store_true", help="where every run stands instead of the tables")
    args = ap.parse_args()
    R = args.runs
    if args.status:
        print(status(R))
        return
    for part in (priors(R), curves(R), table1(R), orderings(R), tasks(R), t2p(R)):
        if part:
            print(part + "\n")


if __name__ == "__main__":
    main()
