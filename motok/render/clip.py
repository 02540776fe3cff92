"""One clip of a motion artifact as a stick figure, drawn the way every motok command draws it:
the first caption as the title and the feature vector's foot contacts on the feet
(``motok render``, ``motok gpt sample --render``), to a file or to frames in memory."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from motok.data.dataset import Clip, MotionFile
from motok.features.humanml3d import NUM_CONTACTS
from motok.render.stick import render_frames, render_motion
from motok.skeleton import Skeleton


def _drawing(clip: Clip, skeleton: Skeleton) -> dict:
    """What the stick figure takes from a clip besides its joints: title, contacts, feet."""
    return dict(title=clip.captions[0][0] if clip.captions else clip.name,
                contacts=clip.features[:, -NUM_CONTACTS:],
                foot_joints=list(skeleton.feet_left) + list(skeleton.feet_right))


def render_clip(clip: Clip, skeleton: Skeleton, out, fps: float, *, max_frames: int | None = None) -> Path:
    """Render ``clip`` to ``out`` (.gif, .mp4 or .png); see :func:`motok.render.stick.render_motion`."""
    return render_motion(clip.joints, skeleton.parents, out, fps=fps, max_frames=max_frames,
                         **_drawing(clip, skeleton))


def clip_frames(clip: Clip, skeleton: Skeleton, fps: float, *, max_frames: int | None = None,
                size: tuple[int, int] = (480, 480)) -> np.ndarray:
    """``clip`` drawn as :func:`render_clip` draws it, as ``(T, H, W, 3) uint8`` frames."""
    return render_frames(clip.joints, skeleton.parents, fps=fps, max_frames=max_frames, size=size,
                         **_drawing(clip, skeleton))


def render_artifact_clip(path, clip, out, max_frames: int | None = None) -> Path:
    """Clip ``clip`` (name or index) of the motion or motion-dataset artifact at ``path``."""
    with MotionFile(path) as mf:
        return render_clip(mf.clip(clip), mf.skeleton, out, mf.fps, max_frames=max_frames)
