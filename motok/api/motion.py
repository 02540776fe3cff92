"""The motion of the Python API: :class:`Motion`, one clip with the skeleton and frame rate it
needs to mean anything, and what is done with motions (read, write, draw, export).

Every function here is a thin layer over the one the command line runs, so a motion written or
drawn from Python is the file ``motok`` would have written or drawn from the same clip.
Nothing here imports torch or MuJoCo.
"""

from __future__ import annotations

__all__ = ["Motion", "export_bvh", "load_motions", "render_frames", "render_motion", "save_motions"]

from dataclasses import dataclass
from pathlib import Path
from typing import Iterable

import numpy as np

from motok.data.dataset import Clip
from motok.errors import UserError
from motok.ranges import checked  # numbers in range for callers from Python too
from motok.skeleton import Skeleton


@dataclass(repr=False)
class Motion:
    """One motion in memory: its frames as the artifacts store them (``clip``: features, joints,
    local rotations, root translation, labels, captions), on ``skeleton`` at ``fps``.

    ``offsets`` (the skeleton's rest offsets, ``(J, 3)``) and ``legacy`` (features in the
    official HumanML3D convention) travel with it because writing, exporting and tracking need
    them; the properties are what a notebook reads."""

    clip: Clip
    skeleton: Skeleton
    fps: float
    offsets: np.ndarray
    legacy: bool = False

    @property
    def name(self) -> str:
        return self.clip.name

    @property
    def caption(self) -> str:
        """The first caption's text ("" for a motion without one)."""
        return self.clip.captions[0][0] if self.clip.captions else ""

    @property
    def joints(self) -> np.ndarray:
        """Global joint positions ``(T, J, 3)`` in metres, Y up, facing +Z at frame 0."""
        return self.clip.joints

    @property
    def features(self) -> np.ndarray:
        """HumanML3D-style features ``(T, 12J - 1)``, not normalized."""
        return self.clip.features

    @property
    def labels(self) -> dict:
        """What made the motion: a GPT sample's text, seed and codes; a tracked clip's outcome."""
        return self.clip.labels

    @property
    def num_frames(self) -> int:
        return self.clip.num_frames

    @property
    def seconds(self) -> float:
        return self.num_frames / self.fps

    def __repr__(self) -> str:
        said = f", {self.caption!r}" if self.caption else ""
        return (f"Motion({self.name!r}, {self.num_frames} frames at {self.fps:g} fps, "
                f"{self.skeleton.num_joints} joints{said})")


def motions(motion: Motion | Iterable[Motion]) -> list[Motion]:
    """One motion or several, as a non-empty list."""
    out = [motion] if isinstance(motion, Motion) else list(motion)
    bad = [type(m).__name__ for m in out if not isinstance(m, Motion)]
    if bad or not out:
        raise UserError(f"expected a Motion or a list of them, got {bad[0] if bad else 'an empty list'}")
    return out


def as_clips(motion: Motion | Iterable[Motion]):
    """The motions as one :class:`~motok.data.memory.MotionClips`: they must share a skeleton,
    frame rate and feature convention (a motion artifact holds one of each)."""
    from motok.data.memory import MotionClips

    ms = motions(motion)
    first = ms[0]
    for m in ms[1:]:
        same = (list(m.skeleton.joints) == list(first.skeleton.joints) and m.fps == first.fps
                and m.legacy == first.legacy)
        if not same:
            raise UserError(f"motions {first.name!r} and {m.name!r} differ in skeleton, frame rate or feature "
                            f"convention; one motion artifact holds one of each")
    return MotionClips([m.clip for m in ms], first.skeleton, first.offsets, first.fps, first.legacy)


def from_clips(source) -> list[Motion]:
    """Every clip of an open motion (:class:`MotionFile` or MotionClips) as a :class:`Motion`."""
    return [Motion(source.clip(i), source.skeleton, source.fps, np.asarray(source.offsets, dtype=np.float32),
                   source.legacy) for i in range(len(source))]


def load_motions(path, *, clips: str | None = None, split: str | None = None) -> list[Motion]:
    """The clips of the motion or motion-dataset artifact at ``path`` (all, or those of ``split``
    and/or matching the glob ``clips``), in the file's order."""
    from motok.data.dataset import MotionFile, select_clips
    from motok.data.memory import MotionClips

    with MotionFile(path) as mf:
        names = select_clips(mf, clips, split) if clips or split else list(mf.names)
        chosen = MotionClips([mf.clip(n) for n in names], mf.skeleton, mf.offsets, mf.fps, mf.legacy, path=str(path))
    return from_clips(chosen)


def save_motions(motion: Motion | Iterable[Motion], path) -> Path:
    """Write motions as one ``motion`` artifact (HDF5, atomic), readable by every ``motok``
    command; the frames are those ``motok gpt sample`` or ``control track`` would write for the
    same clips. Returns the path."""
    from motok.artifacts import Provenance, command_line
    from motok.atomic import check_writable

    clips = as_clips(motion)
    check_writable(path, suffixes=(".h5", ".hdf5"))
    prov = Provenance(command=command_line(), config={"written_by": "motok.save_motions", "clips": clips.names})
    return Path(clips.write(path, prov))


@checked(max_frames=">= 1")
def render_motion(motion: Motion, path, *, max_frames: int | None = None) -> Path:
    """Draw the motion as ``motok render`` does: a stick figure to ``path`` (.gif, .mp4, or
    .png for a contact sheet), titled with its caption. Returns the path."""
    from motok.render.clip import render_clip

    m = motions(motion)[0]
    return render_clip(m.clip, m.skeleton, path, m.fps, max_frames=max_frames)


@checked(max_frames=">= 1")
def render_frames(motion: Motion, *, max_frames: int | None = None,
                  size: tuple[int, int] = (480, 480)) -> np.ndarray:
    """The frames :func:`render_motion` draws, as a ``(T, H, W, 3) uint8`` array (for a
    notebook: ``PIL.Image.fromarray(frames[0])``, or ``mediapy.show_video(frames)``)."""
    from motok.render.clip import clip_frames

    m = motions(motion)[0]
    return clip_frames(m.clip, m.skeleton, m.fps, max_frames=max_frames, size=size)


def export_bvh(motion: Motion, path, *, order: str = "ZXY") -> Path:
    """The motion as a BVH in centimetres (Blender, game engines), as ``motok export bvh``
    writes it. Returns the path."""
    from motok.data.export import export_bvh as write

    m = motions(motion)[0]
    return write(path, m.joints, m.skeleton, m.offsets, m.fps, order=order)
