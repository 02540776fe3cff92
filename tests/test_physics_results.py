"""scripts/physics_results.sh, the resumable queue of the physics results: every option of every
command it issues is one the motok command line has (so a renamed option fails here, not hours
into a queue),
trainings resume exactly where a checkpoint exists and start fresh where none does, existing
outputs are not made again, and the stages run in their order."""

from __future__ import annotations

import json
import os
import subprocess
import sys
import time
from pathlib import Path

import h5py

from conftest import assert_cli_accepts

ROOT = Path(__file__).resolve().parents[1]
SCRIPT = ROOT / "scripts" / "physics_results.sh"
PRIORS = ("hybrid", "continuous", "discrete+", "discrete", "hybrid-vq")


def queue(tmp_path: Path, *stages: str, checkpoints=(), outputs=(), env=None) -> list[list[str]]:
    """Run the queue with a recorder in place of motok; the argv of every command it issued."""
    tmp_path.mkdir(parents=True, exist_ok=True)
    record = tmp_path / "argv.jsonl"
    shim = tmp_path / "record.py"
    shim.write_text(f"import json, sys\nopen({str(record)!r}, 'a').write(json.dumps(sys.argv[1:]) + '\\n')\n")
    runs = tmp_path / "runs"
    for d in checkpoints:
        (runs / d).mkdir(parents=True, exist_ok=True)
        (runs / d / "bundle.json").write_text(json.dumps({"config": {"iterations": 10}, "extra": {"iteration": 10}}))
        (runs / d / "metrics.jsonl").write_text("")
    for f in outputs:
        (runs / f).parent.mkdir(parents=True, exist_ok=True)
        (runs / f).write_text("")
    env = {**os.environ, "R": str(runs), "MOTOK": f"{sys.executable} {shim}", **(env or {})}
    p = subprocess.run(["bash", str(SCRIPT), *stages], env=env, capture_output=True, text=True, timeout=120)
    assert p.returncode == 0, p.stdout + p.stderr
    return [json.loads(line) for line in record.read_text().splitlines()] if record.exists() else []


def tables(runs: Path, *args: str) -> str:
    """What scripts/physics_tables.py prints for the run tree ``runs``."""
    p = subprocess.run([sys.executable, str(ROOT / "scripts" / "physics_tables.py"), "--runs", str(runs), *args],
                       capture_output=True, text=True, timeout=60)
    assert p.returncode == 0, p.stderr
    return p.stdout


def out_of(argv: list[str]) -> str:
    return Path(argv[argv.index("-o") + 1]).name


def test_every_command_is_accepted_by_the_cli(tmp_path):
    every = ["expert_set2", *(f"prior_{k}" for k in PRIORS), "tasks/navigation_hybrid_seed0",
             "tasks/navigation_continuous_seed1", "tasks/inbetween_hybrid_seed0", "tasks/hmd_discrete_seed2",
             "tasks/navigation_hybrid_m4_seed0", "kinematic/tokenizer", "kinematic/gpt"]
    cmds = queue(tmp_path, checkpoints=every)
    kinds = {tuple(a[:2]) for a in cmds}
    # each part of the chain is there: expert, distillation, evaluation, Table 1, tasks, text to physics
    for k in [("control", "expert"), ("control", "distill"), ("control", "eval"), ("control", "generate"),
              ("eval", "motion-matching"), ("control", "train"), ("control", "perturb"), ("control", "track"),
              ("eval", "t2m"), ("gpt", "train"), ("tokenize", "train"), ("preprocess", "--recipe")]:
        assert k in kinds, k
    plots = [a for a in cmds if a[0] == "plot"]
    assert {out_of(a) for a in plots} >= {"expert.png", "priors.png", "navigation.png", "navigation_wall.png"}
    priors = next(a for a in plots if out_of(a) == "priors.png")
    assert [Path(x).name for x in priors[1:1 + len(PRIORS)]] == [f"prior_{k}" for k in PRIORS]
    assert_cli_accepts(cmds)


def test_trainings_resume_only_from_a_checkpoint(tmp_path):
    cmds = queue(tmp_path, "priors", checkpoints=["prior_hybrid"])
    distills = {out_of(a): a for a in cmds if a[:2] == ["control", "distill"]}
    assert list(distills) == [f"prior_{k}" for k in PRIORS]  # in the queue's order
    assert "--resume" in distills["prior_hybrid"]
    assert all("--resume" not in a for name, a in distills.items() if name != "prior_hybrid")
    for k in PRIORS:  # each with its own recipe and kind, at one budget
        a = distills[f"prior_{k}"]
        assert a[a.index("--kind") + 1] == k and a[a.index("--recipe") + 1] == f"recipes/control/prior_{k}.yaml"
        assert "iterations=1500" in a


