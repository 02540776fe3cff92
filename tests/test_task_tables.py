"""scripts/task_tables.py through scripts/physics_tables.py: the task tables over seeds and the
paper's claims, each decided by the rule of motok/eval/seeds.py, read from fabricated run folders."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]


def tables(runs: Path) -> str:
    p = subprocess.run([sys.executable, str(ROOT / "scripts" / "physics_tables.py"), "--runs", str(runs)],
                       capture_output=True, text=True, timeout=60)
    assert p.returncode == 0, p.stderr
    return p.stdout


def test_the_claims_are_decided_over_seeds(tmp_path):
    """3 seeds x 2 priors of in-betweening evaluations with known numbers: each claim's verdict by
    the Welch interval (holds, does not hold, undecided), and undecided under 3 seeds a side."""
    runs = tmp_path / "runs"

    def put(run, seed, task, **vals):
        d = runs / "tasks" / f"{task}_{run}_seed{seed}"
        d.mkdir(parents=True, exist_ok=True)
        name = "eval_navigation.json" if task == "navigation" else f"eval_{task}_test.json"
        (d / name).write_text(json.dumps(vals))

    base = {f"{f}{k}_mean": 50.0 for f in ("", "keyframe_") for k in ("mpjpe_mm", "g_mpjpe_mm", "vel_err_mm",
                                                                      "acc_err_mm")}
    # keyframe MPJPE: hybrid 80, 82, 84 against 90, 92, 94: the difference -10, CI -10 +- 2.776 sqrt(8/3)
    # (-14.5, -5.47) below zero: holds. All-frame MPJPE: hybrid 90, 92, 94 against 80, 82, 84: does
    # not hold. Keyframe G-MPJPE: 80, 90, 100 against 85, 86, 87: the interval spans zero: undecided.
    for s in range(3):
        put("hybrid", s, "inbetween", **{**base, "keyframe_mpjpe_mm_mean": 80.0 + 2 * s, "mpjpe_mm_mean": 90.0 + 2 * s,
                                         "keyframe_g_mpjpe_mm_mean": 80.0 + 10 * s, "success_rate": 0.5 + 0.1 * s})
        put("continuous", s, "inbetween", **{**base, "keyframe_mpjpe_mm_mean": 90.0 + 2 * s,
                                             "mpjpe_mm_mean": 80.0 + 2 * s, "keyframe_g_mpjpe_mm_mean": 85.0 + s,
                                             "success_rate": 0.6})
    out = tables(runs)
    claim = "| in-betweening (Table 2): hybrid below continuous, "
    assert claim + "keyframes MPJPE mm | 82.0 (3) | 92.0 (3) | holds (diff -10, CI [-14.5, -5.47], 3 seeds each) |" in out
    assert (claim + "all frames MPJPE mm | 92.0 (3) | 82.0 (3) | does not hold (diff +10, CI [+5.47, +14.5], "
            "3 seeds each) |") in out
    assert claim + "keyframes G-MPJPE mm | 90.0 (3) | 86.0 (3) | undecided (diff +4" in out
    # the table: mean +- the t half-width over the seeds (82 +- 4.303 * 2 / sqrt(3) = 4.97), shares in percent
    row = next(x for x in out.splitlines() if x.startswith("| hybrid | 0, 1, 2 |"))
    assert row.startswith("| hybrid | 0, 1, 2 | 82.0 ± 5.0 | 90.0 ± 24.8 |") and row.endswith("| 60.0 ± 24.8 % |"), row
    assert "head tracking" not in out and "navigation (" not in out  # runs that are not there claim nothing
    # the third seed of one prior missing: every in-betweening claim undecided, whatever the gap
    for f in (runs / "tasks" / "inbetween_continuous_seed2").iterdir():
        f.unlink()
    out = tables(runs)
    assert claim + "keyframes MPJPE mm | 82.0 (3) | 91.0 (2) | undecided (diff -9, CI [" in out
    verdicts = [x.split(" | ")[-1] for x in out.splitlines() if x.startswith("| in-betweening (Table 2)")]
    assert len(verdicts) == 8 and all(v.startswith("undecided") and "3 and 2 seeds" in v for v in verdicts)
    # navigation: a seed that reached no target has no time to reach, and counts as no seed for it
    for s, (reached, t) in enumerate(((0.02, 3.0), (0.0, None), (0.04, 3.5))):
        put("hybrid", s, "navigation", reached_share=reached, time_to_reach_mean_s=t, falls_per_episode=0.1)
        put("discrete", s, "navigation", reached_share=0.5, time_to_reach_mean_s=2.0, falls_per_episode=0.1 + 0.1 * s)
    out = tables(runs)
    nav = "| navigation (section 6.3): hybrid "
    line = next(x for x in out.splitlines() if x.startswith(nav + "below discrete, time to reach s"))
    assert line.startswith(nav + "below discrete, time to reach s | 3.25 (2) | 2.00 (3) | undecided (diff +1.25")
    assert line.endswith("2 and 3 seeds) |")
    assert nav + "above discrete, targets reached | 2.0 % (3) | 50.0 % (3) | does not hold (diff -0.48" in out
    assert nav + "below discrete, falls / episode | 0.10 (3) | 0.20 (3) | holds (diff -0.1, CI [-0.348, +0.148]" not in out
    assert nav + "below discrete, falls / episode | 0.10 (3) | 0.20 (3) | undecided (diff -0.1, CI [-0.348, +0.148]" in out


def test_the_papers_row_prints_beside_ours(tmp_path, script, monkeypatch):
    """A row of PAPER prints under our row of the same prior, in the columns' formats, and the
    "not transcribed" note goes; a key that is no column of the table is refused. The values here
    are made up for the test, not the paper's."""
    tt = script("task_tables")
    runs = tmp_path / "runs"
    base = {f"{f}{k}_mean": 50.0 for f in ("", "keyframe_") for k in ("mpjpe_mm", "g_mpjpe_mm", "vel_err_mm",
                                                                      "acc_err_mm")}
    for s in range(2):
        d = runs / "tasks" / f"inbetween_hybrid_seed{s}"
        d.mkdir(parents=True)
        (d / "eval_inbetween_test.json").write_text(json.dumps({**base, "success_rate": 0.5}))
    out = tt.seeded_tables(runs)
    assert "are not transcribed" in out and "(paper)" not in out
    monkeypatch.setitem(tt.PAPER["inbetween"], "values",
                        {"discrete": {"mpjpe_mm_mean": 70.0},
                         "hybrid": {"keyframe_mpjpe_mm_mean": 12.34, "mpjpe_mm_mean": 56.7, "success_rate": 0.852}})
    out = tt.seeded_tables(runs)
    lines = out.splitlines()
    ours = next(i for i, x in enumerate(lines) if x.startswith("| hybrid | 0, 1 |"))
    assert lines[ours + 1] == "| hybrid (paper) |  | 12.3 |  |  |  | 56.7 |  |  |  | 85.2 % |", lines[ours + 1]
    # a prior we have no run of still shows the paper's row, after ours
    assert lines[ours + 2] == "| discrete (paper) |  |  |  |  |  | 70.0 |  |  |  |  |", lines[ours + 2]
    assert "not transcribed" not in out
    monkeypatch.setitem(tt.PAPER["inbetween"], "values", {"hybrid": {"keyframe_mpjpe_mm": 12.3}})
    with pytest.raises(ValueError, match="keyframe_mpjpe_mm not among"):
        tt.seeded_tables(runs)
    # refused also in the row of a prior we have no run of
    monkeypatch.setitem(tt.PAPER["inbetween"], "values", {"continuous": {"succes_rate": 0.9}})
    with pytest.raises(ValueError, match="'continuous': succes_rate not among"):
        tt.seeded_tables(runs)


