"""Observation terms beyond the environment's Eq. 7 proprioception (``HumanoidEnv.observation``).

* :func:`imitation_goal`, hybrid-latent paper Eq. 9: for each of the next K reference frames and
  every body, the position, rotation (6D), linear-velocity and angular-velocity differences
  reference - simulation in the heading frame. The rotation difference is conjugated into the
  heading frame as PHC does (``H (R_ref R_sim^T) H^T`` with ``H`` the inverse heading); the
  authors' code left-multiplies only, which is not heading-invariant, and does not rotate the
  angular velocity difference: we rotate both.
"""

from __future__ import annotations

from motok.arrays import xp
from motok.sim.obs import Bodies, cross3, heading, unyaw


def imitation_goal(sim: Bodies, ref: Bodies):
    """Eq. 9, ``(N, K * J * 15)`` from sim bodies ``(N, J, .)`` and reference bodies ``(N, K, J, .)``
    (numpy or torch, :mod:`motok.arrays`)."""
    N, K, J = ref.pos.shape[:3]
    a = xp(sim.pos)
    c, s = heading(sim.rot[:, 0])
    c, s = c[:, None, None, None], s[:, None, None, None]
    qs, qr = sim.quat[:, None], ref.quat
    # q_d = q_ref conj(q_sim), the rotation taking sim to ref. Conjugating it by the heading
    # (H R_d H^T, PHC's form) only turns its vector part by minus the heading, done with the rest.
    w = (qr * qs).sum(-1)
    v = qs[..., :1] * qr[..., 1:] - qr[..., :1] * qs[..., 1:] - cross3(qr[..., 1:], qs[..., 1:])
    d = unyaw(c, s, a.stack([ref.pos - sim.pos[:, None], v, ref.vel - sim.vel[:, None],
                              ref.angvel - sim.angvel[:, None]], -2))  # (N, K, J, 4, 3)
    x, y, z = d[..., 1, 0], d[..., 1, 1], d[..., 1, 2]
    six = a.stack([1 - 2 * (y * y + z * z), 2 * (x * y + w * z), 2 * (x * z - w * y),
                    2 * (x * y - w * z), 1 - 2 * (x * x + z * z), 2 * (y * z + w * x)], -1)  # R_d's first two columns
    return a.concatenate([d[..., 0, :], six, d[..., 2, :], d[..., 3, :]], -1).reshape(N, K * J * 15)