def test_each_prior_is_evaluated_before_the_next_is_distilled(tmp_path):
    """A session that ends in the `priors` stage keeps the numbers of every prior finished; Table 1
    (motion matching) waits for `prioreval` and reads every generation, in the queue's order."""
    cmds = queue(tmp_path, "priors", checkpoints=["prior_hybrid"])
    named = lambda a: next((Path(a[a.index(o) + 1]).name for o in ("--kind", "--prior") if o in a), None)  # noqa: E731
    steps = [(a[1], named(a)) for a in cmds]
    first = steps[:steps.index(("distill", "continuous"))]
    assert first[0] == ("distill", "hybrid")
    assert first[1:] == [("eval", "prior_hybrid")] * 2 + [("generate", "prior_hybrid")] * 8
    assert not any(a[:2] == ["eval", "motion-matching"] for a in cmds)
    gens = [f"table1/{t}.h5" for t in ("hybrid-m1", "hybrid-m2", "continuous", "discrete+-m1", "discrete+-m2",
                                       "discrete+-m3")]
    done = ["prior_hybrid/eval.json", "prior_hybrid/eval_test.json", "prior_continuous/eval.json",
            "prior_continuous/eval_test.json", "prior_discrete+/eval.json", "prior_discrete+/eval_test.json"]
    (tmp_path / "again").mkdir()
    cmds = queue(tmp_path / "again", "prioreval", checkpoints=["prior_hybrid", "prior_continuous", "prior_discrete+"],
                 outputs=gens + done)
    made = [out_of(a) for a in cmds if a[1] == "generate"]
    assert made == [f"hybrid-m{m}.h5" for m in range(3, 9)]  # only the missing rows
    mm = [a for a in cmds if a[:2] == ["eval", "motion-matching"]]
    assert len(mm) == 1 and cmds[-1] == mm[0]
    rows = [Path(mm[0][i + 1]).name for i, x in enumerate(mm[0]) if x == "--motions"]
    assert rows == [f"hybrid-m{m}.h5" for m in range(1, 9)] + ["continuous.h5"] + [f"discrete+-m{m}.h5"
                                                                                      for m in (1, 2, 3)]


def test_some_priors_first_and_table1_later(tmp_path):
    """PRIORS picks the priors `priors` distils (in the queue's order, whatever order it is given
    in) and TABLE1=0 leaves their Table 1 generations to `prioreval`; an unknown name stops the
    queue before anything runs."""
    cmds = queue(tmp_path, "priors", env={"PRIORS": "continuous hybrid", "TABLE1": "0"})
    assert [(a[1], out_of(a) if a[1] == "distill" else None) for a in cmds if a[1] != "eval"] == [
        ("distill", "prior_hybrid"), ("distill", "prior_continuous")]
    assert [a[1] for a in cmds] == ["distill", "eval", "eval"] * 2
    (tmp_path / "later").mkdir()
    cmds = queue(tmp_path / "later", "prioreval", checkpoints=["prior_hybrid"], env={"PRIORS": "continuous"})
    assert [out_of(a) for a in cmds if a[1] == "generate"] == [f"hybrid-m{m}.h5" for m in range(1, 9)]
    p = subprocess.run(["bash", str(SCRIPT), "priors"], env={**os.environ, "R": str(tmp_path / "bad"), "MOTOK": "false",
                       "PRIORS": "hybrid hybird"}, capture_output=True, text=True, timeout=60)
    assert p.returncode == 2 and "unknown prior 'hybird'" in p.stderr and not (tmp_path / "bad").exists()


def test_outputs_that_exist_are_not_made_again(tmp_path):
    cmds = queue(tmp_path, "data", "expert", outputs=["bandai2.h5", "expert_set2/eval_val.json"])
    assert [a[:3] for a in cmds] == [["control", "expert", "train"], ["control", "expert", "eval"]]
    assert cmds[1][cmds[1].index("--split") + 1] == "test"


def sets(argv: list[str]) -> list[str]:
    return [argv[i + 1] for i, x in enumerate(argv) if x == "--set"]


