"""Frame-rate conversion on a common time grid.

Output frame ``k`` sits at time ``k / dst_fps`` for ``k = 0 .. floor((T - 1) * dst_fps / src_fps)``,
i.e. it starts on the first source frame and never extrapolates past the last one. HumanML3D
itself downsamples AMASS by striding; interpolation also handles ratios such as 30 -> 20 fps.
"""

from __future__ import annotations

import numpy as np

from motok.rotations import slerp

_GRID_TOL = 1e-9  # keeps an exact multiple (e.g. 60 -> 20 fps) from losing its last frame to rounding


def time_grid(num_frames: int, src_fps: float, dst_fps: float) -> tuple[np.ndarray, np.ndarray]:
    """Left source index and fraction of each output frame: ``(i0 (K,), frac (K,))``."""
    if src_fps <= 0 or dst_fps <= 0:
        raise ValueError(f"frame rates must be positive, got {src_fps} -> {dst_fps}")
    if num_frames < 1:
        raise ValueError("cannot resample an empty clip")
    count = int(np.floor((num_frames - 1) * dst_fps / src_fps + _GRID_TOL)) + 1
    s = np.arange(count) * (src_fps / dst_fps)
    s = np.minimum(s, num_frames - 1)  # the tolerance may put the last sample a hair past the end
    i0 = np.minimum(np.floor(s).astype(np.int64), max(num_frames - 2, 0))
    return i0, s - i0


def resample_positions(x: np.ndarray, src_fps: float, dst_fps: float) -> np.ndarray:
    """Linear interpolation along axis 0 onto the grid ``k / dst_fps``."""
    x = np.asarray(x)
    i0, frac = time_grid(len(x), src_fps, dst_fps)
    if len(x) == 1:
        return x.copy()
    f = frac.reshape((-1,) + (1,) * (x.ndim - 1))
    return (1.0 - f) * x[i0] + f * x[i0 + 1]


def resample_quats(q: np.ndarray, src_fps: float, dst_fps: float) -> np.ndarray:
    """Slerp of unit quaternions ``(T, ..., 4)`` along axis 0 onto the grid ``k / dst_fps``."""
    q = np.asarray(q, dtype=np.float64)
    i0, frac = time_grid(len(q), src_fps, dst_fps)
    if len(q) == 1:
        return q.copy()
    t = frac.reshape((-1,) + (1,) * (q.ndim - 2))
    return slerp(q[i0], q[i0 + 1], t)
