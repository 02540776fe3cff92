"""Clips in memory that read like a motion artifact: the same questions :class:`MotionFile`
answers (names, splits, frame rate, skeleton, a clip's frames, labels and captions), asked of
:class:`~motok.data.dataset.Clip` objects instead of an HDF5 file.

What consumes a motion artifact (tracking, the reference library) takes either, so a motion made
in memory (by the Python API, a notebook) is tracked without being written to a file first; and
:meth:`MotionClips.write` is the artifact writer, so a file made from it is what the command
line would have made from the same clips.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from motok.artifacts import Provenance
from motok.data.dataset import Clip, clip_index, write_motion
from motok.errors import UserError
from motok.skeleton import Skeleton


@dataclass
class MotionClips:
    """Clips of one skeleton at one frame rate, with the reading interface of :class:`MotionFile`.

    ``path`` names them in messages (there is no file); ``offsets`` are the skeleton's rest
    offsets ``(J, 3)``; ``legacy``: the features follow the official HumanML3D quirks."""

    clips: list[Clip]
    skeleton: Skeleton
    offsets: np.ndarray
    fps: float
    legacy: bool = False
    path: str = "the motions in memory"
    kind: str = "motion"

    def __post_init__(self):
        self.offsets = np.asarray(self.offsets, dtype=np.float32)
        self._index = {c.name: i for i, c in enumerate(self.clips)}
        if len(self._index) != len(self.clips):
            dup = sorted({c.name for c in self.clips if sum(d.name == c.name for d in self.clips) > 1})
            raise UserError(f"{self.path}: clip names must be distinct, {dup} repeat")

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()

    def close(self):
        pass

    def __len__(self):
        return len(self.clips)

    @property
    def names(self) -> list[str]:
        return [c.name for c in self.clips]

    @property
    def splits(self) -> list[str]:
        return [c.split for c in self.clips]

    @property
    def frame_offsets(self) -> np.ndarray:
        return np.concatenate([[0], np.cumsum([c.num_frames for c in self.clips])]).astype(np.int64)

    def index(self, name_or_index) -> int:
        return clip_index(self.names, name_or_index, positions=self._index, where=f"{self.path}: ")

    def frames(self, key: str, clip) -> np.ndarray:
        return getattr(self.clips[self.index(clip)], key)

    def captions(self, clip, tokens: bool = False) -> list[tuple]:
        caps = self.clips[self.index(clip)].captions
        return [tuple(c) if tokens else (c[0], *c[2:]) for c in caps]

    def clip(self, clip) -> Clip:
        return self.clips[self.index(clip)]

    def split_indices(self, split: str) -> list[int]:
        return [i for i, s in enumerate(self.splits) if s == split]

    def write(self, path, provenance: Provenance):
        """These clips as a ``motion`` artifact at ``path`` (atomic), with ``provenance``."""
        return write_motion(path, self.kind, provenance, self.clips, self.skeleton, self.offsets, self.fps,
                            self.legacy)