def test_every_task_cell_is_trained_on_every_seed_at_one_budget(tmp_path):
    """`tasks`: each (task, prior, seed) once, seeds outermost (after one pass every cell has a seed),
    the same iterations for all, the seed as the run's own; a prior not distilled yet is skipped."""
    cmds = queue(tmp_path, "tasks", checkpoints=["prior_hybrid", "prior_continuous", "prior_discrete"],
                 env={"SEEDS": "0 1", "TASKS": "hmd navigation"})
    trains = [a for a in cmds if a[:2] == ["control", "train"]]
    assert [out_of(a) for a in trains] == [f"{t}_{k}_seed{s}" for s in (0, 1) for t in ("hmd", "navigation")
                                           for k in ("continuous", "discrete", "hybrid")]
    for a in trains:
        t, k, s = out_of(a).rsplit("_", 2)
        assert a[a.index("--task") + 1] == t and a[a.index("--recipe") + 1] == f"recipes/control/task_{t}.yaml"
        assert Path(a[a.index("--prior") + 1]).name == f"prior_{k}"
        # every prior at its recipe's settings (the continuous prior's std and lr are the recipe's)
        assert sets(a) == ["iterations=3000", f"seed={s.removeprefix('seed')}"]
        assert Path(a[a.index("-o") + 1]).parent.name == "tasks" and "--resume" not in a
    cmds = queue(tmp_path / "plain", "tasks", checkpoints=["prior_continuous"],
                 env={"SEEDS": "3", "TASKS": "inbetween", "CONTINUOUS_SET": "net.std=0.2"})
    assert [(out_of(a), sets(a)) for a in cmds] == [("inbetween_continuous_seed3",
                                                     ["iterations=3000", "seed=3", "net.std=0.2"])]


def test_fig13_runs_over_the_first_codebooks_on_every_seed(tmp_path):
    cmds = queue(tmp_path, "codebooks", checkpoints=["prior_hybrid", "prior_discrete+"], env={"SEEDS": "0 1 2"})
    runs = [(out_of(a), a[a.index("--codebooks") + 1]) for a in cmds]
    assert runs == [(f"navigation_{k}_m{m}_seed{s}", str(m)) for s in (0, 1, 2)
                    for k, m in (("hybrid", 2), ("hybrid", 4), ("hybrid", 8), ("discrete+", 4))]


def test_bad_seeds_or_tasks_stop_the_queue_before_anything_runs(tmp_path):
    for env, said in (({"SEEDS": "0 one"}, "SEEDS: 'one' is not a seed"),
                      ({"TASKS": "inbetween hdm"}, "TASKS: unknown task 'hdm'")):
        p = subprocess.run(["bash", str(SCRIPT), "tasks"], capture_output=True, text=True, timeout=60,
                           env={**os.environ, "R": str(tmp_path / "bad"), "MOTOK": "false", **env})
        assert p.returncode == 2 and said in p.stderr and not (tmp_path / "bad").exists(), p.stderr


def test_tables_2_3_are_evaluated_on_the_test_clips(tmp_path):
    """Each finished run is evaluated and not trained again: in-betweening and head tracking on
    windows of the test split (their policies trained on the train clips); navigation draws its
    targets and needs no clips, then the thrown balls; the videos of the first seed only."""
    done = ["tasks/navigation_hybrid_seed0", "tasks/inbetween_hybrid_seed1", "tasks/hmd_continuous_seed0"]
    env = {"SEEDS": "0 1"}
    cmds = queue(tmp_path, "tasks", checkpoints=["prior_hybrid", "prior_continuous", *done], env=env)
    assert not any(a[:2] == ["control", "train"] and out_of(a) in [Path(d).name for d in done] for a in cmds)
    evals = {Path(a[a.index("--policy") + 1]).name: a for a in cmds if a[:2] == ["control", "eval"]}
    assert set(evals) == {Path(d).name for d in done}
    for name in ("inbetween_hybrid_seed1", "hmd_continuous_seed0"):
        a = evals[name]
        assert a[a.index("--split") + 1] == "test" and a[a.index("-d") + 1].endswith("bandai2.h5")
    assert "--split" not in evals["navigation_hybrid_seed0"]
    assert "--render" in evals["hmd_continuous_seed0"] and "--render" not in evals["inbetween_hybrid_seed1"]
    periods = [a[a.index("--period") + 1] for a in cmds if "--period" in a]
    assert periods == ["1", "3", "1000"]  # besides the paper's 0.3 s (no --period), in their own files
    outputs = ["tasks/inbetween_hybrid_seed1/eval_inbetween_test.json", "tasks/hmd_continuous_seed0/eval_hmd_test.json",
               "tasks/navigation_hybrid_seed0/eval_navigation.json", "tasks/navigation_hybrid_seed0/perturb.json",
               *(f"tasks/navigation_hybrid_seed0/perturb_period{p}.json" for p in periods)]
    cmds = queue(tmp_path / "again", "tasks", checkpoints=["prior_hybrid", "prior_continuous", *done], outputs=outputs,
                 env=env)
    assert not any(a[:2] in (["control", "eval"], ["control", "perturb"]) for a in cmds)


