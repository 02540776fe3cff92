"""The navigation task: walk to a point on the floor (hybrid-latent paper, appendix C.3).

* reset: reference state initialisation (``mdp.resets``) at a random clip and frame (clips in
  proportion to their length) or at given ones; no reference motion is used after that. A first
  target is drawn around the new root (``mdp.navigation.sample_targets``: 5-10 m, any direction);
* goal: Eq. 15, the target in the root's heading frame, 2 numbers (``heading_frame_target``);
* reward: Eq. 16, ``0.7 exp(-0.5 d^2) + 0.3 exp(-max(0, 1 - v)^2)``, the velocity term 1 within
  0.5 m (``navigation_reward``), 0 after a diverged simulation or an invalid action;
* a new target every ``retarget_seconds`` (4 s); the step's reward and ``info`` are those of the
  target the action was chosen for, the goal returned after it already shows the new one;
* terminated: the head below ``fall_height`` (not on the first step), a diverged simulation or an
  invalid action; truncated: ``episode_seconds`` (8 s, two targets).

The fork (``andreazhangyh/hybrid_latent_prior``, ``humanoid_navigation.py``) differs in two
book-keeping details we do not copy: it computes the goal observation before drawing the new
target (the policy sees the new target one step late) and truncates one step early (239 steps).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from motok.arrays import copy, is_tensor, like, xp
from motok.control.mdp.navigation import (head_fell, heading_frame_target, navigation_reward, planar_distance,
                                          sample_targets)
from motok.control.mdp.resets import host_lengths, reference_state, sample_starts
from motok.control.mdp.terminations import end_of_step
from motok.errors import UserError
from motok.sim.env import HumanoidEnv
from motok.sim.reference import ReferenceLibrary


@dataclass
class NavigationTaskConfig:
    episode_seconds: float = 8.0
    retarget_seconds: float = 4.0  # a new target this often (120 control steps at 30 Hz)
    min_distance: float = 5.0  # m, new targets from the root
    max_distance: float = 10.0
    speed: float = 1.0  # u, m/s toward the target that earns the full velocity term
    reach_radius: float = 0.5  # m: the velocity term is 1 within it; "reached" for evaluation
    k_pos: float = 0.5  # exp(-k_pos d^2)
    w_pos: float = 0.7
    w_vel: float = 0.3
    fall_height: float = 0.5  # m, head height
    early_termination: bool = True
    head_body: str | None = None  # the body tested for falls; None: the skeleton's head joint

    def __post_init__(self):
        for name in ("episode_seconds", "retarget_seconds", "reach_radius"):
            if not getattr(self, name) > 0:
                raise UserError(f"navigation task: {name} must be > 0, got {getattr(self, name)}")
        for name in ("speed", "k_pos", "w_pos", "w_vel"):
            if not getattr(self, name) >= 0:
                raise UserError(f"navigation task: {name} must be >= 0, got {getattr(self, name)}")
        if not 0.0 <= self.min_distance <= self.max_distance:
            raise UserError(f"navigation task: need 0 <= min_distance <= max_distance, got "
                            f"min_distance={self.min_distance}, max_distance={self.max_distance}")


def head_index(skeleton, name: str | None = None) -> int:
    """Body index (skeleton order, as in ``HumanoidEnv.bodies``) of ``name``, or of the skeleton's
    declared head joint when ``name`` is None (``Head`` in bandai21, ``head`` in smpl22)."""
    if name is None:
        return int(skeleton.head)
    if name not in skeleton.joints:
        raise UserError(f"navigation task: head_body {name!r} is not a body of the humanoid; "
                        f"bodies: {', '.join(skeleton.joints)}")
    return skeleton.joints.index(name)


class NavigationTask:
    """Episode state per environment: ``target`` ``(N, 2)`` (world xy, for renderers too),
    ``steps`` since the reset, ``target_steps`` since the target appeared, ``target_index``
    within the episode, ``reached_step`` (first ``target_steps`` within the radius, -1: not yet).

    With an ``on_device`` environment, a library moved to its device and a ``torch.Generator``
    there, the episode state and every term are device tensors (:mod:`motok.arrays`); new targets
    are then drawn for every environment and kept where one is due, so no mask is read on the host."""

    goal_dim = 2
    reward_key = "r_task"
    marker_radius = 0.25  # m, in videos: a target seen from the distance that frames it with the character

    def __init__(self, cfg: NavigationTaskConfig, env: HumanoidEnv, lib: ReferenceLibrary, rng):
        self.cfg, self.env, self.lib, self.rng = cfg, env, lib, rng
        N, S = env.num_envs, lib.starts
        self.max_steps = max(1, int(round(cfg.episode_seconds * env.control_hz)))
        self.retarget_steps = max(1, int(round(cfg.retarget_seconds * env.control_hz)))
        self.head = head_index(env.hum.skeleton, cfg.head_body)
        i64 = lambda v: like(S, np.full(N, v, dtype=np.int64))  # noqa: E731
        self.target = like(env.bodies.pos, np.zeros((N, 2)))
        self.steps, self.target_steps, self.target_index, self.reached_step = i64(0), i64(0), i64(0), i64(-1)
        self.clip, self.frame = i64(0), i64(0)  # the start states
        self._goal = like(env.bodies.pos, np.zeros((N, 2)))

    def _refresh_goal(self, ids) -> None:
        b = self.env.bodies
        self._goal[ids] = heading_frame_target(b.pos[ids, 0], b.rot[ids, 0], self.target[ids])

    def _new_targets(self, ids) -> None:
        self.target[ids] = sample_targets(self.env.bodies.pos[ids, 0, :2], self.rng, self.cfg.min_distance,
                                          self.cfg.max_distance)
        self.target_steps[ids], self.reached_step[ids] = 0, -1

    def set_targets(self, ids, xy) -> None:
        """Put the current targets of ``ids`` at world ``xy`` ``(len(ids), 2)`` (scripted evaluations,
        demos); their clocks restart as for a new target."""
        ids = np.atleast_1d(np.asarray(ids, dtype=np.int64))
        xy = np.asarray(xy, dtype=np.float64)
        if xy.shape != (len(ids), 2) or not np.isfinite(xy).all():
            raise UserError(f"targets must be finite with shape ({len(ids)}, 2), got {xy.shape}")
        ids = like(self.steps, ids)
        self.target[ids] = like(self.target, xy)
        self.target_steps[ids], self.reached_step[ids] = 0, -1
        self._refresh_goal(ids)

    def reset(self, ids, clips=None, frames=None) -> None:
        """Reference starts at random clips and frames from the task's generator, unless
        ``clips``/``frames`` (names or indices; frame 0 by default) are given; then a first target."""
        L = self.lib
        if clips is None:
            c, f = sample_starts(L, len(ids), self.rng, 1)
        else:
            n = len(ids)
            c = np.array([L.index(x) for x in np.broadcast_to(np.asarray(clips, dtype=object), (n,))], dtype=np.int64)
            f = np.broadcast_to(np.asarray(0 if frames is None else frames, dtype=np.int64), (n,)).copy()
            lengths = host_lengths(L)
            bad = (f < 0) | (f >= lengths[c])
            if bad.any():
                raise UserError(f"navigation task: start frames {f[bad].tolist()} are outside their clips "
                                f"(lengths {lengths[c[bad]].tolist()})")
            c, f = like(L.starts, c), like(L.starts, f)
        self.env.set_state(ids, *reference_state(L, c, f))
        self.clip[ids], self.frame[ids], self.steps[ids], self.target_index[ids] = c, f, 0, 0
        self._new_targets(ids)
        self._refresh_goal(ids)

    def goal(self):
        return copy(self._goal)

    def markers(self) -> np.ndarray:
        """``(N, 1, 3)``: each target as a point just above the floor, for videos."""
        t = self.target.cpu().numpy() if is_tensor(self.target) else self.target
        return np.concatenate([t, np.full((len(t), 1), 0.1)], 1)[:, None]

    def update(self, diverged, invalid):
        env, c = self.env, self.cfg
        self.steps += 1
        self.target_steps += 1
        b = env.bodies
        x = xp(b.pos)
        root, rot = b.pos[:, 0], b.rot[:, 0]  # matrices: no quaternion conversion of every body
        dist = planar_distance(root, self.target)
        reached = dist < c.reach_radius
        self.reached_step = x.where(reached & (self.reached_step < 0), self.target_steps, self.reached_step)
        fell = head_fell(b.pos[:, self.head, 2], self.steps, c.fall_height) if c.early_termination \
            else x.zeros_like(reached)
        rewards, terminated, truncated = end_of_step(navigation_reward(root, b.vel[:, 0], rot, self.target, c), fell,
                                                     diverged, invalid, self.steps, self.max_steps)
        ended = terminated | truncated
        retarget = (self.target_steps >= self.retarget_steps) & ~ended
        dt = env.dt
        got = self.reached_step >= 0
        info = {"distance": dist, "reached": reached, "target_time": self.target_steps * dt,
                "target_index": copy(self.target_index), "target_reached": got,
                "time_to_reach": x.where(got, self.reached_step * dt, float("nan")),
                "target_ends": retarget | ended,  # this step was the target's last (for evaluation)
                "root_speed": x.hypot(b.vel[:, 0, 0], b.vel[:, 0, 1]), "fell": fell,
                "diverged": diverged, "invalid_action": invalid, "episode_steps": copy(self.steps)}
        if x is np:
            ids = np.flatnonzero(retarget)
            if len(ids):
                self._new_targets(ids)
                self.target_index[ids] += 1
        else:  # drawn for all, kept where due: the mask never goes to the host
            new = sample_targets(root[:, :2], self.rng, c.min_distance, c.max_distance)
            self.target = x.where(retarget[:, None], new, self.target)
            self.target_steps = x.where(retarget, 0, self.target_steps)
            self.reached_step = x.where(retarget, -1, self.reached_step)
            self.target_index = self.target_index + retarget.to(self.target_index.dtype)
        self._refresh_goal(slice(None))
        return rewards, terminated, truncated, info
