"""Navigation terms (hybrid-latent paper, appendix C.3): reach a point on the floor.

Pure functions on ``(N, ...)`` arrays, composed by ``motok.control.tasks.navigation``:

* :func:`heading_frame_target`, Eq. 15: the target minus the root, planar, rotated into the
  root's heading frame (yaw only): ``x`` ahead of the character, ``y`` on its left.
* :func:`navigation_reward`, Eq. 16: ``r = w_pos exp(-k_pos d^2) + w_vel exp(-max(0, u - v)^2)``
  with ``d`` the planar root-to-target distance and ``v`` the root's speed toward the target. On
  arrival, within the reach radius, the reward is its maximum ``w_pos + w_vel`` anywhere (the
  paper's C.3); with ``full_reward_on_arrival`` off only the velocity term is 1 there and the
  position term goes on decaying with ``d`` (the fork's code).
* :func:`sample_targets`: a new target uniform in direction, distance uniform in ``[min, max]``
  (the paper: "within 10 m", ``[0, 10]``).
* :func:`head_fell`: the fall test, skipped on the first step after a reset; :func:`head_fall`:
  that test and the falls that end an episode.

Where the authors' fork (``andreazhangyh/hybrid_latent_prior``,
``isaacgymenvs/tasks/humanoid_navigation.py``) fixes details the paper leaves open, we follow it:
``v`` counts only the forward part of the velocity (its component along the heading, clamped at
0, so side-stepping or walking backwards toward the target earns nothing), the distance is
uniform (not uniform over the disc's area) and the first step after a reset is not tested for a
fall. Where the fork departs from the paper's text, the paper's is the default and the fork's a
setting: its targets lie 5-10 m away (``min_distance=5``) and its position term decays inside the
reach radius (``full_reward_on_arrival=False``).
"""

from __future__ import annotations

import numpy as np

from motok.arrays import is_tensor, xp
from motok.control.mdp.terminations import fell
from motok.errors import UserError
from motok.rotations import quat_to_matrix
from motok.sim.obs import heading, unyaw


def _f64(a):
    """Host inputs as float64 arrays (lists allowed); device tensors as they are (their precision)."""
    return a if is_tensor(a) else np.asarray(a, dtype=np.float64)


def root_heading(root_quat):
    """Cosine and sine ``(N,)`` of the yaw of the root's forward (+X) axis, from MuJoCo ``(w, x, y, z)``
    quaternions ``(N, 4)`` or rotation matrices ``(N, 3, 3)`` (what ``Bodies.rot`` holds for free)."""
    q = _f64(root_quat)
    return heading(q if tuple(q.shape[-2:]) == (3, 3) else quat_to_matrix(q))


def planar_distance(root_pos, target):
    """``(N,)`` floor distance from the root (``(N, >= 2)``, world) to the target ``(N, 2)``."""
    d = _f64(target) - _f64(root_pos)[:, :2]
    return xp(d).hypot(d[:, 0], d[:, 1])


def heading_frame_target(root_pos, root_quat, target):
    """Eq. 15, ``(N, 2)``: ``target - root_xy`` turned by minus the root's heading.

    ``+x`` is ahead of the character and ``+y`` on its left (MuJoCo: Z up, facing +X at rest), so
    a root yawed by +90 degrees (facing world +Y) sees a target 3 m along world +X at ``(0, -3)``,
    on its right."""
    c, s = root_heading(root_quat)
    disp = _f64(target) - _f64(root_pos)[:, :2]
    x = xp(disp)
    return unyaw(c, s, x.concatenate([disp, x.zeros_like(disp[:, :1])], -1))[:, :2]


def navigation_reward(root_pos, root_vel, root_quat, target, cfg) -> dict:
    """Eq. 16: ``{"r_task", "r_pos", "r_vel"}``, each ``(N,)``.

    ``root_pos``/``root_vel`` world ``(N, 3)`` (only x, y are used), ``root_quat`` ``(N, 4)``
    ``(w, x, y, z)`` (or ``(N, 3, 3)`` matrices), ``target`` ``(N, 2)``; ``cfg`` any object with ``speed`` (u, m/s),
    ``reach_radius`` (m), ``k_pos``, ``w_pos``, ``w_vel``, ``full_reward_on_arrival`` (``NavigationTaskConfig``).

    ``v = (max(0, vel . h) h) . (target - root) / d`` with ``h`` the unit heading: the speed
    toward the target of the forward part of the root's planar velocity (the fork's form)."""
    c, s = root_heading(root_quat)
    disp = _f64(target) - _f64(root_pos)[:, :2]
    x = xp(disp)
    d = x.hypot(disp[:, 0], disp[:, 1])
    vel = _f64(root_vel)
    forward = x.clip(c * vel[:, 0] + s * vel[:, 1], 0.0, None)
    # At d = 0 the direction is undefined; the velocity term is 1 there anyway (within the radius).
    toward = forward * (c * disp[:, 0] + s * disp[:, 1]) / x.clip(d, 1e-9, None)
    near = d < cfg.reach_radius
    r_pos = x.exp(-cfg.k_pos * d * d)
    if cfg.full_reward_on_arrival:  # Eq. 16's maximum anywhere within the radius: arrival is the goal
        r_pos = x.where(near, 1.0, r_pos)
    r_vel = x.where(near, 1.0, x.exp(-x.clip(cfg.speed - toward, 0.0, None) ** 2))
    return {"r_task": cfg.w_pos * r_pos + cfg.w_vel * r_vel, "r_pos": r_pos, "r_vel": r_vel}


def sample_targets(root_xy, rng, min_dist: float, max_dist: float):
    """``(N, 2)`` targets around ``root_xy`` ``(N, >= 2)``: direction uniform on the circle, distance
    uniform in ``[min_dist, max_dist]`` m (the fork's form of the draw; the paper says "within 10 m").
    ``rng``: numpy's generator for host arrays, a ``torch.Generator`` on the device for tensors."""
    if not 0.0 <= min_dist <= max_dist:
        raise UserError(f"target distances need 0 <= min_dist <= max_dist, got min_dist={min_dist}, "
                        f"max_dist={max_dist}")
    root_xy = _f64(root_xy)[:, :2]
    x = xp(root_xy)
    if x is np:
        u = rng.random((len(root_xy), 2))
    else:
        u = x.rand((len(root_xy), 2), generator=rng, device=root_xy.device, dtype=root_xy.dtype)
    angle, dist = 2.0 * np.pi * u[:, 0], min_dist + (max_dist - min_dist) * u[:, 1]
    return root_xy + dist[:, None] * x.stack([x.cos(angle), x.sin(angle)], -1)


def head_fell(head_height, steps, min_height: float):
    """``(N,)``: the head below ``min_height`` m, from the second control step of an episode on
    (``steps`` counts the steps since the reset, 1 on the first): a reference start state can
    still be settling onto the floor during its first step (the fork's grace step)."""
    return fell(_f64(head_height), min_height) & (steps > 1 if is_tensor(steps) else np.asarray(steps) > 1)


def head_fall(head_height, steps, cfg):
    """``(down, ends)``, each ``(N,)``: the fall test of :func:`head_fell` at ``cfg.fall_height``,
    and the falls that end an episode: all of them, or none with ``cfg.early_termination`` off
    (an evaluation that plays every episode to its end)."""
    down = head_fell(head_height, steps, cfg.fall_height)
    return down, (down if cfg.early_termination else xp(down).zeros_like(down))
