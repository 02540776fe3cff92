"""Reward terms, each ``(N,)`` per environment.

* :func:`imitation_reward`, hybrid-latent paper Eq. 10: a **product**
  ``r_im = r_root r_q r_alpha r_ee`` of ``exp(-k e)`` terms with the paper's exponents
  ``k = (10, 2, 0.5, 40)``, from the errors of :func:`imitation_errors`: ``e_root`` the squared
  root position error (m^2), ``e_q`` the sum over hinges of squared joint angle errors (rad^2,
  DeepMimic's pose term), ``e_alpha`` the mean over hinges of squared joint velocity errors
  ((rad/s)^2; a sum would make ``exp(-0.5 e)`` vanish for any walking policy), ``e_ee`` the sum
  over end effectors of squared root-relative position errors (m^2).
* ``k_feet`` (0 by default: Eq. 10 as the paper writes it) multiplies in ``exp(-k_feet e_feet)``,
  ``e_feet`` the mean over the foot bodies (ankles and toes) of their squared linear velocity error
  ((m/s)^2): a planted reference foot then asks the simulated one to hold still, which the
  position terms barely see (a foot sliding 20 cm/s is 7 mm off after one control step).
* :func:`action_rate`, an optional smoothness term (not in the paper): ``e_rate`` the mean over
  action dimensions of ``(a_t - a_(t-1))^2``, the change of the policy's action between control
  steps, as legged-robot RL penalises it (legged_gym's and Isaac Lab's ``action_rate``, which sum
  over joints; the mean keeps one weight meaningful for any number of joints). The expert *adds*
  ``w_action_rate r_action_rate``, ``r_action_rate = -e_rate``, to its reward (``ExpertConfig``):
  a factor in the product would make every jerk cost the whole imitation reward, which is what
  slowed learning under ``k_feet`` (docs/sim.md "Feet"). An episode's first action has no
  predecessor in that episode and costs nothing.
* The style reward (Eq. 11) is a learned term: ``motok.control.rl.amp``.
"""

from __future__ import annotations

from dataclasses import dataclass

from motok.arrays import xp
from motok.errors import UserError
from motok.ranges import In


def check_non_negative(cfg, label: str) -> None:
    """Every field of a reward config (weights, exponents) must be >= 0: one-line error naming it."""
    for name, v in vars(cfg).items():
        if not v >= 0:
            raise UserError(f"{label}: {name} must be >= 0, got {v}")


@dataclass
class ImitationConfig:
    k_root: In[float, ">= 0"] = 10.0  # Eq. 10's factor exp(-k_root e_root), e_root the root position error (m^2)
    k_q: In[float, ">= 0"] = 2.0  # exp(-k_q e_q), e_q the hinge angle error (rad^2)
    k_alpha: In[float, ">= 0"] = 0.5  # exp(-k_alpha e_alpha), e_alpha the mean squared hinge velocity error ((rad/s)^2)
    k_ee: In[float, ">= 0"] = 40.0  # exp(-k_ee e_ee), e_ee the root-relative end-effector position error (m^2)
    # exp(-k_feet e_feet), e_feet the feet's velocity error ((m/s)^2); 0 leaves it out (Eq. 10)
    k_feet: In[float, ">= 0"] = 0.0


def imitation_errors(pos, ref_pos, q, q_ref, qd, qd_ref, ee) -> dict:
    """Squared errors ``(N,)`` of body positions ``(N, J, 3)`` (root = body 0), hinge angles and
    velocities ``(N, H)`` and end effectors ``ee`` (body indices, root-relative); numpy or torch."""
    ee = list(ee)
    rel, rel_ref = pos[:, ee] - pos[:, :1], ref_pos[:, ee] - ref_pos[:, :1]
    return {"root": ((pos[:, 0] - ref_pos[:, 0]) ** 2).sum(-1), "q": ((q - q_ref) ** 2).sum(-1),
            "alpha": ((qd - qd_ref) ** 2).mean(-1), "ee": ((rel - rel_ref) ** 2).sum(-1).sum(-1)}


def feet_error(vel, ref_vel, feet) -> object:
    """``e_feet`` ``(N,)``: mean over the bodies ``feet`` of the squared linear velocity error."""
    feet = list(feet)
    return ((vel[:, feet] - ref_vel[:, feet]) ** 2).sum(-1).mean(-1)


def imitation_reward(err: dict, cfg: ImitationConfig) -> dict:
    """Eq. 10: ``r_im = exp(-10 e_root) exp(-2 e_q) exp(-0.5 e_alpha) exp(-40 e_ee)`` and its factors,
    times ``exp(-k_feet e_feet)`` when ``k_feet > 0`` (``err`` then has ``feet``)."""
    x = xp(err["root"])
    r = {f"r_{k}": x.exp(-getattr(cfg, f"k_{k}") * err[k]) for k in ("root", "q", "alpha", "ee")}
    r["r_im"] = r["r_root"] * r["r_q"] * r["r_alpha"] * r["r_ee"]
    if cfg.k_feet > 0:
        r["r_feet"] = x.exp(-cfg.k_feet * err["feet"])
        r["r_im"] = r["r_im"] * r["r_feet"]
    return r


def action_rate(a, a_prev, fresh):
    """``e_rate`` ``(N,)``: the mean over action dimensions of ``(a - a_prev)^2``, 0 where ``fresh``
    (the environment's first step of an episode: ``a_prev`` belongs to the one before) and where an
    action is not finite (an invalid action ends its episode; it must not poison the return)."""
    x = xp(a)
    e = ((a - a_prev) ** 2).mean(-1)
    return x.where(fresh | ~x.isfinite(e), x.zeros_like(e), e)
