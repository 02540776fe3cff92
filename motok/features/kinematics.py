"""Inverse and forward kinematics in HumanML3D's per-bone convention, vectorized.

HumanML3D (``common/skeleton.py``) stores one rotation per joint ``c``: it rotates the bone
``parent(c) -> c`` from its rest direction (``skeleton.directions[c]``) into place, *relative
to a parent frame*. Writing ``G[c] = qbetween(directions[c], unit(x[c] - x[parent(c)]))`` for
the global rotation of that bone and ``G[0]`` for the root rotation, the stored local rotation
is ``L[c] = inv(G[frame(c)]) * G[c]`` and forward kinematics is

    G[c] = G[frame(c)] * L[c],    x[c] = x[parent(c)] + qrot(G[c], offsets[c]).

The parent frame ``frame(c)`` is where the two conventions differ:

* default (``legacy=False``): ``frame(c) = parent(c)``; a chain that starts at spine3 hangs
  off the accumulated rotation of the bone spine2 -> spine3. The root rotation is the
  heading (the yaw taking +Z onto the body's forward), so locals are facing-invariant.
* ``legacy=True`` (the official code): every chain restarts from the root rotation, so
  ``frame(chain[1]) = root`` even for the arm chains that start at spine3; the root rotation
  is HumanML3D's ``root_quat`` (the yaw taking the forward onto +Z, i.e. the inverse of the
  heading); the face joints are unpacked as ``(l_hip, r_hip, sdr_r, sdr_l)``, which flips the
  sign of the hip term in the forward direction.

Because IK and FK share ``frame``, ``FK(IK(x))`` puts every bone of ``x`` back in place in
both conventions (with the bone lengths of ``offsets``). No loop runs over frames; IK has no
loop at all, FK loops over depth levels of the ``frame`` tree.

Also here: the errors between two joint trajectories (``mpjpe``, ``velocity_error``,
``acceleration_error``) that the tokenizer, the evaluation and the control stage all measure.
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import lru_cache

import numpy as np
from scipy.ndimage import gaussian_filter1d

from motok.rotations import qinv, qmul, qrot
from motok.skeleton import Skeleton

UP = np.array([0.0, 1.0, 0.0])
FORWARD = np.array([0.0, 0.0, 1.0])
SMOOTH_SIGMA = 20  # frames; HumanML3D's gaussian_filter1d(forward, 20, mode='nearest')
_DEGENERATE = 1e-9  # |(1 + u.v, u x v)| below this means u and v are (anti)parallel


@dataclass(frozen=True)
class _Plan:
    frame: np.ndarray  # (J,) parent frame of each joint's rotation (root: -1)
    levels: tuple[np.ndarray, ...]  # joints grouped by depth in the frame tree, root excluded
    ancestors: np.ndarray  # (J, J-1): [j, c-1] = 1 if bone c lies on the path root -> j


@lru_cache(maxsize=64)
def _plan(skeleton: Skeleton, legacy: bool) -> _Plan:
    parents = skeleton.parents
    J = skeleton.num_joints
    frame = parents.copy()
    if legacy:
        for chain in skeleton.chains:  # HumanML3D: R = root_quat at the start of every chain
            frame[chain[1]] = 0
    depth = np.zeros(J, dtype=np.int64)
    for j in range(1, J):  # parents precede children (checked by Skeleton.from_dict)
        depth[j] = depth[frame[j]] + 1
    levels = tuple(np.flatnonzero(depth == d) for d in range(1, depth.max() + 1))
    anc = np.zeros((J, J - 1))
    for j in range(1, J):
        k = j
        while k > 0:
            anc[j, k - 1] = 1.0
            k = parents[k]
    return _Plan(frame=frame, levels=levels, ancestors=anc)


def _normalize(v: np.ndarray) -> np.ndarray:
    return v / np.sqrt((v * v).sum(-1, keepdims=True))


def qbetween_unit(u: np.ndarray, v: np.ndarray, fallback_axis: np.ndarray | None = None) -> np.ndarray:
    """HumanML3D's ``qbetween`` for unit vectors, ``normalize(1 + u.v, u x v)``.

    The official version returns NaN when ``v = -u``; here that case becomes a half turn about
    ``fallback_axis`` (or about an axis perpendicular to ``u``), so one bad frame cannot poison a clip.
    """
    u, v = np.broadcast_arrays(u, v)
    q = np.concatenate([1.0 + (u * v).sum(-1, keepdims=True), np.cross(u, v)], -1)
    n = np.sqrt((q * q).sum(-1, keepdims=True))
    bad = n[..., 0] < _DEGENERATE
    if bad.any():
        ub = u[bad]
        if fallback_axis is not None:
            axis = np.broadcast_to(fallback_axis, ub.shape)
        else:
            helper = np.where(np.abs(ub[:, :1]) < 0.9, [[1.0, 0, 0]], [[0, 1.0, 0]])
            axis = _normalize(np.cross(ub, helper))
        q[bad] = np.concatenate([np.zeros(ub.shape[:-1] + (1,)), axis], -1)
        n[bad] = 1.0
    return q / n


def skeleton_offsets(positions_frame0: np.ndarray, skeleton: Skeleton) -> np.ndarray:
    """HumanML3D ``Skeleton.get_offsets_joints``: rest direction times the frame's bone length."""
    p = np.asarray(positions_frame0, dtype=np.float64)
    lengths = np.linalg.norm(p[1:] - p[skeleton.parents[1:]], axis=-1)
    out = skeleton.directions.astype(np.float64).copy()
    out[1:] *= lengths[:, None]
    return out


