"""Files that appear whole or not at all.

Every writer in motok (HDF5 artifacts, checkpoint bundles, videos, plots, BVH, caches) goes
through :func:`atomic_path`: it writes a temporary sibling and renames it over the target only
when the block succeeds, so a reader never sees a half-written file and a crash or Ctrl-C
leaves none behind (``os.replace`` is atomic within one directory). Files that belong together
(a checkpoint) go through :func:`atomic_paths`, which renames them only when all are written.
Results in JSON go through :func:`write_json` (strict JSON: ``null`` for a missing number).

A writer killed outright (``kill -9``, the OOM killer, a power cut) cannot remove its temporary
file. The name says whose it was, ``.STEM.HOST.PID.RANDOM.partSUFFIX``, so the next writer of
the same target removes the ones whose process is gone from this machine; files of writers on
other machines sharing the folder are left to those machines.
"""

from __future__ import annotations

import contextlib
import glob
import json
import math
import numbers
import os
import re
import shutil
import socket
import tempfile
import uuid
from pathlib import Path
from typing import Iterator

from motok.errors import UserError

_UMASK = os.umask(0o022)  # read it the only way there is: set and restore
os.umask(_UMASK)
# Dots separate the fields of a temporary name, so the host part may not contain any.
_HOST = re.sub(r"[^A-Za-z0-9-]", "-", socket.gethostname())[:32] or "host"


class OutputError(UserError, OSError):
    """An output path that cannot be written: a folder where a file goes, no permission, ..."""


def temp_name(path: Path) -> str:
    return f".{path.stem}.{_HOST}.{os.getpid()}.{uuid.uuid4().hex[:8]}.part{path.suffix}"


def _alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:  # someone else's process: alive
        return True
    return True


def stale_temp_files(path: str | os.PathLike) -> list[Path]:
    """Temporary files of writers of ``path`` on this machine whose process no longer exists."""
    path = Path(path)
    if not path.parent.is_dir():
        return []
    # The host field is absent in names written before it was added (same machine assumed).
    name = re.compile(rf"^\.{re.escape(path.stem)}\.(?:(?P<host>[A-Za-z0-9-]+)\.)?(?P<pid>\d+)\.[0-9a-f]{{8}}"
                      rf"\.part{re.escape(path.suffix)}$")
    out = []
    for p in path.parent.glob(f".{glob.escape(path.stem)}.*.part{glob.escape(path.suffix)}"):
        m = name.match(p.name)
        if m and m["host"] in (None, _HOST) and int(m["pid"]) != os.getpid() and not _alive(int(m["pid"])):
            out.append(p)
    return out


def remove_stale_temp_files(path: str | os.PathLike) -> list[Path]:
    removed = []
    for p in stale_temp_files(path):
        with contextlib.suppress(OSError):  # another writer may be cleaning up the same file
            p.unlink()
            removed.append(p)
    return removed


@contextlib.contextmanager
def atomic_path(path: str | os.PathLike) -> Iterator[Path]:
    """Yield a temporary path beside ``path`` and rename it to ``path`` if the block succeeds.

    The temporary name keeps the suffix, because imageio, Pillow and matplotlib choose the
    format from it, and is hidden (leading dot) and unique per process and call. The file gets
    the ordinary mode (0666 less the umask) before the rename: some writers (safetensors,
    ``mkstemp``) create files readable by their owner only, which would make a shared
    checkpoint unreadable to its recipients.
    """
    with atomic_paths(path) as (tmp,):
        yield tmp


@contextlib.contextmanager
def atomic_paths(*paths: str | os.PathLike) -> Iterator[list[Path]]:
    """:func:`atomic_path` for files that belong together (a checkpoint's weights, training state
    and the metadata that vouches for both): yield a temporary sibling for each, and only when the
    block has written them all rename them into place, one right after the other in the order
    given. A crash or kill while writing (seconds, for a large training state) leaves the old set
    whole; only one between two renames (microseconds) could mix old and new, so the file that
    readers check the others against goes last. Names and modes as :func:`atomic_path`'s."""
    paths = [Path(p) for p in paths]
    tmps = []
    try:
        for path in paths:
            path.parent.mkdir(parents=True, exist_ok=True)
            remove_stale_temp_files(path)
            tmps.append(path.with_name(temp_name(path)))
        yield tmps
        for tmp in tmps:
            os.chmod(tmp, 0o666 & ~_UMASK)
        for tmp, path in zip(tmps, paths):
            os.replace(tmp, path)
    finally:
        for tmp in tmps:
            tmp.unlink(missing_ok=True)