def test_the_transcribed_rows_print_beside_a_run_set(tmp_path, script):
    """The real PAPER: every row's keys are columns of its table (a misspelt key would print
    nothing) and its shares are fractions (a transcribed 85.2 instead of 0.852 prints as 8520 %);
    and over one seed of every prior, each task's table shows each transcribed row right under our
    row of its prior, every value in its own column in that column's format, or, for a task with
    nothing transcribed, says so and names the paper's table."""
    tt = script("task_tables")
    runs = tmp_path / "runs"
    for task, entry in tt.PAPER.items():
        cols = tt.METRICS[task] + tt.EXTRA[task]
        keys = {k for k, _, _, _ in cols}
        for variant, row in entry["values"].items():
            assert set(row) <= keys, (task, variant, set(row) - keys)
            assert all(0.0 <= row[k] <= 1.0 for k, _, _, f in cols if f == tt.PCT and k in row), (task, variant)
        for variant in tt.TASK_PRIORS:
            d = runs / "tasks" / f"{task}_{variant}_seed0"
            d.mkdir(parents=True)
            (d / tt.EVAL_FILE[task]).write_text(json.dumps({k: 0.5 for k in keys}))
    lines = tt.seeded_tables(runs).splitlines()
    for task, entry in tt.PAPER.items():
        start = next(i for i, x in enumerate(lines) if x.startswith(tt.TITLE[task] + ":"))
        end = next((i for i, x in enumerate(lines) if i > start and not x and lines[i - 1].startswith("|")), len(lines))
        block, title = lines[start:end], lines[start]
        assert sum(x.startswith("| ") and " (paper) |" not in x for x in block) == 1 + len(tt.TASK_PRIORS), block
        cols = tt.METRICS[task] + tt.EXTRA[task]
        if not any(entry["values"].values()):
            assert f"The paper's values ({entry['source']}) are not transcribed" in title, title
            assert not any("(paper)" in x for x in block), block
            continue
        assert "not transcribed" not in title, title
        for variant, row in entry["values"].items():
            ours = next(i for i, x in enumerate(block) if x.startswith(f"| {variant} | 0 |"))
            cells = [c.strip() for c in block[ours + 1].strip("|").split("|")]
            assert cells[:2] == [f"{variant} (paper)", ""], block[ours + 1]
            assert cells[2:] == [tt.fmt(row[k], f) if k in row else "" for k, _, _, f in cols], block[ours + 1]
