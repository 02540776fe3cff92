"""Run folders that are never replaced by accident, have one writer, and appear whole.

A command that trains into ``-o RUN`` claims it first (:class:`RunClaim`), before any work:

- ``RUN`` holds a motok run (``bundle.json`` or ``metrics.jsonl``): refused unless ``--resume``
  (continue it) or ``--force`` (replace it). A folder that holds anything else is refused even
  with ``--force``: motok replaces only what it made.
- ``--force`` moves the old run aside to ``RUN.replaced-TIMESTAMP`` rather than deleting it: a run
  can hold days of training, and a ``--force`` recalled from the shell history must not be able
  to destroy it. The move is one rename (no copy), done only when the new run saves its first
  checkpoint, so a forced run that fails early leaves the old one where it was. Delete the
  moved folder when sure.
- the claim holds the lock of :mod:`motok.runlock` for the whole command.
- a new run is written into a hidden temporary sibling (:func:`motok.atomic.temp_name`) and
  renamed to ``RUN`` when its first checkpoint is complete (:func:`publish_staged`, called by
  ``save_bundle``); the trainer keeps writing through a symbolic link left at the temporary
  name, removed at the end. Before that checkpoint a failure, Ctrl-C or full disk removes the
  temporary folder, so ``RUN`` appears whole (with a loadable checkpoint) or not at all; a
  writer killed outright leaves only a hidden folder that the next writer of ``RUN`` removes.
"""

from __future__ import annotations

import datetime as _dt
import errno
import json
import os
import shlex
import shutil
import sys
from pathlib import Path

from motok.atomic import stale_temp_files, temp_name
from motok.errors import UserError
from motok.progress import info as _info
from motok.runlock import OutputLock

RUN_FILES = ("bundle.json", "metrics.jsonl")  # what makes a folder a motok run
_STAGED: dict[str, "RunClaim"] = {}  # absolute temporary path -> its claim


class RunFolderError(UserError):
    pass


def resume_command() -> str:
    """The command line of this process with ``--resume`` instead of ``--force``."""
    args = [a for a in sys.argv[1:] if a != "--force"]
    if "--resume" not in args:
        args.append("--resume")
    return shlex.join(["motok", *args])


def info(msg: str) -> None:
    from rich.markup import escape
    _info(escape(msg))  # paths may hold brackets, which rich would read as markup


def is_motok_run(path: Path) -> bool:
    return any((path / f).is_file() for f in RUN_FILES)


def check_run_target(out: str | os.PathLike, *, resume: bool, force: bool) -> str:
    """``"new"``, ``"resume"`` or ``"replace"``: what writing a run into ``out`` will do; refuses
    what must not happen (a run replaced without ``--force``, a foreign folder at all)."""
    out = Path(out)
    if resume and force:
        raise RunFolderError("--resume continues the run in -o and --force replaces it: give one of them")
    if resume:
        if not out.is_dir():
            raise RunFolderError(f"--resume: there is no run at {out} (no such folder, so no checkpoint bundle "
                                 f"to continue); leave out --resume to start one there")
        return "resume"  # the trainer loads the bundle and says what else is missing
    if out.exists() and not out.is_dir():
        raise RunFolderError(f"-o {out} is a file, not a run folder; motok never replaces a file it did not write")
    if not out.exists() or not any(out.iterdir()):
        return "new"
    if not is_motok_run(out):
        raise RunFolderError(f"-o {out} is a folder that does not hold a motok run; motok never replaces it "
                             f"(even with --force): give a new folder")
    if not force:
        raise RunFolderError(f"-o {out} already holds a run; --resume to continue it, --force to replace it "
                             f"(the old run is moved aside, not deleted)")
    return "replace"


def aside_name(out: Path) -> Path:
    stamp = _dt.datetime.now().strftime("%Y%m%d-%H%M%S")
    aside, n = out.with_name(f"{out.name}.replaced-{stamp}"), 1
    while aside.exists():
        n += 1
        aside = out.with_name(f"{out.name}.replaced-{stamp}-{n}")
    return aside


