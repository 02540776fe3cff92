"""A composed task: navigate with the lower body while the right hand reaches a point held relative
to the pelvis (the hybrid-latent paper's future work: body parts given different goals at once).

The task is the navigation task (``tasks.navigation``: its reset, target, Eq. 15 goal, Eq. 16
reward, fall test and episode length, from the recipe's ``tasks.navigation`` section) with a
second, upper-body goal on top:

* the hand target: a point in the pelvis' heading frame (``x`` ahead, ``y`` left, ``z`` up, from
  the root body), uniform in the box ``target_min``-``target_max`` (in front of the right
  shoulder, from the chest to above the head: reachable while walking), a new one every
  ``target_seconds``. Held relative to the pelvis, not fixed in the world, so it travels with the
  walk and the two goals never pull against each other;
* goal: navigation's 2 numbers, then 6 for the hand: the target in the heading frame (where the
  hand should be: which arm pose) and the target minus the hand (which way to move it);
  ``goal_parts`` says which numbers belong to the lower and which to the upper body, for a policy
  that gives each body part its own goal; any prior's high-level policy reads the whole goal,
  so the task does not depend on the prior it runs over (whole-body or part-wise);
* reward: ``w_nav r_nav + w_hand exp(-k_hand d^2)``, ``r_nav`` Eq. 16 and ``d`` the hand's
  distance to its target (m); 0 after a diverged simulation or an invalid action;
* ends: navigation's (the head below 0.5 m; 8 s).

Evaluation (:func:`evaluate_compose`): navigation's own evaluation (targets reached, time, falls,
idle phase) on the same episodes, plus the hand's: the share of hand targets reached (the hand
within ``reach_radius`` while the target was current), the hand's error per step (mean, median),
and every counted episode's body positions, whose Eq. 8 motion matching against the dataset
(``motok.eval.motion_matching``) :func:`report` adds (``motion_*``: are the composed motions'
transitions like the data's).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from motok.arrays import copy, is_tensor, like, xp
from motok.control.mdp.navigation import root_heading
from motok.control.mdp.task_env import TaskEnv
from motok.control.tasks import navigation
from motok.control.tasks.episodes import Act, episode_quota
from motok.control.tasks.navigation import NavigationTask, NavigationTaskConfig
from motok.control.tasks.registry import TaskSpec
from motok.errors import UserError
from motok.ranges import In
from motok.sim.humanoid import from_mj
from motok.sim.obs import unyaw

HAND_GOAL = 6  # the target in the heading frame (3), target minus hand (3)


@dataclass
class ComposeTaskConfig:
    hand_body: str = "Hand_R"  # the body that reaches for the upper-body target (a body of the humanoid)
    # m, the target's box in the pelvis' heading frame (x ahead, y left, z up): before the right shoulder,
    # from chest height to above the head
    target_min: In[list[float], "any"] = field(default_factory=lambda: [0.2, -0.4, 0.2])
    target_max: In[list[float], "any"] = field(default_factory=lambda: [0.45, -0.1, 0.7])  # m, the box's far corner (as target_min)
    target_seconds: In[float, "> 0"] = 2.0  # a new hand target this often (4 per 8 s navigation episode)
    k_hand: In[float, ">= 0"] = 10.0  # exp(-k_hand d^2), d in m: halves at 26 cm, so the whole box is within reach of a gradient
    w_nav: In[float, ">= 0"] = 0.5  # weight of navigation's reward (Eq. 16, itself at most 1)
    w_hand: In[float, ">= 0"] = 0.5  # weight of the hand term
    reach_radius: In[float, "> 0"] = 0.15  # m: a hand target counts as reached within it (evaluation)

    def __post_init__(self):
        lo, hi = np.asarray(self.target_min, float), np.asarray(self.target_max, float)
        if lo.shape != (3,) or hi.shape != (3,) or (lo > hi).any():
            raise UserError(f"compose task: target_min and target_max must be 3 numbers each with min <= max, got "
                            f"{self.target_min} and {self.target_max}")
        for name in ("target_seconds", "reach_radius"):
            if not getattr(self, name) > 0:
                raise UserError(f"compose task: {name} must be > 0, got {getattr(self, name)}")
        for name in ("k_hand", "w_nav", "w_hand"):
            if not getattr(self, name) >= 0:
                raise UserError(f"compose task: {name} must be >= 0, got {getattr(self, name)}")


def hand_goal(root_pos, root_rot, hand_pos, offset):
    """``(N, 6)``: the target ``offset`` (heading frame, ``(N, 3)``) and the target minus the hand, in
    the heading frame of the root (position ``(N, 3)``, rotation matrices or quaternions)."""
    c, s = root_heading(root_rot)
    rel = unyaw(c, s, hand_pos - root_pos)
    return xp(rel).concatenate([offset, offset - rel], -1)


def hand_reward(distance, cfg: ComposeTaskConfig) -> dict:
    """``{"r_hand"}``: ``exp(-k_hand d^2)`` of the hand's distance ``d`` (m) to its target."""
    return {"r_hand": xp(distance).exp(-cfg.k_hand * distance ** 2)}


