"""Retargeting the dataset onto the humanoid: rest geometry and inverse kinematics.

Rest geometry (:func:`rest_geometry`, used by the MJCF builder): bone lengths from the dataset's
uniform skeleton; directions from the T-pose, except at branching joints (hips, chest), where the
children keep the mocap's own sibling geometry (a generalised Procrustes mean over sampled frames),
and at the ankles, whose toe bones are pitched down to the median stance angle so the sole is flat
at rest.

Inverse kinematics (:func:`solve_locals`): the dataset stores HumanML3D per-bone rotations
(siblings rotate independently, no twist), which a body tree cannot use, so per-joint rotations
are re-derived from the canonical joint positions, top-down, in the spirit of
``motok.data.export.bvh_pose`` but against the humanoid's *fixed* rest geometry:

* branching joints (root, chest): Kabsch fit of the children's rest offsets onto their bones;
* limb roots (hip, shoulder), whose child is a one-hinge knee or elbow: the bone direction is
  matched exactly and the hinge axis is turned onto the normal of the limb's bend plane, so the
  knee can reproduce the foot with its single hinge (a plain swing would leave the bend plane
  wherever the twist-free swing puts it). Near a straight limb the normal is undefined; it is
  blended with the swing solution's axis, which keeps the twist continuous;
* hinges: the signed angle between rest and target child bone about the hinge axis;
* other single-child joints: the shortest-arc swing relative to the parent (no twist, smooth).

:func:`clip_qpos` resamples to the control rate (default 30 Hz) by slerping the local rotations and
interpolating the root position linearly (``motok.features.resample``), then reads the hinge
angles off as intrinsic Euler angles (:func:`locals_to_angles`).
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np

from motok.features.resample import resample_positions, resample_quats
from motok.rotations import kabsch, matrix_to_quat, qbetween, qfix, qinv, qmul, qrot, quat_to_euler
from motok.sim.humanoid import Humanoid, Layout, to_mj
from motok.skeleton import Skeleton

BEND_BLEND = 0.02  # |thigh x shin| (sine of the bend) below which the swing axis takes over


def rest_geometry(joints: np.ndarray, skeleton: Skeleton, offsets: np.ndarray) -> tuple[np.ndarray, dict]:
    """Rest offsets ``(J,3)`` in dataset coordinates and foot measurements, from sampled frames."""
    parents = skeleton.parents
    lengths = np.linalg.norm(offsets, axis=-1)
    rest = skeleton.directions * lengths[:, None]
    bones = joints - joints[:, np.maximum(parents, 0)]
    for j in range(skeleton.num_joints):
        kids = np.flatnonzero(parents == j)
        if len(kids) < 2:
            continue
        template = rest[kids]
        for _ in range(3):  # generalised Procrustes: align every frame to the mean, re-average
            r = kabsch(template, bones[:, kids])
            mean = np.einsum("fkj,fji->fki", bones[:, kids], r).mean(0)
            mean *= (lengths[kids] / np.linalg.norm(mean, axis=-1))[:, None]
            fit = kabsch(rest[kids], mean[None])[0]  # express it in the best-fit T-pose frame
            template = mean @ fit
        rest[kids] = template
    ankles = [skeleton.feet_left[0], skeleton.feet_right[0]]
    toes = [skeleton.feet_left[1], skeleton.feet_right[1]]
    a_y, t_y = joints[:, ankles, 1].ravel(), joints[:, toes, 1].ravel()
    # Stance: both the toe and the ankle near their lowest; the foot's pitch there is its flat pose.
    stance = (t_y < np.quantile(t_y, 0.3) + 0.01) & (a_y < np.quantile(a_y, 0.3) + 0.01)
    if stance.sum() < 10:
        stance = np.ones_like(t_y, dtype=bool)
    toe_len = np.tile(lengths[toes], len(joints))
    pitch = float(np.median(np.arcsin(np.clip((a_y - t_y)[stance] / toe_len[stance], -1, 1))))
    up = np.array([0.0, 1.0, 0.0])
    for t in toes:
        h = rest[t] - up * rest[t][1]
        h /= np.linalg.norm(h)
        rest[t] = lengths[t] * (np.cos(pitch) * h - np.sin(pitch) * up)
    foot = {"pitch": pitch, "ankle_height": float(np.median(a_y[stance])), "toe_height": float(np.median(t_y[stance]))}
    return rest, foot


def _unit(v: np.ndarray) -> np.ndarray:
    return v / np.maximum(np.linalg.norm(v, axis=-1, keepdims=True), 1e-12)


def _axis_angle(axis: np.ndarray, angle: np.ndarray) -> np.ndarray:
    h = 0.5 * np.asarray(angle)[..., None]
    return np.concatenate([np.cos(h), np.sin(h) * axis], -1)


def _frame(u: np.ndarray, n: np.ndarray) -> np.ndarray:
    """Orthonormal frames ``(..., 3, 3)`` with columns ``u``, ``n`` made orthogonal to ``u``, ``u x n``."""
    e1 = _unit(u)
    e2 = _unit(n - (n * e1).sum(-1, keepdims=True) * e1)
    return np.stack([e1, e2, np.cross(e1, e2)], -1)


def solve_locals(x: np.ndarray, layout: Layout) -> np.ndarray:
    """Joint positions ``(T, J, 3)`` (MuJoCo coordinates) -> local rotations ``(T, J, 4)``.

    Slot 0 holds the root's global rotation; a leaf's slot is the identity.
    """
    x = np.asarray(x, dtype=np.float64)
    T, J = x.shape[:2]
    par, rest, kids = layout.parents, layout.rest, layout.children
    bone = x - x[:, np.maximum(par, 0)]
    glob = np.zeros((T, J, 4))
    glob[..., 0] = 1.0
    for j in range(J):  # parents precede children (a Skeleton invariant)
        gp = glob[:, par[j]] if j > 0 else glob[:, 0].copy()
        ks, kind = kids[j], layout.kinds[j]
        if kind == "fixed":
            glob[:, j] = gp
        elif len(ks) > 1:
            glob[:, j] = matrix_to_quat(kabsch(rest[ks], bone[:, ks]))
        elif kind == "hinge":
            a, c = layout.axis_vectors(j)[0], ks[0]
            t = qrot(qinv(gp), bone[:, c])
            t, r = t - (t @ a)[:, None] * a, rest[c] - (rest[c] @ a) * a
            theta = np.arctan2(np.cross(r, t) @ a, t @ r)
            glob[:, j] = qmul(gp, _axis_angle(a, theta))
        else:
            c = ks[0]
            swing = qmul(gp, qbetween(np.broadcast_to(rest[c], (T, 3)), qrot(qinv(gp), bone[:, c])))
            if layout.kinds[c] == "hinge" and kids[c]:
                a = layout.axis_vectors(c)[0]
                u_t, w = _unit(bone[:, c]), _unit(bone[:, kids[c][0]])
                bend = np.cross(u_t, w)
                n = bend + BEND_BLEND * qrot(swing, np.broadcast_to(a, (T, 3)))
                m = _frame(u_t, n) @ _frame(rest[c], a).T
                glob[:, j] = matrix_to_quat(m)
            else:
                glob[:, j] = swing
    local = glob.copy()
    local[:, 1:] = qmul(qinv(glob[:, par[1:]]), glob[:, 1:])
    return qfix(local)


def locals_to_angles(local: np.ndarray, layout: Layout) -> np.ndarray:
    """Local rotations ``(T, J, 4)`` -> hinge angles ``(T, H)`` in ``layout.hinge_names`` order.

    A ball joint's three hinges compose as intrinsic Euler angles in their listed order, which is
    exactly how MuJoCo chains several hinges in one body. Angles are unwrapped along time.
    """
    cols = []
    for j, kind in enumerate(layout.kinds):
        if kind == "ball":
            order = "".join(a.upper() for a in layout.axes[j])
            cols.append(quat_to_euler(local[:, j], order, degrees=False))
        elif kind == "hinge":
            a = layout.axis_vectors(j)[0]
            q = local[:, j]
            cols.append((2 * np.arctan2(q[:, 1:] @ a, q[:, 0]))[:, None])
    ang = np.concatenate(cols, -1) if cols else np.zeros((len(local), 0))
    return np.unwrap(ang, axis=0)


class Pose(NamedTuple):
    root_pos: np.ndarray
    root_quat: np.ndarray
    angles: np.ndarray
    local: np.ndarray


def solve_pose(x: np.ndarray, layout: Layout) -> Pose:
    local = solve_locals(x, layout)
    return Pose(np.asarray(x[:, 0], dtype=np.float64), local[:, 0], locals_to_angles(local, layout), local)


def clip_qpos(joints_data: np.ndarray, hum: Humanoid, src_fps: float, dst_fps: float) -> np.ndarray:
    """A clip's canonical joints (dataset coordinates) -> qpos ``(T', nq)`` at ``dst_fps``."""
    layout = hum.layout
    local = solve_locals(to_mj(joints_data), layout)
    root = to_mj(np.asarray(joints_data, dtype=np.float64)[:, 0])
    if src_fps != dst_fps:
        local = resample_quats(local, src_fps, dst_fps)
        root = resample_positions(root, src_fps, dst_fps)
    qpos = np.zeros((len(local), hum.model.nq))
    qpos[:, :3], qpos[:, 3:7] = root, local[:, 0]
    qpos[:, hum.hinge_qpos_adr] = locals_to_angles(local, layout)
    return qpos