class RunClaim:
    """``with RunClaim(out, resume=..., force=...) as where:`` train into ``where`` (``out`` on
    resume, else a temporary sibling that becomes ``out`` at the first checkpoint)."""

    def __init__(self, out: str | os.PathLike, *, resume: bool = False, force: bool = False):
        if resume and force:
            raise RunFolderError("--resume continues the run in -o and --force replaces it: give one of them")
        self.out, self.resume, self.force = Path(out), resume, force
        self.mode = ""
        self.lock = OutputLock(self.out, "run folder")
        self.tmp: Path | None = None
        self.published = False
        self.aside: Path | None = None

    def __enter__(self) -> Path:
        if self.resume:  # before the lock, which would create the folders above a mistyped path
            check_run_target(self.out, resume=True, force=False)
        # The lock first: a run being written is better told by who writes it than by what is there.
        self.lock.acquire()
        try:
            self.mode = check_run_target(self.out, resume=self.resume, force=self.force)
            self._remove_stale()
            if self.mode == "resume":
                return self.out
            self.out.parent.mkdir(parents=True, exist_ok=True)
            self.tmp = self.out.with_name(temp_name(self.out))
            self.tmp.mkdir()
            _STAGED[os.path.abspath(self.tmp)] = self
            if self.mode == "replace":
                info(f"--force: {self.out} is moved aside when the new run saves its first checkpoint")
            return self.tmp
        except BaseException:  # Ctrl-C included: __exit__ will not run, so undo here
            if self.tmp is not None:
                _STAGED.pop(os.path.abspath(self.tmp), None)
                shutil.rmtree(self.tmp, ignore_errors=True)
            self.lock.release()
            raise

    def _remove_stale(self) -> None:
        """Temporary folders (or the links left after publishing) of writers of ``out`` that died."""
        for stale in stale_temp_files(self.out):
            if stale.is_symlink() or not stale.is_dir():
                stale.unlink(missing_ok=True)
            else:
                shutil.rmtree(stale, ignore_errors=True)

    def publish(self) -> None:
        """Rename the temporary folder to ``out`` (moving an old run aside first under --force)."""
        if self.published or self.tmp is None:
            return
        if self.mode == "replace" and self.out.exists():
            self.aside = aside_name(self.out)
            os.replace(self.out, self.aside)
            info(f"--force: moved the old run {self.out} to {self.aside}")
        elif self.out.is_dir():
            self.out.rmdir()  # empty (checked): a folder cannot be renamed over a folder
        os.replace(self.tmp, self.out)
        self.published = True
        # The trainer still holds the temporary path: let it keep writing through it.
        os.symlink(self.out.name, self.tmp)

    def __exit__(self, exc_type, exc, tb) -> None:
        try:
            if self.tmp is not None:
                _STAGED.pop(os.path.abspath(self.tmp), None)
                if self.published:
                    self.tmp.unlink(missing_ok=True)
                elif exc_type is None and is_motok_run(self.tmp):
                    self.publish()
                    self.tmp.unlink(missing_ok=True)
                else:
                    shutil.rmtree(self.tmp, ignore_errors=True)
        finally:
            self.lock.release()

    def written(self) -> bool:
        """Whether ``out`` now holds what this command wrote (a resumed run, or a published one)."""
        return self.mode == "resume" or self.published


def publish_staged(run: str | os.PathLike) -> None:
    """Called after every checkpoint: the first one of a staged run makes it visible as ``out``."""
    claim = _STAGED.get(os.path.abspath(run))
    if claim is not None:
        claim.publish()


def final_path(path: str | os.PathLike) -> str:
    """``path`` with a staged temporary folder replaced by the run folder it becomes, spelled as
    ``-o`` was (the staged folders are keyed by absolute path; ``-o`` is usually relative)."""
    s = str(path)
    a = os.path.abspath(s)
    for tmp, claim in _STAGED.items():
        if a == tmp or a.startswith(tmp + os.sep):
            return str(claim.out) + a[len(tmp):]
    return s


# --------------------------------------------------------------------------- faults

def disk_full(e: BaseException) -> bool:
    """Whether ``e`` (or what caused it) is a full disk or quota: torch, safetensors and h5py
    wrap the OSError in their own exception types."""
    seen = set()
    while e is not None and id(e) not in seen:
        seen.add(id(e))
        if isinstance(e, OSError) and e.errno in (errno.ENOSPC, errno.EDQUOT):
            return True
        if "No space left on device" in str(e) or "Disk quota exceeded" in str(e):
            return True
        e = e.__cause__ or e.__context__
    return False


def disk_full_path(e: BaseException, default) -> str:
    seen = set()
    while e is not None and id(e) not in seen:
        seen.add(id(e))
        if isinstance(e, OSError) and e.filename:
            return final_path(e.filename)
        e = e.__cause__ or e.__context__
    return str(default)


def checkpoint_iteration(run: Path) -> int | None:
    try:
        return int(json.loads((run / "bundle.json").read_text())["extra"]["iteration"])
    except (OSError, ValueError, KeyError, TypeError):
        return None


def last_logged_iteration(run: Path) -> int | None:
    try:
        lines = (run / "metrics.jsonl").read_text().splitlines()
    except OSError:
        return None
    for line in reversed(lines):
        try:
            return int(json.loads(line)["iteration"])
        except (ValueError, KeyError, TypeError):
            continue  # a line cut short by the interruption
    return None
