"""Runs you can trust, the run folders' half: a finished run is never replaced without --force and
a foreign folder or file never; one writer per run folder and per output file; Ctrl-C says where
it stopped and how to resume, and the resumed run ends where an uninterrupted one does; a full
disk is one line and leaves no half-written folder. docs/guarantees.md names these tests."""

from __future__ import annotations

import json
import os
import re
import shlex
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest
from conftest import unavailable
from typer.testing import CliRunner

from motok.cli.main import app
from motok.runlock import OutputLock, lock_path

REPO = Path(__file__).resolve().parents[1]
runner = CliRunner()
TINY = ["model.width=32", "model.depth=1", "quantizer.dim=16", "quantizer.codebook_size=32", "batch_size=8",
        "window=32", "log_every=2", "threads=1"]



def _default_sigint() -> None:
    """In the child, before it runs: Ctrl-C at its default, as a terminal's command has it. A
    process started with SIGINT ignored keeps it ignored (Python installs KeyboardInterrupt only
    when it is not), and a test runner may hand that on."""
    signal.signal(signal.SIGINT, signal.SIG_DFL)

def by_ctrl_c(returncode: int) -> bool:
    """Exit status 130, or killed by SIGINT itself: the same to a shell (``$?`` is 130 both ways).
    CPython ends a process with SIGINT when a KeyboardInterrupt ever escaped code it ran through
    ``PyRun_*`` (some extension imports do), even one the program caught and handled after."""
    return returncode in (130, -signal.SIGINT)


def sets(*extra: str) -> list[str]:
    return [a for s in TINY + list(extra) for a in ("--set", s)]


def train_args(data, out, *extra: str) -> list[str]:
    return ["-q", "tokenize", "train", "-d", str(data), "-o", str(out), *sets("iterations=4", "save_every=2"), *extra]


def motok(*args: str, **kw) -> subprocess.CompletedProcess:
    env = {**os.environ, "MOTOK_NO_PROGRESS": "1"}
    return subprocess.run([sys.executable, "-m", "motok.cli.main", *args], cwd=REPO, env=env, text=True,
                          capture_output=True, **kw)


def model_sha(run: Path) -> str:
    return json.loads((run / "bundle.json").read_text())["model_sha256"]


def hidden_leftovers(folder: Path) -> list[str]:
    return sorted(p.name for p in folder.iterdir() if p.name.startswith("."))


# --------------------------------------------------------------------------- rule 1: no silent overwrite

def test_a_run_is_replaced_only_with_force_and_moved_aside(small_dataset, tmp_path):
    run = tmp_path / "tok"
    r = runner.invoke(app, train_args(small_dataset, run))
    assert r.exit_code == 0, r.output
    first = model_sha(run)
    r = runner.invoke(app, train_args(small_dataset, run, "--set", "seed=1"))
    assert r.exit_code == 2 and len(r.output.strip().splitlines()) == 1, r.output
    assert str(run) in r.output and "--resume" in r.output and "--force" in r.output
    assert model_sha(run) == first  # untouched
    r = runner.invoke(app, train_args(small_dataset, run, "--resume", "--force"))
    assert r.exit_code == 2 and "give one of them" in r.output
    r = runner.invoke(app, train_args(small_dataset, run, "--set", "seed=1", "--force"))
    assert r.exit_code == 0, r.output
    aside = [p for p in tmp_path.iterdir() if p.name.startswith("tok.replaced-")]
    assert len(aside) == 1 and model_sha(aside[0]) == first  # moved, not deleted
    assert model_sha(run) != first
    assert hidden_leftovers(tmp_path) == []  # no temporary folder, link or lock left behind


def test_a_foreign_folder_or_file_is_never_replaced_even_with_force(small_dataset, tmp_path):
    folder = tmp_path / "notes"
    folder.mkdir()
    (folder / "thesis.tex").write_text("years of work")
    r = runner.invoke(app, train_args(small_dataset, folder, "--force"))
    assert r.exit_code == 2 and "not hold a motok run" in r.output and "even with --force" in r.output, r.output
    assert sorted(p.name for p in folder.iterdir()) == ["thesis.tex"]
    afile = tmp_path / "thesis.tex"
    afile.write_text("years of work")
    r = runner.invoke(app, train_args(small_dataset, afile, "--force"))
    assert r.exit_code == 2 and afile.read_text() == "years of work", r.output
    # An output file that is not a motok artifact: refused before any work, whatever the command.
    h5 = tmp_path / "mine.h5"
    h5.write_bytes(b"not HDF5 at all")
    run = tmp_path / "tok"
    assert runner.invoke(app, train_args(small_dataset, run)).exit_code == 0
    r = runner.invoke(app, ["-q", "tokenize", "encode", "-t", str(run), "-d", str(small_dataset), "-o", str(h5)])
    assert r.exit_code == 2 and "not a motok artifact" in r.output and h5.read_bytes() == b"not HDF5 at all", r.output
    ours = tmp_path / "tokens.h5"  # a motok artifact is replaced, as before (atomically)
    for _ in range(2):
        r = runner.invoke(app, ["-q", "tokenize", "encode", "-t", str(run), "-d", str(small_dataset), "-o", str(ours)])
        assert r.exit_code == 0, r.output


