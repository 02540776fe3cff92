"""The one module that owns artifact I/O.

Every motok HDF5 file carries, as root attributes, its ``kind`` (``motion-dataset``,
``motion``, ...), a ``schema_version`` and a JSON ``provenance`` record (motok version,
command line, resolved config, SHA-256 of every input, creation time, what was skipped, and the
machine: CPU, dispatched SIMD kernels, package versions).
Files are written under a temporary name in the target directory and renamed into place
only when the writer finished without error, so a crash never leaves a half file.
"""

from __future__ import annotations

import contextlib
import datetime as _dt
import hashlib
import json
import os
import sys
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Iterator

import h5py
import numpy as np

from motok import __version__
from motok.atomic import atomic_path
from motok.errors import MotokError
from motok.machine import machine_record

# kind -> schema versions this build reads. The first entry is what it writes.
KINDS: dict[str, tuple[int, ...]] = {
    "motion-dataset": (1,),
    "motion": (1,),
    "tokens": (1,),
    "text-embeddings": (1,),
}


class ArtifactError(MotokError, ValueError):
    pass


@dataclass
class Provenance:
    command: str
    config: dict[str, Any]
    inputs: dict[str, str] = field(default_factory=dict)  # path -> sha256
    skipped: list[dict[str, str]] = field(default_factory=list)
    motok_version: str = __version__
    created: str = field(default_factory=lambda: _dt.datetime.now(_dt.timezone.utc).isoformat(timespec="seconds"))
    machine: dict[str, Any] = field(default_factory=machine_record)  # CPU, kernels, versions (motok.machine)

    def to_json(self) -> str:
        return json.dumps(self.__dict__, sort_keys=True, default=_json_default)

    @classmethod
    def from_json(cls, text: str) -> "Provenance":
        d = json.loads(text)
        d.setdefault("machine", {})  # a record from before machines were recorded is not this machine's
        return cls(**d)


def _json_default(o):
    if isinstance(o, (np.integer,)):
        return int(o)
    if isinstance(o, (np.floating,)):
        return float(o)
    if isinstance(o, (Path,)):
        return str(o)
    if isinstance(o, np.ndarray):
        return o.tolist()
    raise TypeError(f"not JSON-serializable: {type(o).__name__}")


def command_line() -> str:
    return " ".join([Path(sys.argv[0]).name] + sys.argv[1:])


def sha256_file(path: str | os.PathLike, chunk: int = 1 << 20) -> str:
    h = hashlib.sha256()
    with open(path, "rb") as f:
        while block := f.read(chunk):
            h.update(block)
    return h.hexdigest()


def hash_inputs(paths) -> dict[str, str]:
    """SHA-256 of each input file; a directory is hashed over its sorted files' names and contents."""
    out = {}
    for p in map(Path, paths):
        if p.is_dir():
            h = hashlib.sha256()
            for f in sorted(q for q in p.rglob("*") if q.is_file()):
                h.update(str(f.relative_to(p)).encode())
                h.update(bytes.fromhex(sha256_file(f)))
            out[str(p)] = h.hexdigest()
        elif p.exists():
            out[str(p)] = sha256_file(p)
    return out


@contextlib.contextmanager
def write_artifact(path: str | os.PathLike, kind: str, provenance: Provenance) -> Iterator[h5py.File]:
    """Open ``path`` for writing an artifact of ``kind``; it appears only if the block succeeds."""
    if kind not in KINDS:
        raise ArtifactError(f"unknown artifact kind {kind!r}; known kinds: {sorted(KINDS)}")
    with atomic_path(path) as tmp, h5py.File(tmp, "w") as f:
        f.attrs["kind"] = kind
        f.attrs["schema_version"] = KINDS[kind][0]
        f.attrs["provenance"] = provenance.to_json()
        yield f


def open_artifact(path: str | os.PathLike, kind: str | tuple[str, ...] | None = None) -> h5py.File:
    """Open a motok artifact read-only, checking that it is one of ``kind`` at a known version."""
    path = Path(path)
    if not path.exists():
        raise ArtifactError(f"{path}: no such file")
    try:
        f = h5py.File(path, "r")
    except OSError as e:
        raise ArtifactError(f"{path}: not an HDF5 file ({e})") from None
    found = f.attrs.get("kind")
    version = f.attrs.get("schema_version")
    wanted = (kind,) if isinstance(kind, str) else kind
    try:
        if found is None or version is None:
            raise ArtifactError(f"{path}: not a motok artifact (no 'kind'/'schema_version' attributes)")
        found = str(found)
        if wanted is not None and found not in wanted:
            raise ArtifactError(f"{path}: expected a {' or '.join(wanted)} artifact, found kind {found!r}")
        if found not in KINDS:
            raise ArtifactError(f"{path}: unknown artifact kind {found!r} (motok {__version__} knows {sorted(KINDS)})")
        if int(version) not in KINDS[found]:
            raise ArtifactError(f"{path}: {found} schema version {int(version)} is not supported by motok "
                                f"{__version__} (supported: {list(KINDS[found])})")
    except ArtifactError:
        f.close()
        raise
    return f


def provenance_of(f: h5py.File) -> Provenance:
    """The provenance record of an open artifact; a clear error when it is missing or damaged
    (a file made by another tool that copied the ``kind`` attribute, or edited by hand)."""
    raw = f.attrs.get("provenance")
    if raw is None:
        raise ArtifactError(f"{f.filename}: a {f.attrs.get('kind')} artifact without a provenance attribute "
                            f"(not written by motok, or stripped)")
    try:
        return Provenance.from_json(raw.decode() if isinstance(raw, bytes) else str(raw))
    except (ValueError, TypeError) as e:
        raise ArtifactError(f"{f.filename}: the provenance attribute is not a motok provenance record ({e})") from None


def write_strings(group: h5py.Group, name: str, values) -> None:
    group.create_dataset(name, data=np.array([str(v) for v in values], dtype=object),
                         dtype=h5py.string_dtype("utf-8"))


def read_strings(ds: h5py.Dataset) -> list[str]:
    return [s.decode("utf-8") if isinstance(s, bytes) else str(s) for s in ds[()]]
