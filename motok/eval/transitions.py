"""The transitions of motion that Table 1 of the hybrid-latent paper (section 6.2, Eq. 8) compares:
states from joint positions, and the transitions of every clip of a motion artifact.

**The state** ``s_t`` is computed from joint positions alone, so it exists for every motion
artifact (a dataset, simulated or kinematic generation) at its frame rate, and is Eq. 7's
proprioception in the terms joints allow (Eq. 7 itself needs the simulator's hinge angles):

* the root height (1);
* every other joint relative to the root, in the heading frame (3 (J - 1));
* the root's linear velocity in the heading frame (3) and its yaw rate (1), backward differences
  ``(x_t - x_{t-1}) fps``.

The heading is HumanML3D's facing direction (across the hips and shoulders, not smoothed), so
``s_t`` does not change when a motion is moved or turned on the floor. A transition is
``(s_t, s_{t+1})``, ``2 (3J + 2)`` values (130 for 21 joints); a clip of T frames has T - 2.
Motion at another frame rate than the dataset's is resampled to it first.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from motok.errors import UserError


def heading_yaw(joints: np.ndarray, skeleton) -> np.ndarray:
    """``(T,)`` yaw of the facing direction (radians from +Z towards +X)."""
    from motok.features.kinematics import forward_direction

    fwd = forward_direction(np.asarray(joints, np.float64), skeleton, smooth=False)
    return np.arctan2(fwd[:, 0], fwd[:, 2])


def _unturn(v: np.ndarray, yaw: np.ndarray) -> np.ndarray:
    """Vectors ``(T, ..., 3)`` rotated by ``-yaw`` about +Y (world -> heading frame: forward is +Z)."""
    c = np.cos(yaw).reshape((-1,) + (1,) * (v.ndim - 2))
    s = np.sin(yaw).reshape(c.shape)
    x, z = v[..., 0], v[..., 2]
    return np.stack([c * x - s * z, v[..., 1], s * x + c * z], -1)


def states(joints: np.ndarray, fps: float, skeleton) -> np.ndarray:
    """``(T - 1, 3J + 2)`` states of frames 1..T-1 of ``(T, J, 3)`` joints (module docstring)."""
    x = np.asarray(joints, np.float64)
    if len(x) < 2:
        return np.zeros((0, 3 * x.shape[1] + 2))
    yaw = heading_yaw(x, skeleton)
    root = x[:, 0]
    rel = _unturn(x[1:, 1:] - root[1:, None], yaw[1:])
    vel = _unturn(np.diff(root, axis=0) * fps, yaw[1:])
    turn = (np.diff(yaw) + np.pi) % (2 * np.pi) - np.pi  # wrapped to (-pi, pi]
    return np.concatenate([root[1:, 1:2], rel.reshape(len(rel), -1), vel, (turn * fps)[:, None]], 1)


def transitions(joints: np.ndarray, fps: float, skeleton) -> np.ndarray:
    """``(T - 2, 2 (3J + 2))`` rows ``(s_t, s_{t+1})``."""
    s = states(joints, fps, skeleton)
    return np.concatenate([s[:-1], s[1:]], 1)


def acceleration_sum(joints: np.ndarray, fps: float) -> tuple[float, int]:
    """Sum over frames of the mean joint acceleration norm (m/s^2), and the number of frames."""
    x = np.asarray(joints, np.float64)
    if len(x) < 3:
        return 0.0, 0
    a = np.linalg.norm(x[2:] - 2 * x[1:-1] + x[:-2], axis=-1).mean(-1) * fps ** 2
    return float(a.sum()), len(a)


@dataclass
class TransitionSet:
    """The transitions of some clips of one artifact, with the owner clip of every row."""

    path: str
    names: list[str]
    x: np.ndarray  # (n, D) float32, not normalised
    clip: np.ndarray  # (n,) index into names
    fps: float
    jitter_m_s3: float
    acceleration_m_s2: float
    frames: int


def load_set(path, names: list[str] | None = None, fps: float | None = None, skeleton=None) -> TransitionSet:
    """Transitions of the clips ``names`` (all by default) of the motion artifact at ``path``,
    resampled to ``fps`` when given and different; ``skeleton`` (the dataset's) must match."""
    from motok.data.dataset import MotionFile
    from motok.eval.physical import PhysicalSums, clip_sums
    from motok.features.resample import resample_positions

    with MotionFile(path) as mf:
        sk, own = mf.skeleton, mf.fps
        if skeleton is not None and list(sk.joints) != list(skeleton.joints):
            raise UserError(f"{path}: skeleton {sk.name!r} has other joints than the dataset's {skeleton.name!r}")
        ids = list(range(len(mf))) if names is None else [mf.index(n) for n in names]
        off = mf.frame_offsets
        every = mf.h5["frames"]["joints"][()] if len(ids) > 50 else None  # one read beats thousands
        rows, owner, kept, phys = [], [], [], PhysicalSums()
        acc, acc_n, frames = 0.0, 0, 0
        feet = (tuple(sk.feet_left), tuple(sk.feet_right))
        for i in ids:
            j = mf.check_finite("joints", every[off[i]:off[i + 1]], i) if every is not None else mf.frames("joints", i)
            phys.add(clip_sums(j, own, feet))
            a, n = acceleration_sum(j, own)
            acc, acc_n, frames = acc + a, acc_n + n, frames + len(j)
            if fps is not None and abs(fps - own) > 1e-6 and len(j) > 1:
                j = resample_positions(np.asarray(j, np.float64), own, fps)
            t = transitions(j, fps or own, sk)
            if len(t):
                rows.append(t.astype(np.float32))
                owner.append(np.full(len(t), len(kept)))
                kept.append(mf.names[i])
    if not rows:
        raise UserError(f"{path}: no clip has the 3 frames a transition needs")
    return TransitionSet(str(path), kept, np.concatenate(rows), np.concatenate(owner), float(fps or own),
                     phys.result()["jitter_m_s3"], acc / max(acc_n, 1), frames)