def test_a_task_run_stopped_before_its_end_is_resumed_not_evaluated(tmp_path):
    """An evaluation file is never made again, so one of a half-trained policy would stand for the
    run: a run its session stopped is resumed, and evaluated only once its checkpoint is the last."""
    runs = tmp_path / "runs"
    for d, it in (("tasks/navigation_hybrid_seed0", 3000), ("tasks/inbetween_hybrid_seed0", 2950), ("prior_hybrid", 1)):
        (runs / d).mkdir(parents=True)
        (runs / d / "bundle.json").write_text(json.dumps({"config": {"iterations": 3000}, "extra": {"iteration": it}}))
    shim = tmp_path / "record.py"
    shim.write_text("import json, sys\nprint(json.dumps(sys.argv[1:]), file=sys.stderr)\n")
    p = subprocess.run(["bash", str(SCRIPT), "tasks"], capture_output=True, text=True, timeout=120,
                       env={**os.environ, "R": str(runs), "MOTOK": f"{sys.executable} {shim}", "SEEDS": "0",
                            "TASKS": "inbetween navigation"})
    assert p.returncode == 0, p.stdout + p.stderr
    ib = str(runs / "tasks" / "inbetween_hybrid_seed0")
    train = next(x for x in p.stdout.splitlines() if "-o " + ib in x)
    assert train.endswith("--resume")  # resumed where it stopped...
    # ...and, as the recorder leaves it at 2,950, not evaluated
    assert f"skip {ib}: not evaluated at iteration 2950 of 3000" in p.stdout
    assert "--policy " + ib not in p.stdout
    assert "--policy " + str(runs / "tasks" / "navigation_hybrid_seed0") in p.stdout  # the finished one is
    assert "-o " + str(runs / "tasks" / "navigation_hybrid_seed0") not in p.stdout  # and not trained again


def test_every_command_wall_time_is_logged_by_stage(tmp_path):
    """logs/times.tsv: one line per command (stage, log, seconds, its output, status), which
    physics_tables.py --status sums per stage."""
    cmds = queue(tmp_path, "data", "tasks", checkpoints=["prior_hybrid"], env={"SEEDS": "0", "TASKS": "hmd"})
    assert len(cmds) == 2
    lines = [x.split("\t") for x in (tmp_path / "runs" / "logs" / "times.tsv").read_text().splitlines()]
    assert [(x[1], x[2], Path(x[4]).name, x[5]) for x in lines] == [
        ("data", "preprocess", "bandai2.h5", "ok"), ("tasks", "hmd_hybrid_seed0", "hmd_hybrid_seed0", "ok")]
    assert all(x[3].isdigit() for x in lines)
    (tmp_path / "runs" / "logs" / "times.tsv").write_text(
        "2026-12-07T01:00:00Z\ttasks\thmd_hybrid_seed0\t1800\t/r/tasks/hmd_hybrid_seed0\tstopped\n"
        "2026-12-07T02:00:00Z\ttasks\thmd_hybrid_seed0\t900\t/r/tasks/hmd_hybrid_seed0\tok\n"
        "2026-12-07T02:01:00Z\ttasks\ttask_eval\t60\t/r/tasks/hmd_hybrid_seed0\tok\n"
        "2026-12-07T03:00:00Z\ttasks\thmd_continuous_seed0\t3600\t/r/tasks/hmd_continuous_seed0\tok\n"
        "2026-12-07T03:30:00Z\tpriors\tprior_hybrid\t1800\t/r/prior_hybrid\tok\n")
    out = tables(tmp_path / "runs", "--status")
    # tasks: 1,800 + 900 + 60 + 3,600 s; the two runs trained 45 and 60 min (pieces summed, evaluations not)
    assert "| tasks | 4 | 1.77 h |" in out and "| priors | 1 | 0.50 h |" in out, out
    assert "Task runs trained: 2, median 52 min each." in out


def test_an_unknown_stage_fails_before_anything_runs(tmp_path):
    p = subprocess.run(["bash", str(SCRIPT), "data", "bogus"], env={**os.environ, "R": str(tmp_path / "runs"),
                       "MOTOK": "false"}, capture_output=True, text=True, timeout=60)
    assert p.returncode == 2 and "unknown stage 'bogus'" in p.stderr
    assert not (tmp_path / "runs" / "logs").exists() or not any((tmp_path / "runs" / "logs").iterdir())


