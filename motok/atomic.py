"""Files that appear whole or not at all.

Every writer in motok (HDF5 artifacts, checkpoint bundles, videos, plots, BVH, caches) goes
through :func:`atomic_path`: it writes a temporary sibling and renames it over the target only
when the block succeeds, so a reader never sees a half-written file and a crash or Ctrl-C
leaves none behind (``os.replace`` is atomic within one directory).
"""

from __future__ import annotations

import contextlib
import os
import uuid
from pathlib import Path
from typing import Iterator

_UMASK = os.umask(0o022)  # read it the only way there is: set and restore
os.umask(_UMASK)


@contextlib.contextmanager
def atomic_path(path: str | os.PathLike) -> Iterator[Path]:
    """Yield a temporary path beside ``path`` and rename it to ``path`` if the block succeeds.

    The temporary name keeps the suffix, because imageio, Pillow and matplotlib choose the
    format from it, and is hidden (leading dot) and unique per process and call. The file gets
    the ordinary mode (0666 less the umask) before the rename: some writers (safetensors,
    ``mkstemp``) create files readable by their owner only, which would make a shared
    checkpoint unreadable to its recipients.
    """
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(f".{path.stem}.{os.getpid()}.{uuid.uuid4().hex[:8]}.part{path.suffix}")
    try:
        yield tmp
        os.chmod(tmp, 0o666 & ~_UMASK)
        os.replace(tmp, path)
    finally:
        tmp.unlink(missing_ok=True)