def leg_length(offsets: np.ndarray, skeleton: Skeleton) -> float:
    """HumanML3D ``uniform_skeleton``'s leg: abs-max of the two leg bones' offsets, summed."""
    return float(np.abs(offsets[list(skeleton.leg_joints)]).max(-1).sum())


def bone_rotations(joints: np.ndarray, skeleton: Skeleton) -> np.ndarray:
    """``(..., J-1, 4)`` global rotation of each bone: ``qbetween(rest direction, bone direction)``."""
    bones = _normalize(joints[..., 1:, :] - joints[..., skeleton.parents[1:], :])
    return qbetween_unit(skeleton.directions[1:], bones)


def forward_direction(joints: np.ndarray, skeleton: Skeleton, *, smooth: bool, legacy: bool = False) -> np.ndarray:
    """HumanML3D's forward: ``up x normalize(across)``, optionally Gaussian-smoothed over time (axis 0).

    ``across = (r_hip - l_hip) + (r_shoulder - l_shoulder)``; with ``legacy`` the hip term
    is ``l_hip - r_hip`` as in the official IK, which unpacks the face joints in the wrong order.
    """
    r_hip, l_hip, r_sdr, l_sdr = skeleton.face_joints
    if legacy:
        r_hip, l_hip = l_hip, r_hip
    across = _normalize(joints[..., r_hip, :] - joints[..., l_hip, :] + joints[..., r_sdr, :] - joints[..., l_sdr, :])
    forward = np.cross(UP, across)
    if smooth:
        forward = gaussian_filter1d(forward, SMOOTH_SIGMA, axis=0, mode="nearest")
    return _normalize(forward)


def root_quat(forward: np.ndarray) -> np.ndarray:
    """HumanML3D's ``root_quat = qbetween(forward, +Z)``: the yaw that turns the body to face +Z."""
    return qbetween_unit(forward, FORWARD, fallback_axis=UP)


def root_rotation(joints: np.ndarray, skeleton: Skeleton, *, smooth: bool, legacy: bool = False) -> np.ndarray:
    """HumanML3D's IK root rotation ``r_rot`` ``(T, 4)``: ``root_quat`` of the (smoothed) forward.

    ``legacy`` adds the official IK's two quirks: the swapped hip term and ``root_quat[0]``
    forced to the identity (the first rotation velocity then absorbs the step from the
    identity to frame 1's heading).
    """
    rq = root_quat(forward_direction(joints, skeleton, smooth=smooth, legacy=legacy))
    if legacy:
        rq[0] = (1.0, 0.0, 0.0, 0.0)
    return rq


def locals_from_globals(root: np.ndarray, bone_rots: np.ndarray, skeleton: Skeleton,
                        legacy: bool = False) -> np.ndarray:
    """``L[c] = inv(G[frame(c)]) * G[c]`` for all joints at once; ``L[0] = root``."""
    plan = _plan(skeleton, legacy)
    g = np.concatenate([root[..., None, :], bone_rots], -2)
    local = qmul(qinv(g[..., plan.frame[1:], :]), bone_rots)
    return np.concatenate([root[..., None, :], local], -2)


def inverse_kinematics(joints: np.ndarray, skeleton: Skeleton, *, smooth_forward: bool,
                       legacy: bool = False) -> np.ndarray:
    """HumanML3D ``Skeleton.inverse_kinematics_np``: positions ``(T, J, 3)`` -> local rotations ``(T, J, 4)``.

    The root rotation is ``root_quat`` with ``legacy`` and its inverse (the heading) otherwise;
    see the module docstring for the parent frames.
    """
    joints = np.asarray(joints, dtype=np.float64)
    rq = root_rotation(joints, skeleton, smooth=smooth_forward, legacy=legacy)
    root = rq if legacy else qinv(rq)
    return locals_from_globals(root, bone_rotations(joints, skeleton), skeleton, legacy)