def test_every_stage_runs_on_one_arithmetic(tmp_path):
    """The data stage too (its features differ in the last bits with numpy's AVX-512 kernels, and
    an expert trained on them is another run): on an AVX-512 machine every command gets the AVX2
    caps unless ARITH=native; elsewhere nothing is capped (numpy objects to disabling what is not there)."""
    from motok.machine import ARITHMETIC_ENV
    record = tmp_path / "env.jsonl"
    shim = tmp_path / "env.py"
    shim.write_text(f"import json, os\nopen({str(record)!r}, 'a').write(json.dumps("
                    f"{{k: os.environ.get(k) for k in {list(ARITHMETIC_ENV)!r}}}) + '\\n')\n")
    base = {k: v for k, v in os.environ.items() if k not in ARITHMETIC_ENV and k != "ARITH"}
    avx512 = "avx512f" in Path("/proc/cpuinfo").read_text().split() if Path("/proc/cpuinfo").exists() else False
    for arith in ("avx2", "native"):
        record.unlink(missing_ok=True)
        env = {**base, "ARITH": arith, "R": str(tmp_path / arith), "MOTOK": f"{sys.executable} {shim}"}
        p = subprocess.run(["bash", str(SCRIPT), "data", "expert"], env=env, capture_output=True, text=True, timeout=60)
        assert p.returncode == 0, p.stdout + p.stderr
        seen = [json.loads(line) for line in record.read_text().splitlines()]
        assert len(seen) == 4  # preprocess, expert, its val and test evaluations
        capped = avx512 and arith == "avx2"
        for e in seen:
            assert e["NPY_DISABLE_CPU_FEATURES"] == ("X86_V4 AVX512_ICL" if capped else None)
            assert e["ATEN_CPU_CAPABILITY"] == ("avx2" if capped else None)


def test_editing_the_script_while_it_runs_changes_nothing(tmp_path):
    """A queue runs for hours beside a checkout being edited; bash reads a script as it goes, so
    an edit that moves the bytes after the running command would make it run something else."""
    copy = tmp_path / "scripts" / SCRIPT.name
    copy.parent.mkdir()
    copy.write_text(SCRIPT.read_text())
    record = tmp_path / "argv.jsonl"
    shim = tmp_path / "edit.py"
    # the first command the queue issues shifts the whole file by a block of comments, in place
    shim.write_text(f"import json, sys\nfrom pathlib import Path\nr, s = Path({str(record)!r}), Path({str(copy)!r})\n"
                    "if not r.exists():\n    t = s.read_text(); i = t.index('\\n', t.index('set -euo'))\n"
                    "    s.write_text(t[:i + 1] + '# moved\\n' * 400 + t[i + 1:])\n"
                    "r.open('a').write(json.dumps(sys.argv[1:]) + '\\n')\n")
    env = {**os.environ, "R": str(tmp_path / "runs"), "MOTOK": f"{sys.executable} {shim}"}
    p = subprocess.run(["bash", str(copy), "data", "expert"], env=env, capture_output=True, text=True, timeout=60)
    assert p.returncode == 0, p.stdout + p.stderr
    cmds = [json.loads(line) for line in record.read_text().splitlines()]
    assert [a[:2] for a in cmds] == [["preprocess", "--recipe"], ["control", "expert"], ["control", "expert"],
                                     ["control", "expert"]]
    assert p.stdout.count("stage ") == 2 and "done: results" in p.stdout


def test_a_failing_command_stops_the_queue(tmp_path):
    shim = tmp_path / "fail.py"
    shim.write_text("import sys\nsys.exit(3)\n")
    env = {**os.environ, "R": str(tmp_path / "runs"), "MOTOK": f"{sys.executable} {shim}"}
    p = subprocess.run(["bash", str(SCRIPT), "expert", "priors"], env=env, capture_output=True, text=True, timeout=60)
    assert p.returncode == 3
    assert "expert_set2 failed (exit 3)" in p.stdout and "stage priors" not in p.stdout


