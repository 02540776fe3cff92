"""Body states, forward kinematics and the proprioceptive observation, vectorized over environments.

Everything here works on ``(N, ...)`` arrays, with no MuJoCo calls, so the same code serves one
environment or thousands. The observation terms take numpy arrays or torch tensors
(:mod:`motok.arrays`): on a MuJoCo Warp rollout they run on the device that holds the state.

The heading frame is the yaw of the root's forward axis (MuJoCo +X at rest): quantities are
rotated by its inverse so that the policy sees the same numbers wherever the character stands
and whichever way it faces (tests/test_sim.py checks it).

* Observation s, hybrid-latent paper Eq. 7: root height, root orientation (6D, heading
  frame), root linear and angular velocity (heading frame), hinge positions and velocities,
  end-effector positions relative to the root (heading frame).

Goals (Eq. 9 and the tasks'), rewards and terminations are control terms: ``motok.control.mdp``.
"""

from __future__ import annotations

import numpy as np

from motok.arrays import xp
from motok.rotations import matrix_to_quat, quat_to_matrix


class Bodies:
    """World-frame body states ``(N, ..., J, .)`` in skeleton order: positions, orientations,
    linear velocities at the body origins and angular velocities. Orientations are held as
    rotation matrices (body to world) and/or unit quaternions (w, x, y, z); either is derived
    from the other on first use, so each producer gives what it has for free."""

    def __init__(self, pos, vel, angvel, rot=None, quat=None):
        self.pos, self.vel, self.angvel, self._rot, self._quat = pos, vel, angvel, rot, quat

    @property
    def rot(self) -> np.ndarray:
        if self._rot is None:
            self._rot = quat_to_matrix(self._quat)
        return self._rot

    @property
    def quat(self) -> np.ndarray:
        if self._quat is None:
            self._quat = matrix_to_quat(self._rot)
        return self._quat

    def take(self, ids) -> "Bodies":
        return Bodies(self.pos[ids], self.vel[ids], self.angvel[ids], None if self._rot is None else self._rot[ids],
                      None if self._quat is None else self._quat[ids])

    def put(self, ids, other: "Bodies") -> None:
        """Overwrite the rows ``ids`` with ``other``'s (both forms kept consistent)."""
        self.pos[ids], self.vel[ids], self.angvel[ids] = other.pos, other.vel, other.angvel
        if self._rot is not None:
            self._rot[ids] = other.rot
        if self._quat is not None:
            self._quat[ids] = other.quat


