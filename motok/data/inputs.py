"""The inputs of ``motok preprocess``: where they are, which annotations go with them, and what
can be checked of them before any clip is parsed (a mistake found there costs seconds, not the
minutes of reading a whole archive); also how a bad input is reported.

``cfg`` below is a :class:`motok.data.preprocess.PreprocessConfig`.
"""

from __future__ import annotations

import os
import re
from fnmatch import fnmatchcase
from pathlib import Path

from motok.data.annotations import Annotations
from motok.data.bvh import MotionFormatError
from motok.data.root import DataRootError, resolve_data_root
from motok.data.sources import count_sources, list_sources
from motok.errors import MissingFileError, UnknownNameError

BANDAI_FOLDER = "bandai-namco"  # under the data root
BANDAI_ANNOTATIONS = "bandai-namco/annotations"


def check_inputs(cfg, inputs: list[Path], ann: Annotations | None, bad, broken: set[str] | None = None) -> tuple:
    """What the inputs hold, checked before any clip is parsed: names that occur twice, split
    entries that name no input (the ``pattern`` covers them, no ``limit``), caption files that
    are missing or malformed (``bad`` raises, or records them under ``skip_bad``), a
    ``reference_clip`` that is not selected. Returns the clip count for the progress bar (None:
    unknown), ``{clip: captions}`` and the names whose captions were bad (not to be parsed).

    Listing a compressed tar costs one decompression, so it is listed only when there is
    something to check against (annotations or a reference clip). An archive that breaks while
    being listed is ``bad``; skipped, its path is added to ``broken`` and its clips left out."""
    if ann is None and cfg.reference_clip is None:
        known = [count_sources(p, pattern=cfg.clips + ".*") for p in inputs]  # None: a compressed tar
        return (None if None in known else min(sum(known), cfg.limit or sum(known))), {}, set()
    listed = [(n, o) for p in inputs for n, o in _listing(p, bad, broken) if fnmatchcase(n, cfg.clips)][:cfg.limit]
    names = [n for n, _ in listed]
    dup = sorted({n for n in names if names.count(n) > 1})[:5] if len(set(names)) != len(names) else []
    if dup:
        raise MotionFormatError(", ".join(map(str, inputs)), f"clip names occur twice: {dup}")
    captions: dict[str, list] = {}
    excluded: set[str] = set()
    if ann is not None:
        ann.split_of()  # a clip in two splits
        if cfg.limit is None:
            try:
                ann.check_splits(set(names), cfg.clips)
            except MotionFormatError as e:
                raise MotionFormatError(e.source, e.message + _selection_hint(names, cfg.clips), e.line) from None
        for name, origin in listed:
            try:
                captions[name] = [(x.text, x.tokens, x.start, x.end) for x in ann.captions(name)]
            except MotionFormatError as e:
                excluded.add(name)
                bad(BadInput(origin, e))
    if cfg.reference_clip is not None and cfg.reference_clip not in set(names) - excluded:
        raise UnknownNameError(f"reference_clip {cfg.reference_clip!r} is not among the {len(names)} clip(s) of the "
                               f"inputs matching {cfg.clips!r}")
    return len(names), captions, excluded


def _listing(path: Path, bad, broken: set[str] | None) -> list[tuple[str, str]]:
    try:
        return list_sources(path)
    except MotionFormatError as e:
        if e.source != str(path) or broken is None:
            raise
        bad(BadInput(str(path), e))
        broken.add(str(path))
        return []


def _selection_hint(names: list[str], pattern: str) -> str:
    """What to do when the split files name clips the inputs lack: select the inputs' clips."""
    prefix = os.path.commonprefix(names)
    glob = (prefix[:prefix.rfind("_") + 1] if "_" in prefix else prefix) + "*"
    how = f" (all {glob!r}): select them with --clips {glob!r}" if glob not in ("*", pattern) else \
        ": select them with --clips"
    return f"; the inputs hold {len(names)} clip(s) matching {pattern!r}{how}, or give --annotations none"


def resolve_annotations(cfg, inputs: list[Path], data_root) -> Path | None:
    """The annotations folder to use, or None (see the module docstring for ``auto``)."""
    a = cfg.annotations
    if a is None or str(a).lower() == "none":
        return None
    if str(a).lower() != "auto":
        return resolve_input(str(a), data_root)
    try:
        root = resolve_data_root(data_root)
    except DataRootError:
        return None  # no data root: the inputs cannot be the default data set
    bandai = (root / BANDAI_FOLDER).resolve()
    if not all(p.resolve().is_relative_to(bandai) for p in inputs):
        return None
    ann = root / BANDAI_ANNOTATIONS
    if not ann.is_dir():
        raise MissingFileError(f"{ann}: the Bandai-Namco annotations are missing (see docs/data.md), or pass "
                               f"--annotations none for no captions")
    return ann


def resolve_input(p: str, data_root: Path | None) -> Path:
    path = Path(p).expanduser()
    if path.exists() or path.is_absolute():
        return path
    root = resolve_data_root(data_root)
    return root / p


BANDAI_NAME = re.compile(r"^dataset-(\d+)_(.+?)_([a-z-]+)_(\d+)$")


def labels_from_name(name: str) -> dict:
    """Bandai-Namco clip names encode content and style: ``dataset-N_{content}_{style}_{id}``."""
    m = BANDAI_NAME.match(name)
    return {"set": int(m.group(1)), "content": m.group(2), "style": m.group(3)} if m else {}


class BadInput:
    """A clip that failed: where it came from and why, each said once."""

    def __init__(self, origin: str, error: Exception):
        self.origin, self.error = origin, error

    def reason(self) -> str:
        if isinstance(self.error, MotionFormatError) and self.error.source == self.origin:
            return self.error.message if self.error.line is None else f"line {self.error.line}: {self.error.message}"
        msg = str(self.error)
        for sep in (": ", ", "):
            if msg.startswith(self.origin + sep):
                return msg[len(self.origin) + len(sep):]
        return msg
