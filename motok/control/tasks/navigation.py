"""The navigation task: walk to a point on the floor (hybrid-latent paper, appendix C.3).

* reset: reference state initialisation (``mdp.resets``) at a random clip and frame (clips in
  proportion to their length) or at given ones; no reference motion is used after that. A first
  target is drawn around the new root (``mdp.navigation.sample_targets``: within 10 m, any direction);
* goal: Eq. 15, the target in the root's heading frame, 2 numbers (``heading_frame_target``);
* reward: Eq. 16, ``0.7 exp(-0.5 d^2) + 0.3 exp(-max(0, 1 - v)^2)``, its maximum 1 anywhere within
  0.5 m (``navigation_reward``), 0 after a diverged simulation or an invalid action;
* a new target every ``retarget_seconds`` (4 s); the step's reward and ``info`` are those of the
  target the action was chosen for, the goal returned after it already shows the new one;
* terminated: the head below ``fall_height`` (not on the first step), a diverged simulation or an
  invalid action; truncated: ``episode_seconds`` (8 s, two targets).

The fork (``andreazhangyh/hybrid_latent_prior``, ``humanoid_navigation.py``) differs in two
book-keeping details we do not copy: it computes the goal observation before drawing the new
target (the policy sees the new target one step late) and truncates one step early (239 steps).

Evaluation (:func:`evaluate_navigation`): how many targets are reached before they change, how
fast, how often the character falls, and how it moves once there (the idle phase: its root speed,
and the body motion itself, whose motion-matching distance to the dataset
(``motok.eval.motion_matching``) :func:`report` adds to a full evaluation).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Callable

import numpy as np

from motok.arrays import copy, is_tensor, like, xp
from motok.control.mdp.navigation import (head_fall, heading_frame_target, navigation_reward, planar_distance,
                                          sample_targets)
from motok.control.mdp.resets import free_starts, reference_state
from motok.control.mdp.task_env import Task, TaskEnv
from motok.control.mdp.terminations import end_of_step
from motok.control.tasks.episodes import Step, play_episodes
from motok.control.tasks.registry import TaskSpec
from motok.errors import UserError
from motok.ranges import In
from motok.sim.env import HumanoidEnv
from motok.sim.humanoid import from_mj
from motok.sim.reference import ReferenceLibrary


@dataclass
class NavigationTaskConfig:
    episode_seconds: In[float, "> 0"] = 8.0  # an episode's length (two targets)
    retarget_seconds: In[float, "> 0"] = 4.0  # a new target this often (120 control steps at 30 Hz)
    min_distance: In[float, ">= 0"] = 0.0  # m, new targets from the root: "within 10 m" (C.3); the fork's code: 5
    max_distance: In[float, ">= 0"] = 10.0  # m
    speed: In[float, ">= 0"] = 1.0  # u, m/s toward the target that earns the full velocity term
    reach_radius: In[float, "> 0"] = 0.5  # m: arrival (the reward's maximum within it); "reached" for evaluation
    # Eq. 16's maximum (w_pos + w_vel) anywhere within reach_radius (C.3); false: only the velocity
    # term is 1 there and the position term decays on (the fork's code)
    full_reward_on_arrival: bool = True
    k_pos: In[float, ">= 0"] = 0.5  # exp(-k_pos d^2)
    w_pos: In[float, ">= 0"] = 0.7  # weight of the position term (Eq. 16)
    w_vel: In[float, ">= 0"] = 0.3  # weight of the velocity term
    fall_height: In[float, "> 0"] = 0.5  # m, head height
    early_termination: bool = True  # a fall ends the episode
    head_body: str | None = None  # the body tested for falls; None: the skeleton's head joint

    # What a config saved before a key existed did (motok.config.from_dict): the velocity term alone was
    # full within the radius.
    KEYS_ADDED = {"full_reward_on_arrival": False}

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


class NavigationTask(Task):
    """Episode state per environment: ``target`` ``(N, 2)`` (world xy, for renderers too),
    ``steps`` since the reset, ``target_steps`` since the target appeared, ``target_index``
    within the episode, ``reached_step`` (first ``target_steps`` within the radius, -1: not yet).

    With an ``on_device`` environment, a library moved to its device and a ``torch.Generator``
    there, the episode state and every term are device tensors (:mod:`motok.arrays`); new targets
    are then drawn for every environment and kept where one is due, so no mask is read on the host."""

    goal_dim = 2
    reward_key = "r_task"
    marker_radius = 0.25  # m, in videos: a target seen from the distance that frames it with the character
    joins_mid_episode = True  # a target is drawn around wherever the root is

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
        c, f = free_starts(L, len(ids), self.rng, clips, frames, "navigation task")
        self.env.set_state(ids, *reference_state(L, c, f))
        self.clip[ids], self.frame[ids], self.steps[ids], self.target_index[ids] = c, f, 0, 0
        self._new_targets(ids)
        self._refresh_goal(ids)

    def join(self, ids) -> None:
        """A first target around the current root of ``ids``, their episode clock restarted."""
        ids = like(self.steps, np.atleast_1d(np.asarray(ids, dtype=np.int64)))
        self.steps[ids], self.target_index[ids] = 0, 0
        self._new_targets(ids)
        self._refresh_goal(ids)

    def goal(self):
        return copy(self._goal)

    def step_limit(self) -> int:
        return self.max_steps

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
        _, fell = head_fall(b.pos[:, self.head, 2], self.steps, c)  # reported only where it ends the episode
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


# ---------------------------------------------------------------------- evaluation

MIN_IDLE_SECONDS = 0.5  # a stay at the target shorter than this is passing through, not idling
# Nor is walking through the 1 m circle (0.7 s at 1.4 m/s): idling is at most this root speed, m/s,
# under half the data's slowest walking pace (median 1.06 m/s for the turns of set 2).
IDLE_SPEED = 0.5


def stays(mask: np.ndarray, episode: np.ndarray, min_steps: int) -> list[tuple[int, int, int]]:
    """``(env, first step, end step)`` of every run of ``mask (S, N)`` that lasts ``min_steps`` or
    more without ``episode (S, N)`` (an environment's episode counter) changing inside it."""
    same = np.ones(mask.shape, dtype=bool)
    same[1:] = episode[1:] == episode[:-1]
    begin, finish = mask.copy(), mask.copy()
    begin[1:] &= ~(mask[:-1] & same[1:])  # on, and not going on from the step before
    finish[:-1] &= ~(mask[1:] & same[1:])  # on, and not going on into the next step
    out = []
    for n in np.flatnonzero(mask.any(0)):  # a loop over stays, after the rollout
        for a, b in zip(np.flatnonzero(begin[:, n]), np.flatnonzero(finish[:, n]) + 1):
            if b - a >= min_steps:
                out.append((int(n), int(a), int(b)))
    return out


def evaluate_navigation(mdp: TaskEnv, act: Callable[[np.ndarray, np.ndarray], np.ndarray], episodes: int,
                        idle_speed: float = IDLE_SPEED) -> dict:
    """Run ``act(obs, goal) -> actions`` (numpy, all environments at once) on ``mdp`` from fresh
    episodes until ``episodes`` have ended; the task's generator draws the starts and targets.

    A target counts as reached if the root came within the reach radius while it was current; one
    cut short by a fall counts as missed. Returns ``episodes``, ``targets``, ``reached_share``,
    ``time_to_reach_mean_s`` / ``_median_s`` (over reached targets, NaN if none),
    ``falls_per_episode`` (head falls), ``diverged``, ``mean_reward`` (the main term per step),
    ``goal_speeds`` (planar root speed, m/s, of every step spent within the radius) and its
    ``goal_speed_mean`` / ``goal_speed_median``; per target, the root's distance when it appeared
    and the closest it came while it was current (``start_distances``, ``closest_distances``, m)
    with their means and ``approach_share``, the mean share of the starting distance closed
    (``1 - closest / start``: 1 at the target, 0 for no step toward it; a target beyond 4 m is out
    of reach at the rewarded 1 m/s, so the reached share alone does not tell a policy that walks
    toward it from one that stands); and ``idle_bodies``: the body positions
    ``(T, J, 3)`` (MuJoCo frame, control rate) of every stay within the radius, slower than
    ``idle_speed`` (m/s), of at least :data:`MIN_IDLE_SECONDS`, for the idle phase's motion matching."""
    if not isinstance(mdp.task, NavigationTask):
        raise UserError(f"evaluate_navigation needs a TaskEnv around a NavigationTask, got {type(mdp.task).__name__}")
    key, N = mdp.task.reward_key, mdp.num_envs
    c = dict(targets=0, reached=0, falls=0, diverged=0, steps=0, reward=0.0)
    times, speeds, starts, closests = [], [], [], []
    # Per step: who idles at its target, in which of its episodes, and the bodies of those idling.
    idling, episode, bodies = [], [], []
    count = np.zeros(N, dtype=np.int64)  # episodes each environment has ended
    start, closest = np.zeros(N), np.zeros(N)  # per current target: the distance when it appeared, the closest since

    def to_target():
        return np.asarray(planar_distance(mdp.env.bodies.pos[:, 0], mdp.task.target), np.float64)

    def on_step(s: Step) -> None:
        nonlocal closest
        info, live = s.info, s.live
        closest = np.fmin(closest, info["distance"])  # a diverged step (NaN) does not erase the approach
        at_goal = info["reached"] & live
        idling.append(at_goal & (info["root_speed"] < idle_speed))
        episode.append(count.copy())
        bodies.append(mdp.env.bodies.pos[idling[-1]].astype(np.float32))
        ends = info["target_ends"] & live
        c["targets"] += int(ends.sum())
        hit = ends & info["target_reached"]
        c["reached"] += int(hit.sum())
        times.append(info["time_to_reach"][hit])
        starts.append(start[ends])
        closests.append(closest[ends])
        speeds.append(info["root_speed"][at_goal])
        c["falls"] += int((info["fell"] & s.terminated & live).sum())
        c["diverged"] += int((info["diverged"] & live).sum())
        c["reward"] += float(s.rewards[key][live].sum())
        c["steps"] += int(live.sum())
        count[s.ended] += 1
        # A new target from the next step on; an ended episode's new target is measured after its reset.
        new = info["target_ends"].copy()
        new[s.ended] = False
        if new.any():
            start[new] = to_target()[new]
            closest[new] = start[new]

    def on_reset(ids, fresh) -> None:
        start[ids] = to_target()[ids]
        closest[ids] = start[ids]

    play_episodes(mdp, act, episodes, on_step, on_reset)
    times, speeds = np.concatenate(times), np.concatenate(speeds)
    starts, closests = np.concatenate(starts), np.concatenate(closests)
    min_steps = max(3, int(round(MIN_IDLE_SECONDS / mdp.dt)))
    mask = np.stack(idling)
    row = np.full(mask.shape, -1)
    row[mask] = np.arange(int(mask.sum()))  # row-major, as the per-step rows were appended
    pos = np.concatenate(bodies)
    idle = [pos[row[a:b, n]] for n, a, b in stays(mask, np.stack(episode), min_steps)]

    def stat(f, a):
        return float(f(a)) if len(a) else float("nan")

    return {"episodes": int(episodes), "targets": c["targets"], "reached_share": c["reached"] / max(c["targets"], 1),
            "time_to_reach_mean_s": stat(np.mean, times), "time_to_reach_median_s": stat(np.median, times),
            "falls_per_episode": c["falls"] / int(episodes), "diverged": c["diverged"],
            "mean_reward": c["reward"] / max(c["steps"], 1),
            "goal_speeds": speeds, "goal_speed_mean": stat(np.mean, speeds),
            "goal_speed_median": stat(np.median, speeds), "start_distances": starts, "closest_distances": closests,
            "start_distance_mean_m": stat(np.mean, starts), "closest_distance_mean_m": stat(np.mean, closests),
            "approach_share": stat(np.mean, 1.0 - closests / np.maximum(starts, 1e-9)), "idle_bodies": idle}


def idle_matching(idle_bodies: list[np.ndarray], data, names, hz: float) -> dict:
    """The idle phase's naturalness: Eq. 8 motion matching (``motok.eval.motion_matching``) of
    the transitions of ``idle_bodies`` (from :func:`evaluate_navigation`, at the control rate
    ``hz``) against the clips ``names`` of the dataset ``data``: distance, filtered rate, coverage."""
    from motok.eval.motion_matching import match_joints, no_transitions, reference

    if not idle_bodies:  # no stay to match: no threshold to derive either
        return no_transitions()
    return match_joints(reference(data, list(names)), [from_mj(b) for b in idle_bodies], hz)


def report(res: dict, data, lib) -> dict:
    """A full evaluation's measures that need the dataset: the idle phase's motion matching
    against the clips the policy started from (``idle_bodies`` replaced by their summary)."""
    mm = res["idle_motion_matching"] = idle_matching(res.pop("idle_bodies"), data, lib.names, lib.fps)
    res.update({f"idle_{k}": mm[k] for k in ("transitions", "distance_mean", "filtered_rate")})
    return res


# appendix C.3; Table 8: one active codebook (the authors' code: num_quants 1)
SPEC = TaskSpec("navigation", NavigationTaskConfig, NavigationTask, evaluate_navigation, report, codebooks=1)
