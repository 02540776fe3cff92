"""The head-mounted-device tracking task (hybrid-latent paper, appendix C.2): follow a reference
head trajectory, as a VR headset reports it, with the whole body.

* reset: a random clip and start frame (clips drawn in proportion to their usable length) or given
  ones; the start state is the reference there (``mdp.resets``);
* goal: the head's position, rotation, velocity and angular velocity differences to the next
  ``goal_frames`` reference frames (5: the frame the coming step reaches and 4 after it) in the
  root's heading frame (``mdp.head.head_goal``);
* reward: the head-only PHC-form reward against the reference head (``mdp.head.head_reward``),
  0 after a diverged simulation or an invalid action;
* terminated: the head more than ``termination_distance`` from the reference head (1 m, the
  paper's; the fork's recipe uses 1.5 m), a diverged simulation or an invalid action;
  truncated: ``episode_seconds`` (5 s) played, or the clip's end for a given start near it.
  ``info["off_track"]`` is the head test whether or not it ends the episode (``early_termination``).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from motok.arrays import copy, is_tensor, like, xp
from motok.control.mdp.head import HEAD_FEATURES, HeadRewardConfig, head_distance, head_errors, head_goal, \
    head_lost, head_reward
from motok.control.mdp.resets import (ClipProbabilities, check_rate, check_start_frames, given_starts, host_lengths,
                                      reference_bodies, reference_state, sample_starts)
from motok.control.mdp.task_env import Task, TaskEnv
from motok.control.mdp.terminations import body_distances, end_of_step
from motok.control.tasks.episodes import Act, EpisodeErrors, reference_errors, whole_episodes
from motok.control.tasks.registry import TaskSpec
from motok.errors import UserError
from motok.ranges import In
from motok.sim.env import HumanoidEnv
from motok.sim.reference import ReferenceLibrary


@dataclass
class HMDTaskConfig:
    episode_seconds: In[float, "> 0"] = 5.0  # an episode's length (a head trajectory)
    goal_frames: In[int, ">= 1"] = 5  # reference head frames ahead in the goal (the fork's numNextObsSteps)
    termination_distance: In[float, "> 0"] = 1.0  # m, head to reference head (paper C.2; the fork's recipe: 1.5)
    early_termination: bool = True  # off track ends the episode (false: info["off_track"] only)
    reward: HeadRewardConfig = field(default_factory=HeadRewardConfig)  # the head reward's weights and exponents

    def __post_init__(self):
        if not self.episode_seconds > 0:
            raise UserError(f"hmd task: episode_seconds must be > 0, got {self.episode_seconds}")
        if self.goal_frames < 1:
            raise UserError(f"hmd task: goal_frames must be >= 1, got {self.goal_frames}")
        if not self.termination_distance > 0:
            raise UserError(f"hmd task: termination_distance must be > 0, got {self.termination_distance}")


class HMDTask(Task):
    """Episode state per environment: ``clip``, ``start``, ``frame`` (the reference frame the
    simulation is at), ``steps``, ``limit``; ``head`` is the tracked body (the skeleton's head).
    Device tensors with an on-device environment and library (as the imitation task)."""

    reward_key = "r_task"
    clip_p = ClipProbabilities()  # start-clip probabilities (None: by usable length)

    def __init__(self, cfg: HMDTaskConfig, env: HumanoidEnv, lib: ReferenceLibrary, rng):
        check_rate(lib, env.control_hz)
        self.cfg, self.env, self.lib, self.rng = cfg, env, lib, rng
        N, S = env.num_envs, lib.starts
        self.max_steps = max(1, int(round(cfg.episode_seconds * env.control_hz)))
        self.head = int(env.hum.skeleton.head)
        self.goal_dim = cfg.goal_frames * HEAD_FEATURES
        i64 = lambda v: like(S, np.full(N, v, dtype=np.int64))  # noqa: E731
        self.clip, self.start, self.frame, self.steps, self.limit = i64(0), i64(0), i64(0), i64(0), i64(1)
        self._goal = like(lib.qpos, np.zeros((N, self.goal_dim)))
        self._window = like(S, np.arange(cfg.goal_frames + 1))  # the frame reached and the K ahead
        self._host_lengths = host_lengths(lib)  # to check given starts on the host

    def _ahead(self, ids):
        return self.frame[ids, None] + self._window[1:]

    def reset(self, ids, clips=None, frames=None) -> None:
        """Random clips (by ``clip_p``) and start frames leaving a whole episode from the task's
        generator, unless ``clips``/``frames`` (names or indices; frame 0 by default) are given."""
        K, L = self.cfg.goal_frames, self.lib
        if clips is None:
            c, f = sample_starts(L, len(ids), self.rng, self.max_steps + K, self.clip_p)
        else:
            c, f = given_starts(L, clips, frames, len(ids))
        if not is_tensor(c):  # host draws and given starts; a device draw gives no weight to too-short clips
            check_start_frames(L, c, f, K, self._host_lengths)
            c, f = like(L.starts, c), like(L.starts, f)
        self.env.set_state(ids, *reference_state(L, c, f))
        self.clip[ids], self.start[ids], self.frame[ids], self.steps[ids] = c, f, f, 0
        # The last step's goal still reads K real frames ahead: frame + K <= the clip's last frame.
        self.limit[ids] = xp(f).clip(L.lengths[c] - 1 - f - K, None, self.max_steps)
        ahead = reference_bodies(L, self.clip[ids, None], self._ahead(ids))
        self._goal[ids] = head_goal(self.env.bodies.take(ids), ahead, self.head)

    def goal(self):
        return copy(self._goal)

    def step_limit(self):
        return self.limit

    def markers(self) -> np.ndarray:
        """``(N, 1, 3)`` the reference head at the current frame (world), for videos."""
        m = self.lib.body_pos[self.lib.frame_index(self.clip, self.frame), self.head][:, None]
        return m.cpu().numpy() if is_tensor(m) else m

    def next_reference(self):
        """``(qpos, qvel)`` of the reference frame the coming step should reach (the action base)."""
        g = self.lib.frame_index(self.clip, self.frame + 1)
        return self.lib.qpos[g], self.lib.qvel[g]

    def update(self, diverged, invalid):
        env, c = self.env, self.cfg
        self.frame += 1
        self.steps += 1
        refs = reference_bodies(self.lib, self.clip[:, None], self.frame[:, None] + self._window)
        sim, ref = env.bodies, refs.take((slice(None), 0))
        dist = head_distance(sim.pos, ref.pos, self.head)
        off_track = head_lost(dist, c.termination_distance)
        lost = off_track if c.early_termination else xp(dist).zeros_like(diverged)
        rewards, terminated, truncated = end_of_step(head_reward(head_errors(sim, ref, self.head), c.reward), lost,
                                                     diverged, invalid, self.steps, self.limit)
        self._goal = head_goal(sim, refs.take((slice(None), slice(1, None))), self.head)
        info = {"clip": copy(self.clip), "frame": copy(self.frame), "head_error": dist,
                "mean_body_error": body_distances(sim, ref).mean(-1), "head_lost": lost, "off_track": off_track,
                "diverged": diverged,
                "invalid_action": invalid, "episode_steps": copy(self.steps)}
        return rewards, terminated, truncated, info


def evaluate_hmd(mdp: TaskEnv, act: Act, episodes: int) -> dict:
    """Table 3 protocol: ``episodes`` 5 s head trajectories, played to their end, full-body errors
    over all frames plus the head's own error and the share of frames it stayed within the
    termination distance. Early termination is restored afterwards."""
    task = mdp.task
    if not isinstance(task, HMDTask):
        raise UserError(f"evaluate_hmd needs a TaskEnv around an HMDTask, got {type(task).__name__}")
    with whole_episodes(task):
        out = reference_errors(mdp, act, episodes, EpisodeErrors(mdp.num_envs, head=task.head,
                                                     within=task.cfg.termination_distance))
    return {k: v for k, v in out.items() if not k.startswith("keyframe_")} | \
        {"per_episode": {k: v for k, v in out["per_episode"].items() if not k.startswith("keyframe_")}}


# appendix C.2, Table 3; Table 7: two active codebooks (the authors' code: num_quants 2)
SPEC = TaskSpec("hmd", HMDTaskConfig, HMDTask, evaluate_hmd, codebooks=2)
