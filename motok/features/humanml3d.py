"""The HumanML3D motion representation, generalized to any skeleton of J joints (12J - 1 dims).

Per frame: root rotation velocity (1), root xz velocity in the root frame (2), root height (1),
root-relative joint positions in the root frame (3(J-1)), continuous 6D local rotations
(6(J-1)), joint velocities in the root frame (3J), foot contacts (4). ``extract_features``
follows HumanML3D's ``process_file`` step by step; ``legacy=True`` reproduces the official
numbers, the default fixes its inconsistencies (docs/features.md lists each one).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from motok.features.kinematics import (
    bone_rotations, forward_direction, forward_kinematics, inverse_kinematics, leg_length,
    locals_from_globals, root_quat, root_rotation, skeleton_offsets, uniform_skeleton,
)
from motok.features.resample import resample_positions, resample_quats
from motok.rotations import cont6d_to_matrix, matrix_to_quat, qinv, qmul, qrot, quat_to_cont6d, quat_to_matrix
from motok.skeleton import Skeleton

try:
    import torch
except ImportError:  # pragma: no cover
    torch = None

__all__ = [
    "FeatureResult", "extract_features", "skeleton_offsets", "recover_from_ric", "recover_root",
    "recover_local_quats", "forward_kinematics", "inverse_kinematics", "feature_slices", "mean_std",
    "contact_threshold", "resample_positions", "resample_quats", "SMPL_LEG_LENGTH", "STD_EPS",
]

# Thigh + shin (m) of HumanML3D's target skeleton (clip 000021, the skeleton every HumanML3D clip
# is retargeted to), measured on the golden clip new_joints_012314.npy: 0.390188 + 0.425643.
SMPL_LEG_LENGTH = 0.815831
# A feature block whose averaged std is below this is constant in the data; its std becomes 1
# so that normalizing gives 0 instead of inf/NaN.
STD_EPS = 1e-6
NUM_CONTACTS = 4


@dataclass
class FeatureResult:
    """What ``extract_features`` returns; ``local_quats`` use the default convention even with
    ``legacy=True``, so ``forward_kinematics(local_quats, root_translation, offsets, skeleton) == joints``."""

    features: np.ndarray  # (T-1, 12J-1) float32
    joints: np.ndarray  # (T-1, J, 3) canonical global positions (HumanML3D's global_positions[:-1])
    local_quats: np.ndarray  # (T-1, J, 4) local rotations, default convention
    root_translation: np.ndarray  # (T-1, 3) == joints[:, 0]
    offsets: np.ndarray  # (J, 3) target skeleton offsets used (directions * bone lengths)


def feature_slices(num_joints: int) -> dict[str, slice]:
    """The blocks of a feature vector, in order; they end at ``12J - 1``."""
    sizes = [("root_rot_velocity", 1), ("root_linear_velocity", 2), ("root_y", 1),
             ("ric", 3 * (num_joints - 1)), ("rot", 6 * (num_joints - 1)),
             ("local_velocity", 3 * num_joints), ("foot_contact", NUM_CONTACTS)]
    out, start = {}, 0
    for name, n in sizes:
        out[name] = slice(start, start + n)
        start += n
    return out


def contact_threshold(skeleton: Skeleton, fps: float, leg_length: float | None = None) -> float:
    """Squared per-frame foot displacement (m^2) under which a foot is in contact.

    ``skeleton.contact_threshold`` holds HumanML3D's 0.002 m^2, meant for 20 fps and an
    SMPL-sized leg. A per-frame displacement scales with 1/fps and with body size, so its
    square scales by ``(20 / fps)^2 * (leg_length / SMPL_LEG_LENGTH)^2`` (no size scaling when
    ``leg_length`` is None).
    """
    scale = (20.0 / float(fps)) ** 2
    if leg_length is not None:
        scale *= (float(leg_length) / SMPL_LEG_LENGTH) ** 2
    return float(skeleton.contact_threshold) * scale


def _rotate(m: np.ndarray, v: np.ndarray) -> np.ndarray:
    """Apply rotation matrices ``m (..., 3, 3)`` to row vectors ``v (..., N, 3)``."""
    return v @ np.swapaxes(m, -1, -2)


def _foot_contacts(x: np.ndarray, skeleton: Skeleton, threshold: float) -> np.ndarray:
    """HumanML3D ``foot_detect``: squared displacement to the next frame below the threshold."""
    feet = list(skeleton.feet_left) + list(skeleton.feet_right)
    if len(feet) != NUM_CONTACTS:
        raise ValueError(f"skeleton {skeleton.name!r} has {len(feet)} foot joints; the representation "
                         f"needs exactly {NUM_CONTACTS} (two per side)")
    d = x[1:, feet] - x[:-1, feet]
    return ((d * d).sum(-1) < threshold).astype(np.float64)


def extract_features(positions, skeleton: Skeleton, *, target_offsets=None, fps: float = 20.0,
                     legacy: bool = False) -> FeatureResult:
    """HumanML3D ``process_file``: positions ``(T, J, 3)`` (metres, Y up) -> features ``(T-1, 12J-1)``.

    ``target_offsets`` (J, 3) is the skeleton every clip is retargeted to (HumanML3D: clip
    000021's); None keeps the clip's own frame-0 bone lengths. ``fps`` only scales the contact
    threshold: resample first (``resample_positions``) to change the frame rate. ``legacy``
    reproduces the official quirks; the default's departures are listed in docs/features.md.
    """
    x = np.asarray(positions, dtype=np.float64)
    J = skeleton.num_joints
    if x.ndim != 3 or x.shape[1:] != (J, 3):
        raise ValueError(f"positions must be (T, {J}, 3) for skeleton {skeleton.name!r}, got {x.shape}")
    if len(x) < 2:
        raise ValueError("need at least 2 frames: features are per frame transition")

    # Uniform skeleton: retarget bone lengths, scale the root path by the leg-length ratio.
    src = skeleton_offsets(x[0], skeleton)
    tgt = src if target_offsets is None else np.asarray(target_offsets, dtype=np.float64)
    if tgt.shape != (J, 3):
        raise ValueError(f"target_offsets must be ({J}, 3), got {tgt.shape}")
    x = uniform_skeleton(x, skeleton, tgt, src)

    # Put on floor; root xz at the origin at frame 0.
    x[..., 1] -= x[..., 1].min()
    x -= x[0, 0] * np.array([1.0, 0.0, 1.0])

    # Face +Z at frame 0, then the per-frame root rotation r_rot (smoothed forward -> +Z).
    if legacy:
        # Official: facing from frame 0's own forward (correct face order), r_rot from the IK's
        # smoothed forward with the swapped hip term.
        face = quat_to_matrix(root_quat(forward_direction(x[:1], skeleton, smooth=False)[0]))
        x = _rotate(face, x)
        r_rot = root_rotation(x, skeleton, smooth=True, legacy=True)
    else:
        # Default: face +Z by the *smoothed* frame-0 forward, the one the features encode, so that
        # r_rot[0] is the identity and recover_from_ric gives back exactly these positions.
        fwd = forward_direction(x, skeleton, smooth=True)
        face = quat_to_matrix(root_quat(fwd[0]))
        x = _rotate(face, x)
        r_rot = root_quat(_rotate(face, fwd))

    thr = contact_threshold(skeleton, fps, leg_length(tgt, skeleton))
    contacts = _foot_contacts(x, skeleton, thr)

    # Rotation IK on the canonical positions (same bones in both conventions, different frames).
    g = bone_rotations(x, skeleton)
    # Default root = the heading inv(r_rot), so a root child's local is its bone in the facing frame.
    local_default = locals_from_globals(qinv(r_rot), g, skeleton, legacy=False)
    local_feat = locals_from_globals(r_rot, g, skeleton, legacy=True) if legacy else local_default

    # Root: rotation velocity (half-angle: arcsin of the y component), xz velocity, height.
    r_vel = qmul(r_rot[1:], qinv(r_rot[:-1]))
    rot_vel = np.arcsin(np.clip(r_vel[:, 2], -1.0, 1.0))
    # The step t -> t+1 goes into frame t+1's root frame (official; recover_root undoes exactly that).
    lin_vel = qrot(r_rot[1:], x[1:, 0] - x[:-1, 0])[:, [0, 2]]
    root_y = x[:-1, 0, 1]

    m = quat_to_matrix(r_rot)
    ric = _rotate(m[:-1], x[:-1, 1:] - x[:-1, :1] * np.array([1.0, 0.0, 1.0]))
    rot6d = quat_to_cont6d(local_feat[:-1, 1:])
    vel = _rotate(m[:-1], x[1:] - x[:-1])

    n = len(x) - 1
    features = np.concatenate([
        rot_vel[:, None], lin_vel, root_y[:, None], ric.reshape(n, -1), rot6d.reshape(n, -1),
        vel.reshape(n, -1), contacts], -1)
    return FeatureResult(
        features=features.astype(np.float32),
        joints=x[:-1].astype(np.float32),
        local_quats=local_default[:-1].astype(np.float32),
        root_translation=x[:-1, 0].astype(np.float32),
        offsets=tgt.astype(np.float32),
    )


def _is_torch(a) -> bool:
    return torch is not None and isinstance(a, torch.Tensor)


def _out_dtype(features) -> np.dtype:
    dt = np.asarray(features).dtype
    return dt if np.issubdtype(dt, np.floating) else np.dtype(np.float64)


def _root_path(f):
    """``recover_root_rot_pos`` on a float64 array or a tensor (kept in its dtype and device)."""
    xp = torch if _is_torch(f) else np
    zeros_like, cumsum, cos, sin, stack = xp.zeros_like, xp.cumsum, xp.cos, xp.sin, xp.stack
    cat = torch.cat if xp is torch else np.concatenate
    rv = f[..., 0]
    ang = cumsum(cat([zeros_like(rv[..., :1]), rv[..., :-1]], -1), -1)
    z = zeros_like(ang)
    quat = stack([cos(ang), z, sin(ang), z], -1)
    step = zeros_like(f[..., :3])
    step[..., 1:, 0] = f[..., :-1, 1]
    step[..., 1:, 2] = f[..., :-1, 2]
    pos = cumsum(qrot(qinv(quat), step), -2)
    pos[..., 1] = f[..., 3]
    return quat, pos


def recover_root(features):
    """HumanML3D ``recover_root_rot_pos``: ``(..., T, D)`` -> root quat ``(..., T, 4)``, position ``(..., T, 3)``.

    The rotation velocity is a half angle, so ``(cos a, 0, sin a, 0)`` with ``a`` its running
    sum is the yaw ``r_rot`` relative to frame 0; the xz velocity, stored in the frame of the
    next frame's root, is turned back to the world and summed. numpy or torch in, same type out.
    """
    if _is_torch(features):
        return _root_path(features)
    quat, pos = _root_path(np.asarray(features, dtype=np.float64))
    dt = _out_dtype(features)
    return quat.astype(dt), pos.astype(dt)


def recover_from_ric(features, num_joints: int):
    """HumanML3D ``recover_from_ric``: features ``(..., T, D)`` -> positions ``(..., T, J, 3)``.

    Undo the root rotation on the root-relative positions and add the root xz path.
    """
    f = features if _is_torch(features) else np.asarray(features, dtype=np.float64)
    quat, pos = _root_path(f)
    ric = f[..., 4:4 + 3 * (num_joints - 1)]
    ric = ric.reshape(tuple(ric.shape[:-1]) + (num_joints - 1, 3))
    q = qinv(quat)[..., None, :]
    if _is_torch(f):
        xz = torch.zeros_like(pos)
        xz[..., [0, 2]] = pos[..., [0, 2]]
        return torch.cat([pos[..., None, :], qrot(q.expand(tuple(ric.shape[:-1]) + (4,)), ric) + xz[..., None, :]], -2)
    out = qrot(q, ric) + (pos * np.array([1.0, 0.0, 1.0]))[..., None, :]
    return np.concatenate([pos[..., None, :], out], -2).astype(_out_dtype(features))


def recover_local_quats(features, skeleton: Skeleton, legacy: bool = False) -> np.ndarray:
    """The rotation path (HumanML3D ``recover_from_rot``): 6D block + root yaw -> locals ``(..., T, J, 4)``.

    ``forward_kinematics(result, recover_root(features)[1], offsets, skeleton, legacy)`` gives the
    positions. Default: the root is the heading ``inv(r_rot)`` and the positions equal
    ``recover_from_ric``. ``legacy``: the root is ``r_rot`` as in the official recover_from_rot;
    this matches recover_from_ric because the legacy IK forces r_rot[0] to the identity.
    """
    f = features.detach().cpu().numpy() if _is_torch(features) else np.asarray(features)
    f = f.astype(np.float64)
    J = skeleton.num_joints
    d6 = f[..., feature_slices(J)["rot"]].reshape(f.shape[:-1] + (J - 1, 6))
    local = matrix_to_quat(cont6d_to_matrix(d6))
    quat, _ = _root_path(f)
    root = quat if legacy else qinv(quat)
    return np.concatenate([root[..., None, :], local], -2)


def mean_std(features, num_joints: int) -> tuple[np.ndarray, np.ndarray]:
    """HumanML3D ``cal_mean_variance``: per-dimension mean, std averaged within each block.

    ``features``: an array ``(..., D)`` or a list of ``(T_i, D)`` arrays (concatenated over time).
    A block whose averaged std is below ``STD_EPS`` gets std 1 (constant data normalizes to 0).
    """
    if isinstance(features, (list, tuple)):
        data = np.concatenate([np.asarray(a, dtype=np.float64) for a in features], 0)
    else:
        data = np.asarray(features, dtype=np.float64)
    D = 12 * num_joints - 1
    data = data.reshape(-1, data.shape[-1])
    if data.shape[-1] != D:
        raise ValueError(f"features of {num_joints} joints have {D} dims, got {data.shape[-1]}")
    mean = data.mean(0)
    std = data.std(0)
    for sl in feature_slices(num_joints).values():
        s = std[sl].mean()
        std[sl] = s if s >= STD_EPS else 1.0
    return mean.astype(np.float32), std.astype(np.float32)
