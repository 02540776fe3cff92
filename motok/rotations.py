"""Rotation maths shared by every stage.

Quaternions are ``(w, x, y, z)`` with the scalar first, as in HumanML3D. Every function
broadcasts over leading dimensions; the core ones (``qmul``, ``qinv``, ``qrot``,
``qnormalize``, ``qbetween``, the matrix and 6D conversions) accept numpy arrays or torch
tensors alike, so the feature code and the training code share one implementation.

Euler angles follow the BVH convention: a channel order such as ``"ZXY"`` means the
intrinsic rotation ``R = Rz(a0) @ Rx(a1) @ Ry(a2)``, i.e. ``v_parent = R @ v_child``.
"""

from __future__ import annotations

import numpy as np

try:  # torch is a hard dependency of the package, but the maths must not need it
    import torch
except ImportError:  # pragma: no cover
    torch = None


def _stack(parts, like):
    if torch is not None and isinstance(like, torch.Tensor):
        return torch.stack(parts, -1)
    return np.stack(parts, -1)


def _cross(a, b):
    ax, ay, az = a[..., 0], a[..., 1], a[..., 2]
    bx, by, bz = b[..., 0], b[..., 1], b[..., 2]
    return _stack([ay * bz - az * by, az * bx - ax * bz, ax * by - ay * bx], a)


def qmul(a, b):
    """Hamilton product ``a * b`` (apply ``b`` first, then ``a``)."""
    aw, ax, ay, az = a[..., 0], a[..., 1], a[..., 2], a[..., 3]
    bw, bx, by, bz = b[..., 0], b[..., 1], b[..., 2], b[..., 3]
    return _stack([
        aw * bw - ax * bx - ay * by - az * bz,
        aw * bx + ax * bw + ay * bz - az * by,
        aw * by - ax * bz + ay * bw + az * bx,
        aw * bz + ax * by - ay * bx + az * bw,
    ], a if a.ndim >= b.ndim else b)


def qinv(q):
    """Inverse of a unit quaternion (its conjugate)."""
    sign = q.new_tensor([1.0, -1.0, -1.0, -1.0]) if torch is not None and isinstance(q, torch.Tensor) \
        else np.array([1.0, -1.0, -1.0, -1.0], dtype=q.dtype)
    return q * sign


def qnormalize(q):
    return q / ((q * q).sum(-1)[..., None]) ** 0.5


def qrot(q, v):
    """Rotate vectors ``v (..., 3)`` by unit quaternions ``q (..., 4)``.

    Uses ``v' = v + 2w (u x v) + 2 u x (u x v)``, which needs no matrix.
    """
    u = q[..., 1:]
    w = q[..., :1]
    uv = _cross(u, v)
    return v + 2.0 * (w * uv + _cross(u, uv))


def qbetween(v0, v1):
    """The shortest-arc rotation taking direction ``v0`` onto ``v1`` (HumanML3D's ``qbetween``)."""
    v = _cross(v0, v1)
    w = ((v0 * v0).sum(-1) * (v1 * v1).sum(-1)) ** 0.5 + (v0 * v1).sum(-1)
    return qnormalize(_stack([w, v[..., 0], v[..., 1], v[..., 2]], v))


def quat_to_matrix(q):
    w, x, y, z = q[..., 0], q[..., 1], q[..., 2], q[..., 3]
    two_s = 2.0 / (q * q).sum(-1)
    m = _stack([
        1 - two_s * (y * y + z * z), two_s * (x * y - z * w), two_s * (x * z + y * w),
        two_s * (x * y + z * w), 1 - two_s * (x * x + z * z), two_s * (y * z - x * w),
        two_s * (x * z - y * w), two_s * (y * z + x * w), 1 - two_s * (x * x + y * y),
    ], q)
    return m.reshape(tuple(q.shape[:-1]) + (3, 3))


def matrix_to_cont6d(m):
    """The continuous 6D representation (Zhou et al. 2019): the first two matrix columns."""
    return _stack([m[..., 0, 0], m[..., 1, 0], m[..., 2, 0], m[..., 0, 1], m[..., 1, 1], m[..., 2, 1]], m)


def quat_to_cont6d(q):
    return matrix_to_cont6d(quat_to_matrix(q))


def cont6d_to_matrix(d6):
    """Gram-Schmidt back to a rotation matrix (columns x, y, z), as HumanML3D does."""
    x_raw, y_raw = d6[..., 0:3], d6[..., 3:6]
    x = x_raw / ((x_raw * x_raw).sum(-1)[..., None]) ** 0.5
    z = _cross(x, y_raw)
    z = z / ((z * z).sum(-1)[..., None]) ** 0.5
    y = _cross(z, x)
    cols = [x, y, z]
    if torch is not None and isinstance(d6, torch.Tensor):
        return torch.stack(cols, -1)
    return np.stack(cols, -1)


