"""What the commands that train into a run folder do before, while and after they write: claim
the folder (refuse to replace a run without ``--force``, or a folder motok did not make; take the
writer's lock), and turn an interruption or a full disk into one line that says what was kept
and how to go on.

The rules live in :mod:`motok.runfolder` and :mod:`motok.runlock`; this module is their command
line for run folders, :mod:`motok.cli.output_files` for output files (which
:mod:`motok.cli.common` uses, so that one must not import this). Importing it stays cheap (no
torch): the checks run before any work.
"""

from __future__ import annotations

import os
from pathlib import Path
from typing import Callable

import typer

from motok import progress
from motok.errors import MotokError

Force = typer.Option(False, "--force", help="Replace the run in -o: the old run is moved aside to "
                     "-o.replaced-TIME (not deleted) when the new one saves its first checkpoint. A folder "
                     "that is not a motok run is never replaced.")

INTERRUPTED = 130  # the shell's code for a process ended by SIGINT


def _say(msg: str) -> None:
    from rich.markup import escape
    progress.console.print(escape(msg), highlight=False, soft_wrap=True)


def _fail(msg: str, code: int = 2):
    from motok.cli.common import fail
    fail(msg, code)


# --------------------------------------------------------------------------- run folders

from motok.runfolder import resume_command  # noqa: E402  (the trainers print it too, without the CLI)


def _where(out: Path) -> str:
    from motok.runfolder import checkpoint_iteration, last_logged_iteration
    ck = checkpoint_iteration(out)
    if ck is None:
        return ""
    it = last_logged_iteration(out)
    at = f"at iteration {it}, " if it is not None and it >= ck else ""
    return f"{at}last checkpoint: iteration {ck} in {out}"


def train_into(out: Path, fn: Callable[[Path], dict], *, resume: bool = False, force: bool = False,
               resumable: bool = True) -> dict:
    """``fn(where)`` trains into the run folder ``out`` (``where`` is where to write, see
    :class:`motok.runfolder.RunClaim`); returns its summary with ``where`` read as ``out``.
    Under ``torchrun`` only rank 0 claims: the others do not write."""
    from motok.runfolder import RunClaim, disk_full, disk_full_path, final_path

    out = Path(out)
    if int(os.environ.get("RANK", "0")) != 0:
        from motok.cli.common import run
        return run(fn, out)
    claim = None
    try:
        claim = RunClaim(out, resume=resume, force=force)
        with claim as where:
            summary = fn(where)
            return {k: final_path(v) if isinstance(v, (str, Path)) and str(v).startswith(str(where)) else v
                    for k, v in summary.items()}
    except MotokError as e:
        _fail(str(e))
    except KeyboardInterrupt:
        _interrupted(out, claim, resumable)
    except Exception as e:
        if not disk_full(e):
            raise
        path = disk_full_path(e, out)
        if claim is not None and claim.tmp is not None:  # name the run folder, not its temporary name
            path = path.replace(str(claim.tmp), str(out))
        kept = _where(out) if claim is not None and claim.written() else ""
        if kept and resumable:
            _fail(f"no space left on device writing {path}; {kept}: free some space and continue with "
                  f"{resume_command()}")
        _fail(f"no space left on device writing {path}; nothing was kept" +
              ("" if out.exists() else f" ({out} was not created)"))


def _interrupted(out: Path, claim, resumable: bool):
    where = _where(out) if claim is not None and claim.written() else ""
    if not where:
        _say(f"interrupted before the first checkpoint: nothing was kept ({out} was not created)"
             if not out.exists() else f"interrupted before the first checkpoint of this command; {out} is unchanged")
    elif resumable:
        _say(f"interrupted ({where}); continue exactly from there with: {resume_command()}")
    else:
        _say(f"interrupted ({where}); this command cannot resume: run it again with --force to start over")
    raise typer.Exit(INTERRUPTED)
