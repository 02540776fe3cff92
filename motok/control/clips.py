"""Choosing clips of a motion dataset by name."""

from __future__ import annotations

import fnmatch

from motok.errors import UserError


def select_clips(data, pattern: str | None, split: str | None = None) -> list[str]:
    """Names of the clips of the motion artifact at ``data`` in ``split`` (train, val, test;
    all if None) matching the glob ``pattern`` (all if None)."""
    from motok.data.dataset import MotionFile
    with MotionFile(data) as mf:
        names = list(mf.names)
        if split is not None:
            if split not in mf.splits:
                raise UserError(f"{data} has no split {split!r} (it has {sorted(mf.splits)})")
            names = [names[i] for i in mf.split_indices(split)]
    if not pattern:
        return names
    chosen = [n for n in names if fnmatch.fnmatchcase(n, pattern)]
    if not chosen:
        where = f" in split {split!r}" if split else ""
        raise UserError(f"no clip of {data}{where} matches {pattern!r} (e.g. {names[:3]})")
    return chosen