@contextlib.contextmanager
def atomic_folder(path: str | os.PathLike) -> Iterator[Path]:
    """:func:`atomic_path` for a folder of many files (a data set in another tool's layout): yield
    a temporary sibling folder and rename it to ``path`` when the block succeeds. ``path`` must
    not exist or be an empty folder, so nothing of an older export mixes with the new one; a
    failure (or a folder left by a killed writer of the same target) is removed whole."""
    path = Path(path)
    if path.exists() and (not path.is_dir() or any(path.iterdir())):
        raise OutputError(f"output {path} exists and is not an empty folder; give a new folder")
    path.parent.mkdir(parents=True, exist_ok=True)
    for stale in stale_temp_files(path):
        shutil.rmtree(stale, ignore_errors=True)
    tmp = path.with_name(temp_name(path))
    tmp.mkdir(mode=0o777 & ~_UMASK)
    try:
        yield tmp
        if path.exists():
            path.rmdir()  # empty, checked above; a folder cannot be renamed over a folder
        os.replace(tmp, path)
    finally:
        shutil.rmtree(tmp, ignore_errors=True)


def finite_or_null(obj):
    """``obj`` with every NaN or infinity replaced by None, recursively through dicts, lists and
    tuples; numpy and torch scalars and arrays become Python numbers and lists; other values
    unchanged."""
    if type(obj).__module__ in ("numpy", "torch") and hasattr(obj, "tolist"):
        return finite_or_null(obj.tolist())
    if isinstance(obj, numbers.Real) and not isinstance(obj, numbers.Integral):
        x = float(obj)
        return x if math.isfinite(x) else None
    if isinstance(obj, dict):
        return {k: finite_or_null(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [finite_or_null(v) for v in obj]
    return obj


def strict_json(obj, *, default=str) -> str:
    """``obj`` as indented JSON that every parser reads.

    Python's ``json`` writes a missing number as a bare ``NaN``, which jq, JavaScript and most
    parsers reject; motok's results say ``null`` instead (a time to reach when no target was
    reached, a rate over nothing). ``default`` serialises what JSON lacks (paths, dtypes)."""
    return json.dumps(finite_or_null(obj), indent=2, default=default, allow_nan=False)


def write_json(path: str | os.PathLike, obj, *, default=str) -> Path:
    """Write :func:`strict_json` of ``obj`` to ``path`` atomically, with one final newline."""
    text = strict_json(obj, default=default) + "\n"
    with atomic_path(path) as tmp:
        tmp.write_text(text, encoding="utf-8")
    return Path(path)


def check_writable(path: str | os.PathLike, *, folder: bool = False, suffixes: tuple[str, ...] = (),
                   what: str = "output") -> Path:
    """Fail now, before any work, if ``path`` cannot be written: a file output that is a folder
    (or a run folder that is a file), a suffix the writer cannot produce, a parent that is a
    file or not writable. Creates nothing."""
    path = Path(path)
    if folder and path.exists() and not path.is_dir():
        raise OutputError(f"{what} {path} is a file; a run folder goes there")
    if not folder and path.is_dir():
        raise OutputError(f"{what} {path} is a folder; give a file name inside it")
    if suffixes and path.suffix.lower() not in suffixes:
        raise OutputError(f"{what} {path}: unknown suffix {path.suffix or '(none)'!r}; use one of "
                          f"{', '.join(suffixes)}")
    # The nearest existing ancestor must be a writable folder: the writer creates the rest.
    parent = path if folder else path.parent
    while not parent.exists() and parent != parent.parent:
        parent = parent.parent
    if not parent.is_dir():
        raise OutputError(f"{what} {path}: {parent} is a file, not a folder")
    # Try it: permission bits say nothing for root, read-only mounts or /proc.
    try:
        with tempfile.TemporaryFile(dir=parent):
            pass
    except OSError as e:
        raise OutputError(f"{what} {path}: cannot write in {parent} ({e.strerror or e})") from None
    return path
