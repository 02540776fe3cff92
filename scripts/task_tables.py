"""The task tables of docs/results.md (Table 2 in-betweening, Table 3 head tracking, navigation,
Fig. 13) over the seeds of scripts/physics_results.sh's `tasks` and `codebooks` stages, and the
paper's orderings each decided by the rule of motok/eval/seeds.py. Read by physics_tables.py.

Run folders: RUNS/tasks/TASK_VARIANT_seedN (VARIANT: a prior, or PRIOR_mM for M active codebooks),
each with the evaluation the queue writes: eval_inbetween_test.json, eval_hmd_test.json (the test
clips) or eval_navigation.json.
"""

from __future__ import annotations

import json
import re
import statistics
import sys
from pathlib import Path

# the checkout's own motok, the one beside this script, whichever checkout the environment installed
sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
from motok.eval.seeds import MIN_SEEDS, mean_interval, verdict  # noqa: E402

TASK_PRIORS = ("continuous", "discrete", "discrete+", "hybrid")
EVAL_FILE = {"inbetween": "eval_inbetween_test.json", "hmd": "eval_hmd_test.json",
             "navigation": "eval_navigation.json"}
TITLE = {"inbetween": "In-betweening (Table 2)", "hmd": "Head tracking (Table 3)", "navigation": "Navigation"}

# Each table's columns: (key in the evaluation file, heading, better, format). The errors of
# Tables 2-3 as the task evaluations write them (keyframes and all frames; head tracking has no
# keyframes); navigation's targets reached, time to reach, falls and the idle phase's motion matching.
_ERR = (("mpjpe_mm_mean", "MPJPE mm"), ("g_mpjpe_mm_mean", "G-MPJPE mm"), ("vel_err_mm_mean", "vel. err. mm"),
        ("acc_err_mm_mean", "acc. err. mm"))
MM, PCT, TWO = "{:.1f}", "pct", "{:.2f}"
METRICS = {
    "inbetween": [(f"keyframe_{k}", f"keyframes {h}", "lower", MM) for k, h in _ERR]
                 + [(k, f"all frames {h}", "lower", MM) for k, h in _ERR],
    "hmd": [(k, h, "lower", MM) for k, h in _ERR] + [("head_error_mm_mean", "head error mm", "lower", MM)],
    "navigation": [("reached_share", "targets reached", "higher", PCT),
                   ("time_to_reach_mean_s", "time to reach s", "lower", TWO),
                   ("falls_per_episode", "falls / episode", "lower", TWO),
                   ("idle_distance_mean", "idle MM distance", "lower", TWO),
                   ("idle_filtered_rate", "idle filtered", "lower", PCT)],
}
# beside the paper's columns, ours: what share of the episodes never failed, and how much of the
# distance to the targets was closed (most targets are out of reach at the data's walking speed)
EXTRA = {"inbetween": [("success_rate", "success", "higher", PCT)], "hmd": [("success_rate", "success", "higher", PCT)],
         "navigation": [("approach_share", "distance closed", "higher", PCT)]}

# The paper's numbers, one entry per table, named by its source; `values` is empty until they are
# transcribed (docs/results.md "The paper" says why none is yet). A row written here as
# {variant: {key: value}} prints under ours as "VARIANT (paper)", and after all of ours for a prior
# we have no run of. Keys are the evaluation-file keys of METRICS and EXTRA (the paper's keyframe
# MPJPE of Table 2 is "keyframe_mpjpe_mm_mean", its all-frame one "mpjpe_mm_mean"); a key that is
# not one of the table's columns is refused rather than left unprinted. Values in the columns'
# units: positions in millimetres (convert a table in metres or centimetres); velocity and
# acceleration errors in mm per control step and per step squared at the 30 Hz control rate
# (motok.features.kinematics), so a table in mm/s is divided by 30 and one in mm/s^2 by 900;
# seconds; falls per episode; shares as fractions (a paper's 85.2 % is 0.852). A column the paper
# does not report is left out of its row; a paper column we do not measure is named in
# docs/results.md instead.
PAPER = {
    "inbetween": {"source": "Bae et al. 2025, Table 2, section 6.3", "values": {}},
    "hmd": {"source": "Bae et al. 2025, Table 3, section 6.3", "values": {}},
    "navigation": {"source": "Bae et al. 2025, section 6.3, navigation", "values": {}},
}

# The paper's claims, each "A better than B" on every column of its table: the hybrid prior is the
# best for task learning (abstract, section 6.3: Tables 2-3 and navigation); and Fig. 13: a policy
# over the first M codebooks of the hybrid does better than one over all 8, and the hybrid beats
# discrete+ at equal M. (task, A, B, source); a bare prior name is the run at its task's protocol
# codebooks (navigation: 1), ``PRIOR_mM`` the run over the first M.
CLAIMS = [(t, "hybrid", other, src) for t, src in (("inbetween", "Table 2"), ("hmd", "Table 3"),
                                                   ("navigation", "section 6.3"))
          for other in ("continuous", "discrete", "discrete+")] + [
    ("navigation", a, "hybrid_m8", "Fig. 13") for a in ("hybrid", "hybrid_m2", "hybrid_m4")] + [
    ("navigation", "hybrid_m4", "discrete+_m4", "Fig. 13")]

_RUN = re.compile(r"^(inbetween|hmd|navigation)_(.+)_seed(\d+)$")


