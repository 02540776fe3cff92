"""One writer per run folder and per output file: an OS lock beside the target.

Two trainings into one folder would both run to the end and interleave ``metrics.jsonl`` and
checkpoints; two commands writing one file would race for the last rename. The first writer
takes an exclusive ``fcntl.flock`` on ``PARENT/.NAME.lock`` and writes who it is into it (pid,
command, start time, host); a second writer of the same target is refused at once, with those
details, instead of waiting.

The lock sits beside the target, not inside it, because a new run folder only appears at its
first checkpoint (:mod:`motok.runfolder`) and an output file is renamed into place at its end:
the lock has to exist before either. The kernel releases a flock when its process ends, however
it ends (exit, crash, ``kill -9``), so a lock is never left held by a dead writer; only the small
file may stay behind, and the next writer simply takes it.
"""

from __future__ import annotations

import datetime as _dt
import fcntl
import json
import os
import socket
import sys
from pathlib import Path

from motok.errors import UserError


class LockedError(UserError):
    """The run folder or output file is being written by another process."""


def lock_path(target: str | os.PathLike) -> Path:
    target = Path(os.path.abspath(target))
    return target.with_name(f".{target.name}.lock")


def holder_record() -> dict:
    return {"pid": os.getpid(), "host": socket.gethostname(),
            "started": _dt.datetime.now().astimezone().isoformat(timespec="seconds"),
            "command": " ".join([program()] + sys.argv[1:])}


def program() -> str:
    name = Path(sys.argv[0]).name
    return "motok" if name in ("main.py", "__main__.py") else name  # python -m motok.cli.main is motok


def describe_holder(text: str) -> str:
    try:
        h = json.loads(text)
        return f"pid {h['pid']} on {h['host']}, started {h['started']}: {h['command']}"
    except (ValueError, KeyError, TypeError):
        # The holder took the lock a moment ago and has not written its record yet.
        return "another process (it has not said which yet)"


class OutputLock:
    """An exclusive lock on ``target`` held until :meth:`release` (or the process ends)."""

    def __init__(self, target: str | os.PathLike, what: str = "output"):
        self.target, self.what = Path(target), what
        self.path = lock_path(target)
        self.fd: int | None = None

    def acquire(self) -> "OutputLock":
        self.path.parent.mkdir(parents=True, exist_ok=True)
        while True:
            fd = os.open(self.path, os.O_RDWR | os.O_CREAT, 0o644)
            try:
                fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
            except BlockingIOError:
                holder = describe_holder(os.pread(fd, 4096, 0).decode("utf-8", "replace"))
                os.close(fd)
                raise LockedError(f"{self.what} {self.target} is being written by {holder}; wait for it to "
                                  f"finish or stop it (one writer per run folder and per output file)") from None
            except OSError:
                os.close(fd)
                raise
            # A releasing writer unlinks the file after we opened it: then we hold a lock on a
            # name nobody else will find. Start over on the file that is there now.
            try:
                same = os.path.samestat(os.fstat(fd), os.stat(self.path))
            except FileNotFoundError:
                same = False
            if same:
                break
            os.close(fd)
        os.ftruncate(fd, 0)
        os.pwrite(fd, json.dumps(holder_record()).encode(), 0)
        self.fd = fd
        return self

    def release(self) -> None:
        if self.fd is None:
            return
        # Unlink while still holding the lock, so a writer waiting on this file starts over
        # on a fresh one instead of locking a file that no longer has a name.
        try:
            self.path.unlink(missing_ok=True)
        except OSError:
            pass
        os.close(self.fd)
        self.fd = None

    def __enter__(self) -> "OutputLock":
        return self.acquire()

    def __exit__(self, *exc) -> None:
        self.release()