def test_the_tables_read_the_queue_outputs(tmp_path):
    """scripts/physics_tables.py prints nothing for an empty tree and, for a prior run and a Table 1
    report as the queue writes them, rows with their numbers."""
    tables = ROOT / "scripts" / "physics_tables.py"
    runs = tmp_path / "runs"
    runs.mkdir()
    p = subprocess.run([sys.executable, str(tables), "--runs", str(runs)], capture_output=True, text=True, timeout=60)
    assert p.returncode == 0 and p.stdout.strip() == ""
    prior = runs / "prior_hybrid"
    prior.mkdir()
    rows = [{"iteration": i, "samples": 4096 * i, "wall_s": 1.1 * i, "samples_per_s": 3800.0, "code_usage": 0.9}
            for i in (1, 2)]
    rows[1]["eval_success"] = 0.25
    (prior / "metrics.jsonl").write_text("\n".join(json.dumps(r) for r in rows))
    overall = {"success_rate": 0.635, "success_rate_any_body": 0.604, "mpjpe_mm": 52.6, "g_mpjpe_mm": 114.0,
               "root_vel_err_mm": 8.16, "root_acc_err_mm": 5.92}
    (prior / "eval_test.json").write_text(json.dumps({"overall": overall}))
    (runs / "table1").mkdir()
    (runs / "table1" / "table1.json").write_text(json.dumps({
        "threshold": {"value": 3.668, "definition": "95th percentile"},
        "dataset": {"transitions": 10, "jitter_m_s3": 55.7},
        "rows": [{"motion": "runs/table1/hybrid-m1.h5", "transitions": 5, "distance_mean": 1.25, "filtered_rate": 0.1,
                  "coverage": 0.2, "coverage_within_threshold": 0.15, "jitter_m_s3": 60.0}]}))
    with h5py.File(runs / "table1" / "hybrid-m1.h5", "w") as f:  # the labels `control generate` writes
        f.create_group("clips")["labels"] = [json.dumps({"sample": i, "fell_at_s": t}) for i, t in
                                             enumerate((None, 4.5, None))]
    nav = runs / "tasks" / "navigation_hybrid_seed0"  # thrown balls: one row per run and period
    nav.mkdir(parents=True)
    ball = {"episodes": 64, "hits": 566, "terminated_share": 63 / 64, "recoveries": 90, "hits_resolved": 500,
            "recovery_rate": 0.18, "hits_censored": 66, "reached_share": 0.01, "success": 1 / 64,
            "config": {"period": 0.3}}
    (nav / "perturb.json").write_text(json.dumps(ball))
    (nav / "perturb_period1000.json").write_text(json.dumps({**ball, "hits": 0, "recoveries": 0, "hits_resolved": 0,
                                                             "recovery_rate": None, "hits_censored": 0,
                                                             "config": {"period": 1000.0}}))
    (nav / "perturb_period3.json").write_text(json.dumps({**ball, "hits": 102, "terminated_share": 0.5,
                                                          "config": {"period": 3.0}}))
    out = subprocess.run([sys.executable, str(tables), "--runs", str(runs)], capture_output=True, text=True,
                         timeout=60).stdout
    rows = [x for x in out.splitlines() if x.startswith("| navigation_hybrid_seed0 |")]
    assert rows == ["| navigation_hybrid_seed0 | 0.3 s | 566 | 63 / 64 | 90 / 500 | 18.0 % | 66 | 1.0 % | 1.6 % |",
                    "| navigation_hybrid_seed0 | 3 s | 102 | 32 / 64 | 90 / 500 | 18.0 % | 66 | 1.0 % | 1.6 % |",
                    "| navigation_hybrid_seed0 | never in 8 s | 0 | 63 / 64 | 0 / 0 |  | 0 | 1.0 % | 1.6 % |"], out
    assert "| hybrid | 2 | 0.0 M | 0 min | 3,800 |  | 63.5 % | 60.4 % | 52.6 | 114.0 | 8.16 | 5.92 | 0.90 |" in out
    assert "| prior | 2 |" in out and "| hybrid | 25.0 % |" in out
    assert "| hybrid-m1 | 5 | 1.250 | 10.0 % | 20.0 % | 15.0 % |  | 60.0 | 1 / 3 |" in out and "threshold 3.668" in out
    kin = runs / "kinematic"  # text to physics: the t2m table as written, and each tracking's report
    kin.mkdir()
    (kin / "t2m-physics.md").write_text("| Motion | R@1 ↑ |\n|---|---|\n| generated_sim | 0.500±0.010 |\n")
    (kin / "generated_sim.track.json").write_text(json.dumps({
        "clips": 100, "written": 98, "tracked_to_end": 0.749, "mpjpe_mm": 52.2, "g_mpjpe_mm": 120.5,
        "sole_slip": {"simulated": {"sole_slip_cm_s": 30.5}, "reference": {"sole_slip_cm_s": 18.1}}}))
    (kin / "real_test_sim.track.json").write_text(json.dumps({  # written before the sole slip was reported
        "clips": 427, "written": 427, "tracked_to_end": 0.916, "mpjpe_mm": 47.3, "g_mpjpe_mm": 100.0}))
    out = subprocess.run([sys.executable, str(tables), "--runs", str(runs)], capture_output=True, text=True,
                         timeout=60).stdout
    assert "| generated_sim | 0.500±0.010 |" in out
    assert "| generated_sim | 100 | 98 | 74.9 % | 52.2 | 120.5 | 30.5 | 18.1 |" in out, out
    assert "| real_test_sim | 427 | 427 | 91.6 % | 47.3 | 100.0 |  |  |" in out