class ComposeTask(NavigationTask):
    """Navigation's episode state, plus per environment the hand target ``offset`` ``(N, 3)``
    (heading frame), ``hand_steps`` since it appeared and ``hand_reached`` (within the radius
    since then). ``cfg`` is navigation's settings, ``compose`` this task's."""

    marker_radius = np.array([NavigationTask.marker_radius, 0.06])  # m: the floor target, the hand target
    marker_rgba = np.array([[0.9, 0.2, 0.2, 0.8], [0.1, 0.8, 0.2, 0.9]])  # the hand target green, told from the head

    def __init__(self, cfg: ComposeTaskConfig, env, lib, rng, nav: NavigationTaskConfig | None = None):
        super().__init__(nav if nav is not None else NavigationTaskConfig(), env, lib, rng)
        self.compose = cfg
        joints = list(env.hum.skeleton.joints)
        if cfg.hand_body not in joints:
            raise UserError(f"compose task: hand_body {cfg.hand_body!r} is not a body of the humanoid; "
                            f"bodies: {', '.join(joints)}")
        self.hand = joints.index(cfg.hand_body)
        self.goal_dim = NavigationTask.goal_dim + HAND_GOAL
        self.goal_parts = {"lower": slice(0, NavigationTask.goal_dim), "upper": slice(NavigationTask.goal_dim,
                                                                                     self.goal_dim)}
        N = env.num_envs
        self.hand_limit = max(1, int(round(cfg.target_seconds * env.control_hz)))
        self.offset = like(env.bodies.pos, np.zeros((N, 3)))
        self.hand_steps = like(self.steps, np.zeros(N, dtype=np.int64))
        self.hand_reached = like(env.bodies.pos, np.zeros(N)) > 0

    @classmethod
    def build(cls, cfg, env, lib, rng, cfgs=None):
        return cls(cfg, env, lib, rng, None if cfgs is None else cfgs.navigation)

    def _new_hand_targets(self, ids) -> None:
        c = self.compose
        n = len(self.hand_steps[ids])
        u = self.rng.random((n, 3)) if not is_tensor(self.offset) else \
            xp(self.offset).rand((n, 3), generator=self.rng, device=self.offset.device, dtype=self.offset.dtype)
        lo, hi = like(self.offset, np.asarray(c.target_min, float)), like(self.offset, np.asarray(c.target_max, float))
        self.offset[ids] = lo + (hi - lo) * u
        self.hand_steps[ids], self.hand_reached[ids] = 0, False

    def set_hand_targets(self, ids, offset) -> None:
        """Put the hand targets of ``ids`` at ``offset`` ``(len(ids), 3)`` (heading frame; tests, demos)."""
        ids = like(self.steps, np.atleast_1d(np.asarray(ids, dtype=np.int64)))
        self.offset[ids] = like(self.offset, np.asarray(offset, dtype=np.float64))
        self.hand_steps[ids], self.hand_reached[ids] = 0, False

    def reset(self, ids, clips=None, frames=None) -> None:
        super().reset(ids, clips, frames)
        self._new_hand_targets(ids)

    def join(self, ids) -> None:
        """Navigation's (a target around the current root), and a first hand target."""
        super().join(ids)
        self._new_hand_targets(like(self.steps, np.atleast_1d(np.asarray(ids, dtype=np.int64))))

    def hand_distance(self):
        """``(N,)`` m from the hand to its target."""
        b = self.env.bodies
        e = hand_goal(b.pos[:, 0], b.rot[:, 0], b.pos[:, self.hand], self.offset)[:, 3:]
        return xp(e).sqrt((e * e).sum(-1))

    def goal(self):
        b = self.env.bodies
        h = hand_goal(b.pos[:, 0], b.rot[:, 0], b.pos[:, self.hand], self.offset)
        return xp(h).concatenate([super().goal(), h], -1)

    def hand_target(self) -> np.ndarray:
        """``(N, 3)`` world position of each hand target."""
        b = self.env.bodies
        c, s = root_heading(b.rot[:, 0])
        o = self.offset
        x = xp(o)
        return b.pos[:, 0] + x.stack([c * o[:, 0] - s * o[:, 1], s * o[:, 0] + c * o[:, 1], o[:, 2]], -1)

    def markers(self) -> np.ndarray:
        """``(N, 2, 3)``: the floor target and the hand target."""
        t = self.hand_target()
        return np.concatenate([super().markers(), (t.cpu().numpy() if is_tensor(t) else t)[:, None]], 1)

    def update(self, diverged, invalid):
        rewards, terminated, truncated, info = super().update(diverged, invalid)
        c, x = self.compose, xp(diverged)
        self.hand_steps += 1
        d = self.hand_distance()
        self.hand_reached = self.hand_reached | (d < c.reach_radius)
        r_hand = x.where(diverged | invalid, 0.0, hand_reward(d, c)["r_hand"])
        rewards = {**rewards, "r_nav": rewards["r_task"], "r_hand": r_hand,
                   "r_task": c.w_nav * rewards["r_task"] + c.w_hand * r_hand}
        ended = terminated | truncated
        due = (self.hand_steps >= self.hand_limit) & ~ended
        info = {**info, "hand_error": d, "hand_target_reached": copy(self.hand_reached),
                "hand_target_ends": due | ended}
        if x is np:
            ids = np.flatnonzero(due)
            if len(ids):
                self._new_hand_targets(ids)
        else:  # drawn for all, kept where due: the mask never goes to the host
            before = (copy(self.offset), copy(self.hand_steps), copy(self.hand_reached))
            self._new_hand_targets(slice(None))
            self.offset = x.where(due[:, None], self.offset, before[0])
            self.hand_steps = x.where(due, self.hand_steps, before[1])
            self.hand_reached = x.where(due, self.hand_reached, before[2])
        return rewards, terminated, truncated, info


