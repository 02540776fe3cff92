"""Captions and splits in the HumanML3D layout.

``texts/<clip>.txt`` holds one caption a line as ``caption#word/POS ...#start#end``: start =
end = 0 means the caption covers the whole clip, otherwise it covers the span in seconds.
``train.txt``, ``val.txt`` and ``test.txt`` list clip names, one a line.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from fnmatch import fnmatchcase
from pathlib import Path

from motok.data.bvh import MotionFormatError
from motok.errors import MissingFileError

SPLITS = ("train", "val", "test")


@dataclass(frozen=True)
class Caption:
    text: str
    tokens: str
    start: float  # seconds; start == end == 0 means the whole clip
    end: float


def parse_caption_file(path: Path) -> list[Caption]:
    out = []
    for lineno, line in enumerate(path.read_text(encoding="utf-8").splitlines(), 1):
        if not line.strip():
            continue
        parts = line.split("#")
        if len(parts) != 4:
            raise MotionFormatError(str(path), f"expected 'caption#tokens#start#end' (4 fields separated by '#'), "
                                    f"found {len(parts)} field(s)", line=lineno)
        text, tokens, s, e = parts
        try:
            start, end = float(s or 0.0), float(e or 0.0)
        except ValueError:
            raise MotionFormatError(str(path), f"start/end must be numbers of seconds, got {s!r} and {e!r}",
                                    line=lineno) from None
        if not (math.isfinite(start) and math.isfinite(end)) or start < 0 or (end != 0 and end <= start):
            raise MotionFormatError(str(path), f"span start={start} end={end} is not a valid span in seconds",
                                    line=lineno)
        if not text.strip():
            raise MotionFormatError(str(path), "empty caption", line=lineno)
        out.append(Caption(text.strip(), tokens.strip(), start, end))
    if not out:
        raise MotionFormatError(str(path), "caption file has no captions")
    return out


@dataclass
class Annotations:
    root: Path
    splits: dict[str, list[tuple[str, int]]]  # split -> [(clip, line number)]

    @classmethod
    def load(cls, root: str | Path) -> "Annotations":
        root = Path(root)
        if not root.is_dir():
            raise MissingFileError(f"annotations directory {root} does not exist")
        if not (root / "texts").is_dir():
            raise MissingFileError(f"{root}: no texts/ directory of captions (HumanML3D layout expected)")
        splits: dict[str, list[tuple[str, int]]] = {}
        for split in SPLITS:
            f = root / f"{split}.txt"
            if f.exists():
                splits[split] = [(ln.strip(), i) for i, ln in enumerate(f.read_text().splitlines(), 1) if ln.strip()]
        return cls(root, splits)

    def split_of(self) -> dict[str, str]:
        out: dict[str, str] = {}
        for split, entries in self.splits.items():
            for clip, lineno in entries:
                if clip in out and out[clip] != split:
                    raise MotionFormatError(str(self.root / f"{split}.txt"),
                                            f"clip {clip!r} is already in split {out[clip]!r}", line=lineno)
                out[clip] = split
        return out

    def caption_path(self, clip: str) -> Path:
        return self.root / "texts" / f"{clip}.txt"

    def captions(self, clip: str) -> list[Caption]:
        p = self.caption_path(clip)
        if not p.exists():
            raise MotionFormatError(str(p), f"clip {clip!r} has no caption file (expected {p})")
        return parse_caption_file(p)

    def check_splits(self, clips: set[str], pattern: str = "*") -> None:
        """Every split entry that the selection ``pattern`` covers must name a clip among the inputs."""
        for split, entries in self.splits.items():
            for clip, lineno in entries:
                if fnmatchcase(clip, pattern) and clip not in clips:
                    raise MotionFormatError(str(self.root / f"{split}.txt"),
                                            f"names clip {clip!r}, which is not among the inputs", line=lineno)