def test_the_orderings_are_read_from_the_outputs(tmp_path):
    """Each of the paper's orderings is said to hold or not from the numbers of the files, in the
    right direction (a lower distance and MPJPE are better, a higher coverage and success)."""
    tables = ROOT / "scripts" / "physics_tables.py"
    runs = tmp_path / "runs"

    def put(rel, obj):
        (runs / rel).parent.mkdir(parents=True, exist_ok=True)
        (runs / rel).write_text(json.dumps(obj))

    def printed():
        return subprocess.run([sys.executable, str(tables), "--runs", str(runs)], capture_output=True, text=True,
                              timeout=60).stdout

    row = lambda tag, d, c: {"motion": f"runs/table1/{tag}.h5", "transitions": 5, "distance_mean": d,
                             "filtered_rate": 0.1, "coverage": c, "coverage_within_threshold": c, "jitter_m_s3": 1.0}
    put("table1/table1.json", {"threshold": {"value": 3.0, "definition": "x"},
                               "dataset": {"transitions": 10, "jitter_m_s3": 1.0},
                               "rows": [row("hybrid-m1", 1.5, 0.30), row("discrete+-m1", 2.0, 0.40)]})
    for kind, success, mpjpe in (("hybrid", 0.93, 49.0), ("hybrid-vq", 0.95, 52.0), ("discrete+", 0.90, 50.0),
                                 ("discrete", 0.80, 55.0)):
        put(f"prior_{kind}/eval_test.json", {"overall": {"success_rate": success, "mpjpe_mm": mpjpe}})
    out = printed()
    assert "| hybrid(1) distance below discrete+(1) (Table 1) | hybrid-m1 1.500, discrete+-m1 2.000 | holds |" in out
    assert "| hybrid(1) coverage above discrete+(1) (Table 1) | hybrid-m1 30.0 %, discrete+-m1 40.0 % | does not hold |" in out
    assert "discrete+ above discrete, test clips played to the end | discrete+ 90.0 %, discrete 80.0 % | holds |" in out
    assert "hybrid above hybrid-vq, test clips played to the end | hybrid 93.0 %, hybrid-vq 95.0 % | does not hold |" in out
    assert "hybrid below hybrid-vq, test MPJPE | hybrid 49.0 mm, hybrid-vq 52.0 mm | holds |" in out
    assert "continuous" not in out.split("orderings")[1]  # no continuous run: no row claims anything of it
    assert "navigation" not in out.split("orderings")[1]  # nor of navigation runs that are not there
    # with coverage at equal size in the report, the claim is read from it (the row that fell sooner had
    # fewer transitions to cover with)
    rows = [{**row("hybrid-m1", 1.5, 0.30), "coverage_equal_n": 0.25, "coverage_n": 4},
            {**row("discrete+-m1", 2.0, 0.40), "coverage_equal_n": 0.20, "coverage_n": 4}]
    put("table1/table1.json", {"threshold": {"value": 3.0, "definition": "x"},
                               "dataset": {"transitions": 10, "jitter_m_s3": 1.0}, "rows": rows})
    out = printed()
    assert "| hybrid(1) coverage equal n above discrete+(1) (Table 1) | hybrid-m1 25.0 %, discrete+-m1 20.0 % | holds |" in out
    assert "| coverage, equal n (4) |" in out and "| hybrid-m1 | 5 | 1.500 | 10.0 % | 30.0 % | 30.0 % | 25.0 % |" in out


def test_the_status_says_where_each_run_stands(tmp_path):
    tables = ROOT / "scripts" / "physics_tables.py"
    runs = tmp_path / "runs"
    (runs / "logs").mkdir(parents=True)
    (runs / "logs" / "queue.log").write_text("[14:00:00] stage expert\n[14:00:01] expert_set2: motok control ...\n")
    expert = runs / "expert_set2"
    expert.mkdir()
    rows = [{"iteration": i, "samples": 4096 * i, "wall_s": 3.6 * i, "samples_per_s": 4000.0 + i} for i in (1, 2, 3)]
    rows[1].update(eval_success=0.5, eval_mpjpe_mm=50.0)
    (expert / "metrics.jsonl").write_text("\n".join(json.dumps(r) for r in rows))
    (expert / "eval_val.json").write_text("{}")
    (expert / "bundle.json").write_text("{}")
    out = subprocess.run([sys.executable, str(tables), "--runs", str(runs), "--status"], capture_output=True,
                         text=True, timeout=60).stdout
    assert "| expert_set2 | 3 | 0.0 M | 0.00 h | 4,002 | success 0.5 (it 2), mpjpe_mm 50 (it 2) | eval_val.json |" in out
    assert out.strip().endswith("queue: [14:00:01] expert_set2: motok control ...")
    # with a bundle: the goal from the command's --until (else the config), and the time left at the pace
    (expert / "bundle.json").write_text(json.dumps({"provenance": {"command": "motok control expert train --until 1003"},
                                                    "config": {"iterations": 40000}}))
    out = subprocess.run([sys.executable, str(tables), "--runs", str(runs), "--status"], capture_output=True,
                         text=True, timeout=60).stdout
    assert "| expert_set2 | 3 / 1003 (1.0 h left) |" in out  # 1,000 iterations at 3.6 s each
    (expert / "bundle.json").write_text(json.dumps({"provenance": {"command": "motok control distill"},
                                                    "config": {"iterations": 3}}))
    out = subprocess.run([sys.executable, str(tables), "--runs", str(runs), "--status"], capture_output=True,
                         text=True, timeout=60).stdout
    assert "| expert_set2 | 3 / 3 (done) |" in out
    task = runs / "inbetween_hybrid"  # a task policy logs its evaluation under the task's own names
    task.mkdir()
    (task / "metrics.jsonl").write_text(json.dumps({"iteration": 100, "samples": 204_800, "wall_s": 90.0,
                                                    "eval_success_rate": 0.625, "eval_mpjpe_mm_mean": 76.04}))
    out = subprocess.run([sys.executable, str(tables), "--runs", str(runs), "--status"], capture_output=True,
                         text=True, timeout=60).stdout
    assert "| success_rate 0.625 (it 100), mpjpe_mm_mean 76 (it 100) |" in out, out


