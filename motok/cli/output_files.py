"""Output files of any command: an existing file that motok did not write is never replaced
(how motok knows its own: :data:`OWN`), and one writer at a time holds a file (the lock of
:mod:`motok.runlock`, beside it).
Also the one line for a full disk met while writing one. :mod:`motok.cli.common` calls these
from its output options and from :func:`motok.cli.common.run`; nothing here imports the command
line, and importing it stays cheap.
"""

from __future__ import annotations

from pathlib import Path

from motok.errors import UserError
from motok.marks import MARK, MD_MARK

SCAN = 1 << 20  # a mark sits in the header (PNG, GIF) or the index at the end (MP4): read no more


def _marked(path: Path) -> bool:
    with open(path, "rb") as f:
        head = f.read(SCAN)
        size = f.seek(0, 2)
        f.seek(max(size - SCAN, 0))
        tail = f.read(SCAN)
    mark = MARK.encode()
    return mark in head or mark in tail


def _json_report(path: Path) -> bool:
    import json
    try:
        obj = json.loads(path.read_text(encoding="utf-8"))
    except (OSError, ValueError):
        return False
    return isinstance(obj, dict) and ("kind" in obj or "provenance" in obj)


def _h5_artifact(path: Path) -> bool:
    from motok.artifacts import KINDS
    try:
        import h5py
        with h5py.File(path, "r") as f:
            kind = f.attrs.get("kind")
    except OSError:
        return False
    return (kind.decode() if isinstance(kind, bytes) else kind) in KINDS


def _md_report(path: Path) -> bool:
    with open(path, "rb") as f:
        return f.readline().strip() == MD_MARK.encode()


def _mjcf(path: Path) -> bool:
    # motok's MJCF carries its build record in a <custom><text> element named motok_*
    with open(path, "rb") as f:
        return b'name="motok_' in f.read(SCAN * 4)


# How motok knows a file it wrote, by suffix. A suffix not here (BVH: Blender's importer reads
# nothing before HIERARCHY nor after the frames, so a BVH has no room for a writer's mark) cannot
# tell, and an existing file of it is never replaced: the user moves it.
OWN = {".h5": _h5_artifact, ".hdf5": _h5_artifact, ".json": _json_report, ".md": _md_report,
       ".png": _marked, ".gif": _marked, ".mp4": _marked, ".xml": _mjcf}
WHAT = {".h5": "a motok artifact", ".hdf5": "a motok artifact", ".json": "a motok report",
        ".md": "a motok report", ".xml": "a motok MJCF"}


# The files of a run folder that make the run: a report or an MJCF written over one of them (`eval
# t2m -o RUN/bundle.json`) would pass for motok's own file and leave a run that no longer loads.
RUN_OWN = ("bundle.json", "metrics.jsonl", "model.safetensors", "train_state.pt", "humanoid.xml")


def foreign_file(path: Path) -> str | None:
    """Why the existing file ``path`` must not be replaced, or None: motok replaces only a file
    it recognises as its own (:data:`OWN`) and never one of a run's own files (:data:`RUN_OWN`);
    an output of another suffix is replaced, atomically."""
    from motok.runfolder import is_motok_run

    path = Path(path)
    if path.name in RUN_OWN and is_motok_run(path.parent):
        return (f"{path} is a file of the run {path.parent}; an output never takes the place of a run's own "
                f"files (not even with --force): choose another output")
    suffix = path.suffix.lower()
    if not path.is_file() or (suffix not in OWN and suffix != ".bvh"):
        return None
    if suffix == ".bvh":
        return (f"{path} exists and a BVH has no room for a mark of its writer, so motok cannot tell "
                f"whether it wrote it and never replaces one (not even with --force): delete it or choose "
                f"another output")
    try:
        if OWN[suffix](path):
            return None
    except OSError:
        pass
    what = WHAT.get(suffix, f"a {suffix[1:].upper()} that motok wrote")
    return (f"{path} exists and is not {what}; motok never replaces a file it did not write "
            f"(not even with --force): move it or choose another output")


def refuse_foreign(path, label: str) -> None:
    """Refuse a foreign file where a command writes a file named after its output (``-o
    walk.h5`` also writes ``walk.track.json``), before any work."""
    why = foreign_file(Path(path))
    if why:
        raise UserError(f"{label} {why}")


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
