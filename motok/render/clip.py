"""One clip of a motion artifact as a stick figure, drawn the way every motok command draws it:
the first caption as the title and the feature vector's foot contacts on the feet
(``motok render``, ``motok gpt sample --render``)."""

from __future__ import annotations

from pathlib import Path

from motok.data.dataset import Clip, MotionFile
from motok.features.humanml3d import NUM_CONTACTS
from motok.render.stick import render_motion
from motok.skeleton import Skeleton


def render_clip(clip: Clip, skeleton: Skeleton, out, fps: float, *, max_frames: int | None = None) -> Path:
    """Render ``clip`` to ``out`` (.gif, .mp4 or .png); see :func:`motok.render.stick.render_motion`."""
    title = clip.captions[0][0] if clip.captions else clip.name
    feet = list(skeleton.feet_left) + list(skeleton.feet_right)
    return render_motion(clip.joints, skeleton.parents, out, fps=fps, title=title,
                         contacts=clip.features[:, -NUM_CONTACTS:], foot_joints=feet, max_frames=max_frames)


def render_artifact_clip(path, clip, out, max_frames: int | None = None) -> Path:
    """Clip ``clip`` (name or index) of the motion or motion-dataset artifact at ``path``."""
    with MotionFile(path) as mf:
        return render_clip(mf.clip(clip), mf.skeleton, out, mf.fps, max_frames=max_frames)