def test_stop_at_stops_the_queue_after_the_command_under_way(tmp_path):
    """STOP_AT: the queue sends itself kill -TERM's signal at that time; the command under way
    gets it (a training stops at its next checkpoint) and nothing after it starts."""
    record = tmp_path / "argv.jsonl"
    shim = tmp_path / "slow.py"
    shim.write_text(f"import json, sys, time\nopen({str(record)!r}, 'a').write(json.dumps(sys.argv[1:]) + '\\n')\n"
                    "time.sleep(8)\n")
    env = {**os.environ, "R": str(tmp_path / "runs"), "MOTOK": f"{sys.executable} {shim}", "STOP_AT": "+2 sec"}
    p = subprocess.run(["bash", str(SCRIPT), "data", "expert"], env=env, capture_output=True, text=True, timeout=60)
    assert p.returncode == 0, p.stdout + p.stderr
    assert "stopping itself at" in p.stdout and "stopped on request after preprocess" in p.stdout
    assert [json.loads(line)[0] for line in record.read_text().splitlines()] == ["preprocess"]


def test_stop_at_refuses_a_time_past_or_unreadable(tmp_path):
    for bad, said in (("-1 min", "is not in the future"), ("half past never", "not a time date -d reads")):
        env = {**os.environ, "R": str(tmp_path / "runs"), "MOTOK": "false", "STOP_AT": bad}
        p = subprocess.run(["bash", str(SCRIPT), "data"], env=env, capture_output=True, text=True, timeout=60)
        assert p.returncode == 2 and said in p.stderr and "stage data" not in p.stdout, (bad, p.stdout, p.stderr)


def test_stop_at_a_clock_time_already_past_means_tomorrow(tmp_path):
    # a session that crosses midnight: at 22:50, STOP_AT=01:25 is the next day's
    past = time.time() - 120
    env = {**os.environ, "R": str(tmp_path / "runs"), "MOTOK": "true",
           "STOP_AT": time.strftime("%H:%M", time.localtime(past))}
    p = subprocess.run(["bash", str(SCRIPT), "data"], env=env, capture_output=True, text=True, timeout=60)
    assert p.returncode == 0, p.stdout + p.stderr
    tomorrow = time.strftime("%Y-%m-%d", time.gmtime(int(past // 60 * 60) + 86400))
    assert f"stopping itself at {tomorrow} " in p.stdout, p.stdout


def test_a_queue_that_ends_before_stop_at_takes_its_timer_along(tmp_path):
    # the timer and its sleep share the queue's output: one left behind would hold it open for the
    # hour, and queue() would time out instead of returning
    cmds = queue(tmp_path, "data", env={"STOP_AT": "+1 hour"})
    assert [a[0] for a in cmds] == ["preprocess"]


def test_a_failing_command_under_stop_at_keeps_its_status(tmp_path):
    shim = tmp_path / "fail.py"
    shim.write_text("import sys\nsys.exit(3)\n")
    env = {**os.environ, "R": str(tmp_path / "runs"), "MOTOK": f"{sys.executable} {shim}", "STOP_AT": "+1 hour"}
    p = subprocess.run(["bash", str(SCRIPT), "expert"], env=env, capture_output=True, text=True, timeout=60)
    assert p.returncode == 3 and "expert_set2 failed (exit 3)" in p.stdout