def matrix_to_quat(m: np.ndarray) -> np.ndarray:
    """Rotation matrices to unit quaternions with ``w >= 0`` (numpy; robust branch per element)."""
    m = np.asarray(m, dtype=np.float64)
    m00, m11, m22 = m[..., 0, 0], m[..., 1, 1], m[..., 2, 2]
    # Four candidate magnitudes; pick the largest per element for numerical stability.
    cand = np.stack([1 + m00 + m11 + m22, 1 + m00 - m11 - m22, 1 - m00 + m11 - m22, 1 - m00 - m11 + m22], -1)
    best = cand.argmax(-1)
    s = np.sqrt(np.maximum(np.take_along_axis(cand, best[..., None], -1)[..., 0], 1e-12)) * 2
    q = np.empty(m.shape[:-2] + (4,))
    rows = {
        0: (s / 4, (m[..., 2, 1] - m[..., 1, 2]) / s, (m[..., 0, 2] - m[..., 2, 0]) / s, (m[..., 1, 0] - m[..., 0, 1]) / s),
        1: ((m[..., 2, 1] - m[..., 1, 2]) / s, s / 4, (m[..., 0, 1] + m[..., 1, 0]) / s, (m[..., 0, 2] + m[..., 2, 0]) / s),
        2: ((m[..., 0, 2] - m[..., 2, 0]) / s, (m[..., 0, 1] + m[..., 1, 0]) / s, s / 4, (m[..., 1, 2] + m[..., 2, 1]) / s),
        3: ((m[..., 1, 0] - m[..., 0, 1]) / s, (m[..., 0, 2] + m[..., 2, 0]) / s, (m[..., 1, 2] + m[..., 2, 1]) / s, s / 4),
    }
    for k, comps in rows.items():
        sel = best == k
        q[sel] = np.stack([c[sel] for c in comps], -1)
    return q * np.where(q[..., :1] < 0, -1.0, 1.0)


def kabsch(src: np.ndarray, dst: np.ndarray) -> np.ndarray:
    """Rotations ``R (F, 3, 3)`` minimising ``sum_k |R src_k - dst_k|^2``; src ``(K, 3)``, dst ``(F, K, 3)``.

    Kabsch's algorithm (Kabsch 1976; numpy only): with ``H = sum_k src_k dst_k^T = U S V^T``,
    ``R = V diag(1, 1, d) U^T``, where ``d = sign det(V U^T)`` keeps ``R`` a rotation rather than
    a reflection when the point sets are (near-)planar or noisy.
    """
    h = np.einsum("ki,fkj->fij", src, dst)
    u, _, vt = np.linalg.svd(h)
    d = np.sign(np.linalg.det(np.einsum("fji,fkj->fik", vt, u)))
    fix = np.ones(u.shape[:-1])
    fix[:, -1] = d
    return np.einsum("fji,fj,fkj->fik", vt, fix, u)


_AXES = {"X": 0, "Y": 1, "Z": 2}


def euler_to_quat(angles: np.ndarray, order: str, degrees: bool = True) -> np.ndarray:
    """Intrinsic Euler angles ``(..., 3)`` in channel ``order`` (e.g. ``"ZXY"``) to quaternions."""
    a = np.asarray(angles, dtype=np.float64)
    if degrees:
        a = np.deg2rad(a)
    half = 0.5 * a
    c, s = np.cos(half), np.sin(half)
    q = None
    for i, axis in enumerate(order.upper()):
        qi = np.zeros(a.shape[:-1] + (4,))
        qi[..., 0] = c[..., i]
        qi[..., 1 + _AXES[axis]] = s[..., i]
        q = qi if q is None else qmul(q, qi)
    return q


def quat_to_euler(q: np.ndarray, order: str, degrees: bool = True) -> np.ndarray:
    """Unit quaternions to intrinsic Euler angles in ``order`` (inverse of :func:`euler_to_quat`)."""
    from scipy.spatial.transform import Rotation  # gimbal-lock handling done right, vectorized

    q = np.asarray(q, dtype=np.float64)
    flat = q.reshape(-1, 4)
    r = Rotation.from_quat(flat[:, [1, 2, 3, 0]])  # scipy is scalar-last
    e = r.as_euler(order.upper(), degrees=degrees)
    return e.reshape(q.shape[:-1] + (3,))


def qfix(q: np.ndarray) -> np.ndarray:
    """Flip signs along time (axis 0) so consecutive quaternions lie in one hemisphere."""
    q = np.array(q, copy=True)
    dots = (q[1:] * q[:-1]).sum(-1)
    flips = np.cumsum(dots < 0, axis=0) % 2
    q[1:][flips.astype(bool)] *= -1
    return q


def slerp(q0: np.ndarray, q1: np.ndarray, t) -> np.ndarray:
    """Spherical linear interpolation between unit quaternions, broadcasting ``t``."""
    t = np.asarray(t, dtype=np.float64)
    dot = (q0 * q1).sum(-1)
    q1 = np.where(dot[..., None] < 0, -q1, q1)
    dot = np.abs(dot)
    theta = np.arccos(np.clip(dot, -1.0, 1.0))
    sin_t = np.sin(theta)
    near = sin_t < 1e-6  # nearly parallel: linear interpolation is exact enough and stable
    safe = np.where(near, 1.0, sin_t)
    w0 = np.where(near, 1.0 - t, np.sin((1.0 - t) * theta) / safe)
    w1 = np.where(near, t, np.sin(t * theta) / safe)
    return qnormalize(w0[..., None] * q0 + w1[..., None] * q1)


def yaw_quat(angle):
    """Rotation about +Y by ``angle`` radians."""
    angle = np.asarray(angle, dtype=np.float64)
    z = np.zeros_like(angle)
    return np.stack([np.cos(angle / 2), z, np.sin(angle / 2), z], -1)