# ---------------------------------------------------------------------- evaluation

class _Watch:
    """``mdp`` as :func:`~motok.control.tasks.navigation.evaluate_navigation` drives it, recording the
    hand's measures and every counted episode's body positions on the way (the same quota of
    episodes per environment as the loop it serves: ``episode_quota``)."""

    def __init__(self, mdp: TaskEnv, episodes: int):
        self.mdp, N = mdp, mdp.num_envs
        self.quota, self.done = episode_quota(episodes, N), np.zeros(N, dtype=np.int64)
        self.frames: list[list[np.ndarray]] = [[] for _ in range(N)]
        self.episodes: list[np.ndarray] = []
        self.errors: list[np.ndarray] = []
        self.targets = self.reached = 0

    def __getattr__(self, name):
        return getattr(self.mdp, name)

    def reset(self, ids=None, **where):
        out = self.mdp.reset(ids, **where)
        for i in range(self.mdp.num_envs) if ids is None else np.atleast_1d(ids):
            self.frames[i] = [self.mdp.env.bodies.pos[i].astype(np.float32)]
        return out

    def step(self, actions):
        out = self.mdp.step(actions)
        term, trunc, info = out[3], out[4], out[5]
        live = self.done < self.quota
        ok = live & ~np.asarray(info["diverged"])
        self.errors.append(np.asarray(info["hand_error"])[ok])
        ends = np.asarray(info["hand_target_ends"]) & live
        self.targets += int(ends.sum())
        self.reached += int((ends & np.asarray(info["hand_target_reached"])).sum())
        pos = self.mdp.env.bodies.pos
        for i in np.flatnonzero(live):
            self.frames[i].append(pos[i].astype(np.float32))
        for i in np.flatnonzero((term | trunc) & live):
            self.episodes.append(np.stack(self.frames[i]))
            self.done[i] += 1
        return out


def evaluate_compose(mdp: TaskEnv, act: Act, episodes: int) -> dict:
    """Navigation's evaluation of the episodes (``evaluate_navigation``: targets reached, time,
    falls, idle phase; ``mean_reward`` is the composed reward) plus ``hand_targets``,
    ``hand_reached_share``, ``hand_error_mean_m`` / ``hand_error_median_m`` (per step) and
    ``motion_bodies`` (every counted episode's body positions ``(T, J, 3)``, MuJoCo frame, for
    :func:`report`'s motion matching)."""
    if not isinstance(mdp.task, ComposeTask):
        raise UserError(f"evaluate_compose needs a TaskEnv around a ComposeTask, got {type(mdp.task).__name__}")
    watch = _Watch(mdp, int(episodes))
    res = navigation.evaluate_navigation(watch, act, episodes)
    err = np.concatenate(watch.errors)
    return {**res, "hand_targets": watch.targets, "hand_reached_share": watch.reached / max(watch.targets, 1),
            "hand_error_mean_m": float(err.mean()) if len(err) else float("nan"),
            "hand_error_median_m": float(np.median(err)) if len(err) else float("nan"),
            "motion_bodies": watch.episodes}


def report(res: dict, data, lib) -> dict:
    """Navigation's additions (its idle phase), and the Eq. 8 motion matching of the composed
    episodes' transitions against the clips the policy started from (``motion_*``)."""
    from motok.eval.motion_matching import match_joints, no_transitions, reference

    res = navigation.report(res, data, lib)
    bodies = res.pop("motion_bodies")
    mm = match_joints(reference(data, list(lib.names)), [from_mj(b) for b in bodies], lib.fps) if bodies \
        else no_transitions()
    res["motion_matching"] = mm
    res.update({f"motion_{k}": mm[k] for k in ("transitions", "distance_mean", "filtered_rate")})
    return res


# Two active codebooks: the hand goal is a body point to follow, as head tracking's is, which the paper
# learns with 2 (Table 7) where navigation alone has 1 (Table 8).
SPEC = TaskSpec("compose", ComposeTaskConfig, ComposeTask, evaluate_compose, report, codebooks=2,
                reads=lambda cfg: ("navigation",))
