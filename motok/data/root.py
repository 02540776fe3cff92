"""Where the data lives: ``--data-root``, else ``$MOTOK_DATA``, else ``../shared/datasets``
beside the checkout, else a clear error saying where to get it."""

from __future__ import annotations

import os
from pathlib import Path

from motok.errors import MotokError

DOWNLOAD_HINT = (
    "Download the Bandai-Namco Research motion datasets from "
    "github.com/BandaiNamcoResearchInc/Bandai-Namco-Research-Motiondataset, lay them out as "
    "DATA/bandai-namco/bandai-namco-{1,2}.tar.xz plus DATA/bandai-namco/annotations/ "
    "(see docs/data.md), then pass --data-root DATA or set MOTOK_DATA=DATA."
)


class DataRootError(MotokError, FileNotFoundError):
    pass


def _checkout_default() -> Path:
    # motok/data/root.py -> checkout root is three levels up; shared/ sits beside the checkout.
    return Path(__file__).resolve().parents[3] / "shared" / "datasets"


def resolve_data_root(data_root: str | os.PathLike | None = None) -> Path:
    if data_root is not None:
        p = Path(data_root).expanduser()
        if not p.is_dir():
            raise DataRootError(f"--data-root {p} is not a directory. {DOWNLOAD_HINT}")
        return p
    env = os.environ.get("MOTOK_DATA")
    if env:
        p = Path(env).expanduser()
        if not p.is_dir():
            raise DataRootError(f"MOTOK_DATA={p} is not a directory. {DOWNLOAD_HINT}")
        return p
    p = _checkout_default()
    if p.is_dir():
        return p
    raise DataRootError(f"no data root: neither --data-root nor MOTOK_DATA is set and {p} does not exist. "
                        f"{DOWNLOAD_HINT}")