# --------------------------------------------------------------------------- rule 2: one writer

HOLD = ("import sys, time; from motok.runlock import OutputLock; OutputLock(sys.argv[1]).acquire(); "
        "print('held', flush=True); time.sleep(120)")


def _holder(target: Path) -> subprocess.Popen:
    p = subprocess.Popen([sys.executable, "-c", HOLD, str(target)], cwd=REPO, stdout=subprocess.PIPE, text=True)
    assert p.stdout.readline().strip() == "held"
    return p


def test_a_second_writer_is_refused_and_told_who_holds_the_run(small_dataset, tmp_path):
    run, out = tmp_path / "tok", tmp_path / "tokens.h5"
    holder = _holder(run)
    try:
        r = runner.invoke(app, train_args(small_dataset, run))
        assert r.exit_code == 2 and len(r.output.strip().splitlines()) == 1, r.output
        assert f"pid {holder.pid}" in r.output and "started" in r.output and "being written" in r.output
        assert not run.exists()
    finally:
        holder.kill()  # kill -9: the kernel releases the lock with the process
        holder.wait()
    r = runner.invoke(app, train_args(small_dataset, run))
    assert r.exit_code == 0, r.output
    assert not lock_path(run).exists()  # released and removed at the end
    holder = _holder(out)  # one writer per output file too
    try:
        r = runner.invoke(app, ["-q", "tokenize", "encode", "-t", str(run), "-d", str(small_dataset), "-o", str(out)])
        assert r.exit_code == 2 and f"pid {holder.pid}" in r.output and not out.exists(), r.output
    finally:
        holder.kill()
        holder.wait()


def test_a_lock_is_exclusive_within_and_across_processes(tmp_path):
    a = OutputLock(tmp_path / "x.h5").acquire()
    with pytest.raises(Exception, match=f"pid {os.getpid()}"):
        OutputLock(tmp_path / "x.h5").acquire()
    a.release()
    OutputLock(tmp_path / "x.h5").acquire().release()
    assert list(tmp_path.iterdir()) == []


# --------------------------------------------------------------------------- rule 7: interruptions, disk full