def seeded_runs(R: Path) -> dict:
    """{task: {variant: {seed: evaluation}}} of every evaluated run under R/tasks."""
    out: dict = {}
    for d in sorted((R / "tasks").glob("*_seed*")):
        m = _RUN.match(d.name)
        if not m or not (d / EVAL_FILE[m[1]]).exists():
            continue
        out.setdefault(m[1], {}).setdefault(m[2], {})[int(m[3])] = json.loads((d / EVAL_FILE[m[1]]).read_text())
    return out


def values(evals: dict, key: str) -> list[float]:
    """One value per seed, in seed order; a seed whose evaluation has none (no target reached, so no
    time to reach) is left out, and the seed count says so."""
    return [e[key] for _, e in sorted(evals.items()) if isinstance(e.get(key), (int, float))]


def fmt(x: float, f: str) -> str:
    return f"{100 * x:.1f} %" if f == PCT else f.format(x)


def cell(xs: list[float], f: str) -> str:
    """mean ± the 95 % half-width over seeds (shares in percent); one seed: its value."""
    if not xs:
        return ""
    if len(xs) == 1:
        return fmt(xs[0], f) + " (1 seed)"
    iv = mean_interval(xs)
    if f == PCT:
        return f"{100 * iv.estimate:.1f} ± {100 * iv.half:.1f} %"
    return f"{f.format(iv.estimate)} ± {f.format(iv.half)}"


def _table(head: list[str], rows: list[list]) -> str:
    out = ["| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
    return "\n".join(out + ["| " + " | ".join(str(c) for c in r) + " |" for r in rows])


def seeded_tables(R: Path) -> str:
    """One table per task: a row per prior (and per M for navigation) with the mean ± 95 % interval
    of every column over its seeds, the paper's row beside each where PAPER has it."""
    runs, out = seeded_runs(R), []
    for task in ("inbetween", "hmd", "navigation"):
        if task not in runs:
            continue
        cols = METRICS[task] + EXTRA[task]
        rows = []
        transcribed = PAPER[task]["values"]
        for v, paper in transcribed.items():
            unknown = sorted(set(paper) - {k for k, _, _, _ in cols})
            if unknown:
                raise ValueError(f"PAPER[{task!r}] row {v!r}: {', '.join(unknown)} not among the table's columns")
        order = [v for v in TASK_PRIORS if v in runs[task]] + sorted(v for v in runs[task] if v not in TASK_PRIORS)
        # each paper row under ours; the paper's rows of priors we have no run of after all of ours
        for v in order + [v for v in transcribed if v not in runs[task]]:
            if v in runs[task]:
                ev = runs[task][v]
                rows.append([v, ", ".join(str(s) for s in sorted(ev))] + [cell(values(ev, k), f) for k, _, _, f in cols])
            if transcribed.get(v):
                p = transcribed[v]
                rows.append([f"{v} (paper)", ""] + [fmt(p[k], f) if k in p else "" for k, _, _, f in cols])
        note = "" if any(transcribed.values()) else \
            f" The paper's values ({PAPER[task]['source']}) are not transcribed: PAPER in scripts/task_tables.py."
        out.append(f"{TITLE[task]}: mean ± 95 % interval over seeds (Student t).{note}\n\n"
                   + _table(["prior", "seeds"] + [h for _, h, _, _ in cols], rows))
    return "\n\n".join(out)


def claims(R: Path) -> str:
    """Each of the paper's claims on every column of its table, with its verdict: holds, does not
    hold or undecided (the Welch interval of the difference of means, at least MIN_SEEDS seeds)."""
    runs, rows = seeded_runs(R), []
    for task, a, b, src in CLAIMS:
        ea, eb = runs.get(task, {}).get(a), runs.get(task, {}).get(b)
        if not ea or not eb:
            continue
        for key, head, better, f in METRICS[task]:
            xa, xb = values(ea, key), values(eb, key)
            if not xa or not xb:
                continue
            word = "below" if better == "lower" else "above"
            rows.append([f"{TITLE[task].split(' (')[0].lower()} ({src}): {a} {word} {b}, {head}",
                         f"{fmt(sum(xa) / len(xa), f)} ({len(xa)})", f"{fmt(sum(xb) / len(xb), f)} ({len(xb)})",
                         str(verdict(xa, xb, better))])
    if not rows:
        return ""
    return (f"The paper's claims over seeds (holds / does not hold: the 95 % Welch interval of the difference "
            f"excludes zero that way; undecided otherwise or under {MIN_SEEDS} seeds a side):\n\n"
            + _table(["claim", "A: mean (seeds)", "B: mean (seeds)", "verdict"], rows))


def stage_times(R: Path) -> str:
    """The wall time of each stage from the queue's $R/logs/times.tsv: commands, hours, and the
    task runs' median training time (a run trained in pieces counts once, its pieces summed)."""
    f = R / "logs" / "times.tsv"
    if not f.exists():
        return ""
    per_stage: dict = {}
    per_run: dict = {}
    for line in f.read_text().splitlines():
        parts = line.split("\t")
        if len(parts) < 6:
            continue
        _, stage, name, secs, out, _ = parts[:6]
        s = per_stage.setdefault(stage or "-", [0, 0.0])
        s[0] += 1
        s[1] += float(secs)
        if _RUN.match(Path(out).name) and name == Path(out).name:  # a training piece, not an evaluation
            per_run[out] = per_run.get(out, 0.0) + float(secs)
    rows = [[k, n, f"{secs / 3600:.2f} h"] for k, (n, secs) in per_stage.items()]
    out = "Wall time per stage (logs/times.tsv):\n\n" + _table(["stage", "commands", "wall"], rows)
    if per_run:
        out += (f"\n\nTask runs trained: {len(per_run)}, median "
                f"{statistics.median(per_run.values()) / 60:.0f} min each.")
    return out