def cross3(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    return a[..., [1, 2, 0]] * b[..., [2, 0, 1]] - a[..., [2, 0, 1]] * b[..., [1, 2, 0]]


def _mv(m: np.ndarray, v: np.ndarray) -> np.ndarray:
    return np.matmul(m, v[..., None])[..., 0]


def _skew(a: np.ndarray) -> np.ndarray:
    k = np.zeros(a.shape[:-1] + (3, 3))
    k[..., 0, 1], k[..., 0, 2], k[..., 1, 2] = -a[..., 2], a[..., 1], -a[..., 0]
    return k - np.swapaxes(k, -1, -2)


class TreeKinematics:
    """Forward kinematics of a motok humanoid from qpos/qvel, level by level over the tree.

    Mirrors MuJoCo's ``mj_kinematics`` + ``cvel`` for this model class (free root, 0/1/3 body-axis
    hinges at each body origin, identity body orientations); checked against MuJoCo in the tests.
    Rotation matrices rather than quaternions: one ``matmul`` per composition, so a pass costs a
    few numpy calls per tree level whatever the number of environments.
    """

    def __init__(self, hum):
        lay, m = hum.layout, hum.model
        self.parents, self.rest, self.J = lay.parents, lay.rest, len(lay.names)
        depth = np.zeros(self.J, dtype=int)
        for j in range(1, self.J):
            depth[j] = depth[lay.parents[j]] + 1
        self.levels = [(lv, lay.parents[lv]) for lv in (np.flatnonzero(depth == d) for d in range(1, depth.max() + 1))]
        dof = {int(m.jnt_qposadr[k]): int(m.jnt_dofadr[k]) for k in range(m.njnt)}
        self.ball = np.array([j for j in range(self.J) if lay.kinds[j] == "ball"], dtype=int)
        self.hinge = np.array([j for j in range(self.J) if lay.kinds[j] == "hinge"], dtype=int)
        self.ball_q = np.array([hum.qpos_adr[j] for j in self.ball], dtype=int).reshape(-1, 3)
        self.ball_v = np.array([[dof[int(a)] for a in row] for row in self.ball_q], dtype=int).reshape(-1, 3)
        self.ball_ax = np.array([lay.axis_vectors(j) for j in self.ball]).reshape(-1, 3, 3)
        self.hinge_q = np.array([hum.qpos_adr[j][0] for j in self.hinge], dtype=int)
        self.hinge_v = np.array([dof[int(a)] for a in self.hinge_q], dtype=int)
        self.hinge_ax = np.array([lay.axis_vectors(j)[0] for j in self.hinge]).reshape(-1, 3)
        # Rodrigues: R = I + sin(t) K + (1 - cos(t)) K^2, with K the axis' cross-product matrix.
        self.ball_k = _skew(self.ball_ax)
        self.ball_k2 = self.ball_k @ self.ball_k
        self.hinge_k = _skew(self.hinge_ax)
        self.hinge_k2 = self.hinge_k @ self.hinge_k

    @staticmethod
    def _rodrigues(k, k2, t):
        return np.eye(3) + np.sin(t)[..., None, None] * k + (1.0 - np.cos(t))[..., None, None] * k2

    def __call__(self, qpos: np.ndarray, qvel: np.ndarray) -> Bodies:
        N, J = len(qpos), self.J
        local = np.broadcast_to(np.eye(3), (N, J, 3, 3)).copy()
        wloc = np.zeros((N, J, 3))  # joint angular velocity in the parent body's frame
        if len(self.ball):
            r = self._rodrigues(self.ball_k, self.ball_k2, qpos[:, self.ball_q])  # (N, B, 3, 3, 3)
            r01 = r[:, :, 0] @ r[:, :, 1]
            local[:, self.ball] = r01 @ r[:, :, 2]
            dq = qvel[:, self.ball_v]
            wloc[:, self.ball] = (self.ball_ax[:, 0] * dq[..., :1] + _mv(r[:, :, 0], self.ball_ax[:, 1]) * dq[..., 1:2]
                                  + _mv(r01, self.ball_ax[:, 2]) * dq[..., 2:])
        if len(self.hinge):
            local[:, self.hinge] = self._rodrigues(self.hinge_k, self.hinge_k2, qpos[:, self.hinge_q])
            wloc[:, self.hinge] = self.hinge_ax * qvel[:, self.hinge_v, None]
        pos, rot = np.empty((N, J, 3)), np.empty((N, J, 3, 3))
        vel, ang = np.empty((N, J, 3)), np.empty((N, J, 3))
        q = qpos[:, 3:7] / np.linalg.norm(qpos[:, 3:7], axis=-1, keepdims=True)
        pos[:, 0], rot[:, 0], vel[:, 0] = qpos[:, :3], quat_to_matrix(q), qvel[:, :3]
        ang[:, 0] = _mv(rot[:, 0], qvel[:, 3:6])  # the free joint's angular velocity is in the body frame
        for lv, p in self.levels:
            rp = rot[:, p]
            rot[:, lv] = rp @ local[:, lv]
            pos[:, lv] = pos[:, p] + _mv(rp, self.rest[lv])
            ang[:, lv] = ang[:, p] + _mv(rp, wloc[:, lv])
            vel[:, lv] = vel[:, p] + cross3(ang[:, p], pos[:, lv] - pos[:, p])
        return Bodies(pos, vel, ang, rot=rot)


def heading(root_rot):
    """Cosine and sine of the yaw of the root's forward (+X) axis, ``(...)`` each."""
    fx, fy = root_rot[..., 0, 0], root_rot[..., 1, 0]
    x = xp(root_rot)
    n = x.clip(x.hypot(fx, fy), 1e-9, None)  # the forward axis pointing straight up has no heading
    return fx / n, fy / n


def unyaw(c, s, v):
    """Rotate vectors ``(..., 3)`` by minus the heading: world -> heading frame (elementwise, no matmul)."""
    x, y = v[..., 0], v[..., 1]
    return xp(v).stack([c * x + s * y, c * y - s * x, v[..., 2]], -1)


def observation(qpos, qvel, bodies: Bodies, end_effectors):
    """Eq. 7, ``(N, 1 + 6 + 3 + 3 + 2H + 3E)``, numpy or torch (as the state is given)."""
    N, x = len(qpos), xp(qpos)
    c, s = heading(bodies.rot[:, 0])
    root = bodies.rot[:, 0]
    six = unyaw(c[:, None], s[:, None], x.stack([root[..., 0], root[..., 1]], 1)).reshape(N, 6)
    ee = list(end_effectors)
    vecs = x.concatenate([bodies.vel[:, :1], bodies.angvel[:, :1], bodies.pos[:, ee] - bodies.pos[:, :1]], 1)
    vecs = unyaw(c[:, None], s[:, None], vecs).reshape(N, -1)
    return x.concatenate([bodies.pos[:, 0, 2:3], six, vecs[:, :6], qpos[:, 7:], qvel[:, 6:], vecs[:, 6:]], -1)