def test_ctrl_c_says_where_it_stopped_and_resume_ends_where_an_uninterrupted_run_does(small_dataset, tmp_path):
    args = ["-q", "tokenize", "train", "-d", str(small_dataset), *sets("iterations=300", "save_every=50")]
    straight = motok(*args, "-o", str(tmp_path / "straight"))
    assert straight.returncode == 0, straight.stderr
    run = tmp_path / "run"
    env = {**os.environ, "MOTOK_NO_PROGRESS": "1"}
    for _ in range(3):  # a very fast machine can finish the run before the interrupt arrives: start again
        shutil.rmtree(run, ignore_errors=True)
        p = subprocess.Popen(preexec_fn=_default_sigint, args=[sys.executable, "-m", "motok.cli.main", *args, "-o",
                             str(run)], cwd=REPO, env=env, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
        deadline = time.time() + 120
        while not (run / "bundle.json").exists() and p.poll() is None and time.time() < deadline:
            time.sleep(0.02)
        p.send_signal(signal.SIGINT)
        _, err = p.communicate(timeout=60)
        if p.returncode != 0:
            break
    assert by_ctrl_c(p.returncode), err
    line = err.strip().splitlines()[-1]
    m = re.search(r"last checkpoint: iteration (\d+) in (\S+)\); continue exactly from there with: (motok .*)$", line)
    assert m and line.startswith("interrupted"), err
    assert int(m[1]) == json.loads((run / "bundle.json").read_text())["extra"]["iteration"] and m[2] == str(run)
    command = shlex.split(m[3])
    assert command[-1] == "--resume" and command[1:-1] == [*args, "-o", str(run)]
    resumed = motok(*command[1:])
    assert resumed.returncode == 0, resumed.stderr
    assert model_sha(run) == model_sha(tmp_path / "straight")
    assert hidden_leftovers(tmp_path) == []


def test_ctrl_c_before_the_first_checkpoint_leaves_no_folder(small_dataset, tmp_path):
    run = tmp_path / "run"
    env = {**os.environ, "MOTOK_NO_PROGRESS": "1"}
    args = ["-q", "tokenize", "train", "-d", str(small_dataset), "-o", str(run),
            *sets("iterations=100000", "save_every=100000", "log_every=1")]
    p = subprocess.Popen(preexec_fn=_default_sigint, args=[sys.executable, "-m", "motok.cli.main", *args], cwd=REPO, env=env,
                         stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    deadline = time.time() + 120
    # Interrupt the training loop itself (its first logged iterations in the claimed folder), not
    # whatever start-up phase a fixed delay after the claim happens to land in on a loaded machine.
    while (not any(tmp_path.glob(".run.*.part/metrics.jsonl")) and p.poll() is None
           and time.time() < deadline):
        time.sleep(0.02)
    p.send_signal(signal.SIGINT)
    _, err = p.communicate(timeout=60)
    assert by_ctrl_c(p.returncode) and "nothing was kept" in err, err
    assert list(tmp_path.iterdir()) == []


@pytest.fixture
def full_disk(tmp_path):
    """A 2 MB tmpfs with about 300 KB free: a tokenizer's first checkpoint does not fit."""
    mnt = tmp_path / "small"
    mnt.mkdir()
    if os.geteuid() != 0:
        unavailable("mounting a tmpfs to fill needs root")
    r = subprocess.run(["mount", "-t", "tmpfs", "-o", "size=2m", "tmpfs", str(mnt)], capture_output=True, text=True)
    if r.returncode != 0:
        unavailable(f"cannot mount a tmpfs here: {r.stderr.strip()}")
    try:
        (mnt / "filler").write_bytes(b"\0" * 1_700_000)
        yield mnt
    finally:
        subprocess.run(["umount", str(mnt)], check=False)


def test_a_full_disk_is_one_line_and_leaves_no_half_written_run(small_dataset, full_disk):
    run = full_disk / "tok"
    r = motok(*train_args(small_dataset, run))
    assert r.returncode == 2, r.stderr
    lines = r.stderr.strip().splitlines()
    assert len(lines) == 1 and "no space left on device" in lines[0] and str(run) in lines[0], r.stderr
    assert "Traceback" not in r.stderr and ".part" not in lines[0]
    assert sorted(p.name for p in full_disk.iterdir()) == ["filler"]  # no folder, no temporary, no lock


def test_a_full_disk_while_writing_a_file_is_one_line_and_leaves_no_partial_file(bandai_slice, full_disk):
    out = full_disk / "walks.h5"
    r = motok("-q", "preprocess", "-d", str(bandai_slice), "--clips", "dataset-2_walk_normal_00[1-4]", "-o", str(out))
    assert r.returncode == 2, r.stderr
    lines = r.stderr.strip().splitlines()
    assert len(lines) == 1 and "no space left on device" in lines[0] and str(out) in lines[0], r.stderr
    assert sorted(p.name for p in full_disk.iterdir()) == ["filler"]


def test_a_writer_killed_outright_leaves_only_what_the_next_writer_removes(tmp_path):
    from motok.atomic import _HOST
    from motok.runfolder import RunClaim, publish_staged

    run = tmp_path / "tok"
    dead = 2 ** 22 + 12345  # above the kernel's default pid_max: no such process
    (tmp_path / f".tok.{_HOST}.{dead}.0badc0de.part").mkdir()  # killed before its first checkpoint
    (tmp_path / f".tok.{_HOST}.{dead}.deadbeef.part").symlink_to("tok")  # killed after it
    with RunClaim(run) as where:
        assert where.parent == tmp_path and where.name.startswith(".tok.") and not run.exists()
        (where / "metrics.jsonl").write_text("")
        (where / "bundle.json").write_text("{}")
        publish_staged(where)  # what save_bundle does after each checkpoint
        assert run.is_dir() and (where / "metrics.jsonl").exists()  # still writable through the old name
    assert sorted(p.name for p in tmp_path.iterdir()) == ["tok"]
    with pytest.raises(Exception, match="there is no run at"):
        RunClaim(tmp_path / "missing" / "run", resume=True).__enter__()
    assert not (tmp_path / "missing").exists()


def test_the_summary_names_the_run_folder_not_its_temporary_name(tmp_path, monkeypatch):
    """A new run trains in a hidden sibling until its first checkpoint; what the command prints
    must be the -o it was given, relative as given (it was the hidden name with a relative -o)."""
    from motok.cli.outputs import train_into
    from motok.runfolder import publish_staged

    monkeypatch.chdir(tmp_path)

    def fn(where):
        (where / "bundle.json").write_text("{}")
        publish_staged(where)
        return {"run": str(where), "video": str(where / "curve.png"), "data": "walks.h5"}

    for out in (Path("runs") / "expert", tmp_path / "abs" / "expert"):
        summary = train_into(out, fn)
        assert summary == {"run": str(out), "video": str(out / "curve.png"), "data": "walks.h5"}, summary