def global_rotations(local_quats: np.ndarray, skeleton: Skeleton, legacy: bool = False) -> np.ndarray:
    """Accumulate ``G[c] = G[frame(c)] * L[c]`` level by level (vectorized within a level)."""
    plan = _plan(skeleton, legacy)
    q = np.asarray(local_quats, dtype=np.float64)
    g = q.copy()
    for level in plan.levels:
        g[..., level, :] = qmul(g[..., plan.frame[level], :], q[..., level, :])
    return g


def forward_kinematics(local_quats: np.ndarray, root_translation: np.ndarray, offsets: np.ndarray,
                       skeleton: Skeleton, legacy: bool = False) -> np.ndarray:
    """HumanML3D ``Skeleton.forward_kinematics_np``: ``(..., J, 4)`` locals + root -> ``(..., J, 3)``.

    Bone ``c`` is ``qrot(G[c], offsets[c])``; positions are the root plus the sum of the bones
    on the path from the root (one matrix product instead of a walk down each chain).
    """
    g = global_rotations(local_quats, skeleton, legacy)
    bones = qrot(g[..., 1:, :], np.asarray(offsets, dtype=np.float64)[1:])
    root = np.asarray(root_translation, dtype=np.float64)[..., None, :]
    return root + _plan(skeleton, legacy).ancestors @ bones


def uniform_skeleton(positions: np.ndarray, skeleton: Skeleton, target_offsets: np.ndarray,
                     source_offsets: np.ndarray | None = None) -> np.ndarray:
    """HumanML3D ``uniform_skeleton``: IK (unsmoothed), then FK with ``target_offsets``.

    FK(IK(x)) rebuilds each bone as ``qrot(G[c], target_offsets[c])`` whatever the root
    rotation and parent frames (they cancel), so that is computed directly; the root
    trajectory is scaled by the leg-length ratio target/source as in the official code.
    The equality with the explicit IK -> FK round trip is checked in tests/test_features.py.
    """
    x = np.asarray(positions, dtype=np.float64)
    tgt = np.asarray(target_offsets, dtype=np.float64)
    src = skeleton_offsets(x[0], skeleton) if source_offsets is None else source_offsets
    scale = leg_length(tgt, skeleton) / leg_length(src, skeleton)
    bones = qrot(bone_rotations(x, skeleton), tgt[1:])
    return scale * x[:, None, 0] + _plan(skeleton, False).ancestors @ bones


# --------------------------------------------------------------------------- errors between joint trajectories

def mpjpe(pred: np.ndarray, gt: np.ndarray, root_relative: bool = True) -> np.ndarray:
    """``(T,)`` per-frame mean per-joint position error in mm of ``(T, J, 3)`` joints in metres.

    ``root_relative``: both skeletons are moved to their own root first (the MoMask/HumanML3D
    convention), which ignores drift of the integrated root trajectory.
    """
    p, g = np.asarray(pred, np.float64), np.asarray(gt, np.float64)
    if root_relative:
        p, g = p - p[:, :1], g - g[:, :1]
    return np.linalg.norm(p - g, axis=-1).mean(-1) * 1000.0


def velocity_error(pred: np.ndarray, gt: np.ndarray) -> np.ndarray:
    """``(T - 1,)`` per-frame mean norm of the difference of first differences (mm/frame) of
    ``(T, J, 3)`` joints in metres; pass ``x[:, :1]`` for the root alone."""
    p, g = np.asarray(pred, np.float64), np.asarray(gt, np.float64)
    return np.linalg.norm(np.diff(p, axis=0) - np.diff(g, axis=0), axis=-1).mean(-1) * 1000.0


def acceleration_error(pred: np.ndarray, gt: np.ndarray) -> np.ndarray:
    """``(T - 2,)`` per-frame mean norm of the difference of second differences (mm/frame^2) of
    ``(T, J, 3)`` joints in metres, as in HMR-style video work: it measures jitter the position
    error averages away."""
    p, g = np.asarray(pred, np.float64), np.asarray(gt, np.float64)
    ap = p[2:] - 2 * p[1:-1] + p[:-2]
    ag = g[2:] - 2 * g[1:-1] + g[:-2]
    return np.linalg.norm(ap - ag, axis=-1).mean(-1) * 1000.0
