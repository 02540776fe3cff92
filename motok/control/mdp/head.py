"""Head-mounted-device tracking terms (hybrid-latent paper, appendix C.2): only the head of the
reference is known, as a VR headset would report it.

* :func:`head_goal`: for each of the next ``K`` reference frames (``t + 1 .. t + K``, the fork's
  ``numNextObsSteps: 5``), the head's position, rotation (6D), linear and angular velocity
  differences reference - simulation in the heading frame of the **root** (Eq. 9's terms for one
  body, ``observations.imitation_goal``: the rotation difference conjugated into the heading frame
  and the angular velocity rotated, where the fork left-multiplies the rotation and leaves the
  angular velocity in the world frame);
* :func:`head_errors` / :func:`head_reward`: the fork's ``simple_track`` reward, PHC's form on the
  head alone, ``0.5 exp(-100 |dp|^2) + 0.3 exp(-10 theta^2) + 0.1 exp(-0.1 |dv|^2) + 0.1 exp(-0.1 |dw|^2)``
  with ``theta`` the angle between the simulated and reference head rotations;
* termination: the head farther than a distance from the reference head
  (``terminations.tracking_failure`` on the head's distance). The paper says 1 m; the fork's
  recipe (``LafanTracking.yaml``: ``track_dist_1.5``) uses 1.5 m.
"""

from __future__ import annotations

from dataclasses import dataclass

from motok.arrays import xp
from motok.control.mdp.observations import imitation_goal
from motok.control.mdp.rewards import check_non_negative
from motok.control.mdp.terminations import tracking_failure
from motok.ranges import In
from motok.sim.obs import Bodies, cross3

HEAD_FEATURES = 15  # position (3), rotation 6D (6), velocity (3), angular velocity (3)


def _bodies(b: Bodies, idx: list[int]) -> Bodies:
    """The bodies ``idx`` of ``b`` (the body axis is the second to last)."""
    return Bodies(b.pos[..., idx, :], b.vel[..., idx, :], b.angvel[..., idx, :], quat=b.quat[..., idx, :])


def head_goal(sim: Bodies, ref: Bodies, head: int):
    """``(N, K * 15)`` from sim bodies ``(N, J, .)`` and reference bodies ``(N, K, J, .)``."""
    N, K = ref.pos.shape[:2]
    # imitation_goal takes the heading from its first body: pass the root along, drop its columns.
    g = imitation_goal(_bodies(sim, [0, head]), _bodies(ref, [0, head]))
    return g.reshape(N, K, 2, HEAD_FEATURES)[:, :, 1].reshape(N, K * HEAD_FEATURES)


def rotation_angle(q, q_ref):
    """Angle (rad, in [0, pi]) of the rotation between unit quaternions ``(..., 4)`` (numpy or torch)."""
    x = xp(q)
    w = x.abs((q * q_ref).sum(-1))
    v = q[..., :1] * q_ref[..., 1:] - q_ref[..., :1] * q[..., 1:] - cross3(q_ref[..., 1:], q[..., 1:])
    return 2.0 * x.arctan2(x.sqrt((v * v).sum(-1)), w)  # atan2 keeps small angles accurate


@dataclass
class HeadRewardConfig:
    """Weights and exponents of the head reward (the fork's ``compute_phc_reward`` on the head)."""

    w_pos: In[float, ">= 0"] = 0.5  # weight of exp(-k_pos e_pos)
    k_pos: In[float, ">= 0"] = 100.0  # exponent on e_pos, the the head's position error (m^2)
    w_rot: In[float, ">= 0"] = 0.3  # weight of exp(-k_rot e_rot)
    k_rot: In[float, ">= 0"] = 10.0  # exponent on e_rot, the the angle between head rotations (rad^2)
    w_vel: In[float, ">= 0"] = 0.1  # weight of exp(-k_vel e_vel)
    k_vel: In[float, ">= 0"] = 0.1  # exponent on e_vel, the the head's velocity error ((m/s)^2)
    w_angvel: In[float, ">= 0"] = 0.1  # weight of exp(-k_angvel e_angvel)
    k_angvel: In[float, ">= 0"] = 0.1  # exponent on e_angvel, the the head's angular velocity error ((rad/s)^2)

    def __post_init__(self):
        check_non_negative(self, "hmd reward")


def head_errors(sim: Bodies, ref: Bodies, head: int) -> dict:
    """Squared errors ``(N,)`` of the head: position (m^2), rotation angle (rad^2), linear and
    angular velocity, from sim and reference bodies ``(N, J, .)``."""
    sq = lambda a, b: ((a[:, head] - b[:, head]) ** 2).sum(-1)  # noqa: E731
    return {"pos": sq(sim.pos, ref.pos), "rot": rotation_angle(sim.quat[:, head], ref.quat[:, head]) ** 2,
            "vel": sq(sim.vel, ref.vel), "angvel": sq(sim.angvel, ref.angvel)}


def head_reward(err: dict, cfg: HeadRewardConfig) -> dict:
    """``r_task = sum_k w_k exp(-k_k e_k)`` and its terms ``r_pos``, ``r_rot``, ``r_vel``, ``r_angvel``."""
    keys = ("pos", "rot", "vel", "angvel")
    x = xp(err["pos"])
    r = {f"r_{k}": x.exp(-getattr(cfg, f"k_{k}") * err[k]) for k in keys}
    r["r_task"] = sum(getattr(cfg, f"w_{k}") * r[f"r_{k}"] for k in keys)
    return r


def head_distance(sim_pos, ref_pos, head: int):
    """``(N,)`` distance (m) of the simulated head to the reference head."""
    d = sim_pos[:, head] - ref_pos[:, head]
    return xp(d).sqrt((d * d).sum(-1))


def head_lost(dist, threshold: float):
    """The HMD termination: the head more than ``threshold`` m from the reference head."""
    return tracking_failure(dist[:, None], "any", threshold)
