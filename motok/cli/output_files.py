"""Output files of any command: an existing HDF5 file that is not a motok artifact is never
replaced, and one writer at a time holds a file (the lock of :mod:`motok.runlock`, beside it).
Also the one line for a full disk met while writing one. :mod:`motok.cli.common` calls these
from its output options and from :func:`motok.cli.common.run`; nothing here imports the command
line, and importing it stays cheap.
"""

from __future__ import annotations

from pathlib import Path

from motok.errors import UserError

H5_SUFFIXES = (".h5", ".hdf5")


def foreign_file(path: Path) -> str | None:
    """Why the existing file ``path`` must not be replaced, or None: an HDF5 output must be a
    motok artifact (its root ``kind``). Other outputs (videos, images, BVH, JSON reports) carry
    no mark of who wrote them and are replaced, atomically, as before."""
    if not path.is_file() or path.suffix.lower() not in H5_SUFFIXES:
        return None
    from motok.artifacts import KINDS
    try:
        import h5py
        with h5py.File(path, "r") as f:
            kind = f.attrs.get("kind")
    except OSError:
        kind = None
    kind = kind.decode() if isinstance(kind, bytes) else kind
    if kind in KINDS:
        return None
    return (f"{path} exists and is not a motok artifact; motok never replaces a file it did not write "
            f"(not even with --force): move it or choose another output")


def claim_output_file(ctx, path, label: str) -> None:
    """Refuse a foreign file at ``path`` and hold the writer's lock beside it until the command
    (the click context ``ctx``) ends; a refusal is a :class:`motok.errors.UserError`."""
    from motok.runlock import OutputLock
    path = Path(path)
    why = foreign_file(path)
    if why:
        raise UserError(f"{label} {why}")
    try:
        lock = OutputLock(path, f"{label} output").acquire()  # LockedError names the holder
    except OSError:
        return  # no lock where the folder cannot hold one (the writer's own check reports why)
    _claimed.append(path)

    def release():
        lock.release()
        if path in _claimed:
            _claimed.remove(path)
        if release in _releases:
            _releases.remove(release)
    _releases.append(release)
    ctx.call_on_close(release)


_claimed: list[Path] = []  # the output files of the running command, to name in a fault
_releases: list = []  # their locks' releases, also for a refusal while the options are still parsed


def release_claims() -> None:
    """Release the locks this command took on its outputs. Click runs a context's close callbacks
    only once the command line is parsed, so a later option refused while parsing would otherwise
    leave ``.NAME.lock`` files beside outputs that were never written."""
    for release in list(_releases):
        release()


def disk_full_message(e: BaseException) -> str | None:
    """One line for a full disk met while writing an output file (which atomic writing removed),
    or None when ``e`` is something else."""
    from motok.runfolder import disk_full, disk_full_path
    if not disk_full(e):
        return None
    named = ", ".join(map(str, _claimed)) or "the output"
    path = disk_full_path(e, named)
    if Path(path).name.startswith("."):  # a temporary name: say which output it was to become
        path = named
    return f"no space left on device writing {path}; nothing was written: free some space and run it again"
