"""The motion in-betweening task (hybrid-latent paper, appendix C.1): pass through keyframes of a
reference window at their frames.

* reset: a random clip and window start (clips drawn in proportion to their usable length) or given
  ones; the start state is the reference at the window's first frame (``mdp.resets``), which is
  also the first keyframe. ``num_keyframes`` keyframes in all: the start, interior keyframes at
  least ``min_keyframe_gap_seconds`` apart, the window's last frame. The interior ones are
  zero-velocity poses (C.1; ``keyframe_selection="still"``, ``mdp.keyframes.sample_still_keyframes``:
  local minima of the reference's pose speed) or, with ``"uniform"``, any frames (the fork's
  draw, ``sample_keyframes``). Training uses 4 per 4 s window (C.1); the paper's Table 2 evaluates
  with 5 per 4 s, which ``eval_keyframes`` holds and :func:`evaluate_inbetween` switches to;
* goal: Eq. 12 position and rotation differences to two keyframes, plus (added to them, as the
  fork does) the Eq. 13 sinusoidal encoding of the frames left until the goal keyframe.
  ``goal_keyframes="previous"`` (the default): the current interval's start keyframe (the last
  one passed) and its goal keyframe (the next to reach), Eq. 12-13 and the fork's
  (``_curr_keyframe_indices`` and ``+ 1``); ``"next"``: the goal keyframe and the one after it
  (the last keyframe twice on the last stretch);
* reward: Eq. 14 against the reference at every frame (``mdp.keyframes.inbetween_reward``), 0 after
  a diverged simulation or an invalid action;
* terminated: the bodies too far from the reference (``mdp.terminations.tracking_failure``):
  by default any body more than 0.5 m from its reference, the maximum distance of B.1 and C.1
  (``termination="mean"``: the mean over bodies, the fork's ``error_mean``, which leaves the feet
  out of that mean), a diverged simulation or an invalid action; truncated: the last keyframe's
  frame is reached. ``info["off_track"]`` is that distance test whether or not it ends the episode
  (``early_termination``), for evaluations that play every window to its end.

Book-keeping that differs from the fork: the goal moves on to the next keyframe at the frame a
keyframe is reached (the fork shows the reached keyframe for one more step, with 0 frames left),
and the episode end is a truncation (the fork flags it as both a timeout and a termination).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from motok.arrays import copy, is_tensor, like, take_along, xp
from motok.control.mdp.keyframes import (KEYFRAME_FEATURES, InbetweenRewardConfig, check_keyframe_count,
                                         check_keyframes, inbetween_errors, inbetween_reward, keyframe_goal,
                                         next_keyframe, pose_speed, sample_keyframes, sample_still_keyframes,
                                         time_encoding)
from motok.control.mdp.resets import (ClipProbabilities, check_rate, given_starts, host_lengths, reference_bodies,
                                      reference_state, sample_starts)
from motok.control.mdp.task_env import Task, TaskEnv
from motok.control.mdp.terminations import MODES, body_distances, end_of_step, tracking_failure
from motok.control.tasks.episodes import Act, EpisodeErrors, reference_errors, whole_episodes
from motok.control.tasks.registry import TaskSpec
from motok.errors import UserError
from motok.ranges import In
from motok.sim.env import HumanoidEnv
from motok.sim.obs import Bodies
from motok.sim.reference import ReferenceLibrary

GOAL_KEYFRAMES = ("next", "previous")
KEYFRAME_SELECTIONS = ("still", "uniform")
TIME_ENCODINGS = ("add", "concat", "none")


@dataclass
class InbetweenTaskConfig:
    window_seconds: In[float, "> 0"] = 4.0  # a window's length; its last frame is the last keyframe
    num_keyframes: In[int, ">= 2"] = 4  # per window, the start and the window's last frame included (C.1, training)
    eval_keyframes: In[int, ">= 2"] = 5  # per window in evaluation (Table 2)
    min_keyframe_gap_seconds: In[float, ">= 0"] = 0.5  # the fork's 15 frames at 30 Hz
    # Interior keyframes: "still", zero-velocity poses (C.1: local minima of the pose's speed);
    # "uniform", any frames (the fork's full_random_long draw)
    keyframe_selection: str = "still"
    # "previous": the interval's start and goal keyframes (Eq. 12-13; the fork's too); "next": the goal
    # keyframe and the one after it
    goal_keyframes: str = "previous"
    time_encoding: str = "add"  # "add" to the keyframe goal (the fork's), "concat" time_encoding_dim numbers, "none"
    time_encoding_dim: In[int, ">= 1"] = 16  # only with "concat"
    termination: str = "any"  # "any" body (the maximum distance, B.1 and C.1) or the "mean" over bodies (the fork's)
    termination_distance: In[float, "> 0"] = 0.5  # m, from the reference
    early_termination: bool = True  # off track ends the episode (false: info["off_track"] only)
    reward: InbetweenRewardConfig = field(default_factory=InbetweenRewardConfig)  # Eq. 14's weights and exponents

    # What a config saved before a key existed did (motok.config.from_dict): uniform keyframes.
    KEYS_ADDED = {"keyframe_selection": "uniform"}

    def __post_init__(self):
        if not self.window_seconds > 0:
            raise UserError(f"inbetween task: window_seconds must be > 0, got {self.window_seconds}")
        if self.keyframe_selection not in KEYFRAME_SELECTIONS:
            raise UserError(f"inbetween task: keyframe_selection must be 'still' or 'uniform', "
                            f"not {self.keyframe_selection!r}")
        if self.goal_keyframes not in GOAL_KEYFRAMES:
            raise UserError(f"inbetween task: goal_keyframes must be 'next' or 'previous', not {self.goal_keyframes!r}")
        if self.time_encoding not in TIME_ENCODINGS:
            raise UserError(f"inbetween task: time_encoding must be 'add', 'concat' or 'none', "
                            f"not {self.time_encoding!r}")
        if self.time_encoding == "concat" and self.time_encoding_dim < 1:
            raise UserError(f"inbetween task: time_encoding_dim must be >= 1, got {self.time_encoding_dim}")
        if self.termination not in MODES:
            raise UserError(f"inbetween task: termination must be 'any' or 'mean', not {self.termination!r}")
        if not self.termination_distance > 0:
            raise UserError(f"inbetween task: termination_distance must be > 0, got {self.termination_distance}")


class InbetweenTask(Task):
    """Episode state per environment: ``clip``, ``start`` (the window's first frame), ``frame`` (the
    reference frame the simulation is at), ``steps``, ``limit`` (steps to the last keyframe),
    ``keyframes`` ``(N, K)`` (clip frames, for renderers too) and ``target`` (index of the next
    keyframe to reach). Device tensors with an on-device environment and library (as imitation)."""

    reward_key = "r_task"
    marker_radius = 0.045  # m, in videos: a keyframe is 21 joint dots, which must read as a pose
    clip_p = ClipProbabilities()  # start-clip probabilities (None: by usable length)

    def __init__(self, cfg: InbetweenTaskConfig, env: HumanoidEnv, lib: ReferenceLibrary, rng):
        check_rate(lib, env.control_hz)
        self.cfg, self.env, self.lib, self.rng = cfg, env, lib, rng
        N, S = env.num_envs, lib.starts
        self.window = max(2, int(round(cfg.window_seconds * env.control_hz)))
        self.min_gap = int(round(cfg.min_keyframe_gap_seconds * env.control_hz))
        for k in (cfg.num_keyframes, cfg.eval_keyframes):
            check_keyframe_count(k, self.window, self.min_gap)
        self._key_dim = 2 * len(env.hum.skeleton.joints) * KEYFRAME_FEATURES
        self.goal_dim = self._key_dim + (cfg.time_encoding_dim if cfg.time_encoding == "concat" else 0)
        i64 = lambda v: like(S, np.full(N, v, dtype=np.int64))  # noqa: E731
        self.clip, self.start, self.frame, self.steps, self.limit, self.target = (i64(v) for v in (0, 0, 0, 0, 1, 1))
        self.set_keyframe_count(cfg.num_keyframes)
        self._goal = like(lib.qpos, np.zeros((N, self.goal_dim)))
        self._host_lengths = host_lengths(lib)  # to check given starts on the host
        self._speed = pose_speed(lib.body_vel)  # (F,) the pose's speed per library frame: the still keyframes

    def set_keyframe_count(self, count: int) -> None:
        """Keyframes per window from now on (e.g. ``cfg.eval_keyframes``); every environment must be
        reset afterwards. The goal does not depend on it."""
        check_keyframe_count(count, self.window, self.min_gap)
        self.num_keyframes = int(count)
        self.keyframes = like(self.lib.starts, np.tile(np.arange(self.num_keyframes, dtype=np.int64),
                                                       (self.env.num_envs, 1)))

    def reset(self, ids, clips=None, frames=None, keyframes=None) -> None:
        """Random clips (by ``clip_p``), window starts and keyframes from the task's generator, unless
        ``clips``/``frames`` (names or indices; window start, 0 by default) or ``keyframes`` (offsets
        within the window, ``(len(ids), num_keyframes)``, starting at 0) are given."""
        L, n, T, K = self.lib, len(ids), self.window, self.num_keyframes
        if clips is None:
            c, f = sample_starts(L, n, self.rng, T - 1, self.clip_p)
        else:
            c, f = given_starts(L, clips, frames, n)
        if keyframes is None and self.cfg.keyframe_selection == "still":
            speed = self._speed[L.frame_index(c[:, None], f[:, None] + like(f, np.arange(T, dtype=np.int64)))]
            off = sample_still_keyframes(self.rng, speed, K, self.min_gap)
        elif keyframes is None:
            off = sample_keyframes(self.rng, n, K, T, self.min_gap)
        else:
            off = np.asarray(keyframes, dtype=np.int64)
            off = np.broadcast_to(off, (n,) + off.shape[-1:]).copy() if off.ndim == 1 else off
            if off.shape != (n, K):
                raise UserError(f"inbetween task: keyframes must have shape ({n}, {K}), got {off.shape}")
            check_keyframes(off, T)
        if not is_tensor(c) or not is_tensor(off):  # given or host windows; device draws fit by construction
            c, f, off = (v.cpu().numpy() if is_tensor(v) else v for v in (c, f, off))
            lengths = self._host_lengths
            bad = (f < 0) | (f + off[:, -1] > lengths[c] - 1)
            if bad.any():
                raise UserError(f"inbetween task: windows from frames {f[bad].tolist()} run past their clips' ends "
                                f"(keyframes to offset {off[bad, -1].tolist()}, clip lengths {lengths[c[bad]].tolist()})")
            c, f, off = like(L.starts, c), like(L.starts, f), like(L.starts, off)
        self.env.set_state(ids, *reference_state(L, c, f))
        self.clip[ids], self.start[ids], self.frame[ids], self.steps[ids] = c, f, f, 0
        self.keyframes[ids] = f[:, None] + off
        self.limit[ids] = off[:, -1]
        self._refresh_goal(ids)

    def _refresh_goal(self, ids) -> None:
        c = self.cfg
        t = self.frame[ids] - self.start[ids]
        keys = self.keyframes[ids]
        nxt = next_keyframe(keys - self.start[ids, None], t)
        self.target[ids] = nxt
        x = xp(keys)
        pair = x.stack([nxt, x.clip(nxt + 1, None, self.num_keyframes - 1)] if c.goal_keyframes == "next"
                       else [nxt - 1, nxt], 1)
        g = keyframe_goal(self.env.bodies.take(ids), reference_bodies(self.lib, self.clip[ids, None],
                                                                      take_along(keys, pair, 1)))
        if c.time_encoding != "none":
            tta = x.clip(take_along(keys, nxt[:, None], 1)[:, 0] - self.frame[ids], 0, None)
            dim = self._key_dim if c.time_encoding == "add" else c.time_encoding_dim
            enc = time_encoding(tta, dim, max(self.window - 4, 0), g.dtype if is_tensor(g) else None)
            g = g + enc if c.time_encoding == "add" else x.concatenate([g, enc], 1)
        self._goal[ids] = g

    def goal(self):
        return copy(self._goal)

    def keyframe_bodies(self) -> Bodies:
        """Reference bodies ``(N, K, J, .)`` of every environment's keyframes."""
        return reference_bodies(self.lib, self.clip[:, None], self.keyframes)

    def step_limit(self):
        return self.limit

    def for_evaluation(self) -> None:
        """The evaluation's keyframe count (Table 2's 5 per window), so a video shows what is measured."""
        self.set_keyframe_count(self.cfg.eval_keyframes)

    def markers(self) -> np.ndarray:
        """``(N, J, 3)`` world body positions of the next keyframe to reach, for videos."""
        g = self.lib.frame_index(self.clip, take_along(self.keyframes, self.target[:, None], 1)[:, 0])
        m = self.lib.body_pos[g]
        return m.cpu().numpy() if is_tensor(m) else m

    def next_reference(self):
        """``(qpos, qvel)`` of the reference frame the coming step should reach (the action base)."""
        g = self.lib.frame_index(self.clip, self.frame + 1)
        return self.lib.qpos[g], self.lib.qvel[g]

    def update(self, diverged, invalid):
        env, L, c = self.env, self.lib, self.cfg
        self.frame += 1
        self.steps += 1
        g = L.frame_index(self.clip, self.frame)
        sim, ref = env.bodies, reference_bodies(L, self.clip, self.frame)
        err = inbetween_errors(sim.pos, ref.pos, env.qpos[:, 7:], L.qpos[g, 7:], env.qvel[:, 6:], L.qvel[g, 6:],
                               env.end_effectors)
        dist = body_distances(sim, ref)
        x = xp(dist)
        off_track = tracking_failure(dist, c.termination, c.termination_distance)
        fell = off_track if c.early_termination else x.zeros_like(diverged)
        rewards, terminated, truncated = end_of_step(inbetween_reward(err, c.reward), fell, diverged, invalid,
                                                     self.steps, self.limit)
        hit = self.keyframes[:, 1:] == self.frame[:, None]  # the start keyframe is no target
        info = {"clip": copy(self.clip), "frame": copy(self.frame), "at_keyframe": hit.any(1),
                "keyframe_index": x.where(hit.any(1), (hit * 1).argmax(1) + 1, -1),
                "max_body_error": x.amax(dist, -1), "mean_body_error": dist.mean(-1), "off_track": off_track,
                "diverged": diverged,
                "invalid_action": invalid, "episode_steps": copy(self.steps)}
        self._refresh_goal(slice(None))
        return rewards, terminated, truncated, info


def evaluate_inbetween(mdp: TaskEnv, act: Act, episodes: int) -> dict:
    """Table 2 protocol: ``episodes`` 4 s windows with ``cfg.eval_keyframes`` keyframes each (5,
    where training uses 4), played to their end, errors over all frames and at the target
    keyframes. The task's keyframe count and early termination are restored afterwards and every
    environment reset."""
    task = mdp.task
    if not isinstance(task, InbetweenTask):
        raise UserError(f"evaluate_inbetween needs a TaskEnv around an InbetweenTask, got {type(task).__name__}")
    before = task.num_keyframes
    task.set_keyframe_count(task.cfg.eval_keyframes)
    try:
        with whole_episodes(task):
            out = reference_errors(mdp, act, episodes, EpisodeErrors(mdp.num_envs))
    finally:
        task.set_keyframe_count(before)
        mdp.reset()
    return {"keyframes_per_window": int(task.cfg.eval_keyframes), **out}


# appendix C.1, Table 2; Table 6: one active codebook (the authors' code: num_quants 1)
SPEC = TaskSpec("inbetween", InbetweenTaskConfig, InbetweenTask, evaluate_inbetween, codebooks=1)
