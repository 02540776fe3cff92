"""The imitation task: track reference clips (hybrid-latent paper section 4.3 / appendix B.2).

* reset: reference state initialisation (``mdp.resets``) at a random clip and frame (clips drawn
  in proportion to their usable length) or at given ones;
* goal: Eq. 9 differences to the next K reference frames (``mdp.observations.imitation_goal``);
* reward: Eq. 10, the product form (``mdp.rewards.imitation_reward``), 0 after a diverged
  simulation or an invalid action;
* terminated: early termination when the bodies are too far from the reference
  (``mdp.terminations.tracking_failure``), a diverged simulation or an invalid action;
  truncated: the time limit or the end of the clip (one step before the goal runs out of frames).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from motok.control.mdp.observations import imitation_goal
from motok.control.mdp.resets import (check_rate, check_start_frames, given_starts, reference_bodies, reference_state,
                                      sample_starts)
from motok.control.mdp.rewards import ImitationConfig, imitation_errors, imitation_reward
from motok.control.mdp.terminations import MODES, body_distances, end_of_step, tracking_failure
from motok.errors import UserError
from motok.sim.env import HumanoidEnv
from motok.sim.obs import Bodies
from motok.sim.reference import ReferenceLibrary


@dataclass
class ImitationTaskConfig:
    max_episode_seconds: float = 10.0
    goal_frames: int = 1  # K reference frames ahead in the goal (Eq. 9)
    termination: str = "any"  # "any" body beyond the distance, or the "mean" over bodies (PHC's failure test)
    termination_distance: float = 0.5  # m, from the reference
    early_termination: bool = True
    reward: ImitationConfig = field(default_factory=ImitationConfig)

    def __post_init__(self):
        if self.termination not in MODES:
            raise UserError(f"termination must be 'any' or 'mean', not {self.termination!r}")


class ImitationTask:
    """Episode state: ``clip``, ``frame`` (the reference frame the simulation is at), ``steps``, ``limit``."""

    reward_key = "r_im"

    def __init__(self, cfg: ImitationTaskConfig, env: HumanoidEnv, lib: ReferenceLibrary, rng: np.random.Generator):
        check_rate(lib, env.control_hz)
        self.cfg, self.env, self.lib, self.rng = cfg, env, lib, rng
        N = env.num_envs
        self.max_steps = max(1, int(round(cfg.max_episode_seconds * env.control_hz)))
        self.goal_dim = cfg.goal_frames * len(env.hum.skeleton.joints) * 15
        self.clip, self.frame = np.zeros(N, dtype=np.int64), np.zeros(N, dtype=np.int64)
        self.steps, self.limit = np.zeros(N, dtype=np.int64), np.ones(N, dtype=np.int64)
        self._goal = np.zeros((N, self.goal_dim))
        self.clip_p: np.ndarray | None = None  # start-clip probabilities (None: by usable length)

    def reference(self, clips: np.ndarray, frames: np.ndarray) -> Bodies:
        """Reference body states at ``frames`` of ``clips`` (clamped to each clip's last frame)."""
        return reference_bodies(self.lib, clips, frames)

    def _ahead(self, ids) -> np.ndarray:
        return self.frame[ids, None] + np.arange(1, self.cfg.goal_frames + 1)

    def reset(self, ids: np.ndarray, clips=None, frames=None) -> None:
        """Random clips (by ``clip_p``) and frames from the task's generator, unless
        ``clips``/``frames`` (names or indices) are given."""
        K, L = self.cfg.goal_frames, self.lib
        if clips is None:
            c, f = sample_starts(L, len(ids), self.rng, K + 1, self.clip_p)
        else:
            c, f = given_starts(L, clips, frames, len(ids))
            check_start_frames(L, c, f, K)
        self.env.set_state(ids, *reference_state(L, c, f))
        self.clip[ids], self.frame[ids], self.steps[ids] = c, f, 0
        # The last step's goal still needs K frames ahead: frame + K <= last frame of the clip.
        self.limit[ids] = np.minimum(self.max_steps, L.lengths[c] - 1 - f - K)
        self._goal[ids] = imitation_goal(self.env.bodies.take(ids), self.reference(self.clip[ids, None], self._ahead(ids)))

    def goal(self) -> np.ndarray:
        return self._goal.copy()

    def next_reference(self) -> tuple[np.ndarray, np.ndarray]:
        """``(qpos, qvel)`` of the reference frame the coming step should reach (the action base)."""
        g = self.lib.frame_index(self.clip, self.frame + 1)
        return self.lib.qpos[g], self.lib.qvel[g]

    def current_reference_qpos(self) -> np.ndarray:
        return self.lib.qpos[self.lib.frame_index(self.clip, self.frame)]

    def update(self, diverged: np.ndarray, invalid: np.ndarray):
        env, L, c = self.env, self.lib, self.cfg
        self.frame += 1
        self.steps += 1
        N = env.num_envs
        refs = self.reference(self.clip[:, None], self.frame[:, None] + np.arange(c.goal_frames + 1))
        sim = env.bodies
        self._goal = imitation_goal(sim, refs.take((slice(None), slice(1, None))))
        ref = refs.take((slice(None), 0))
        g = L.frame_index(self.clip, self.frame)
        err = imitation_errors(sim.pos, ref.pos, env.qpos[:, 7:], L.qpos[g, 7:], env.qvel[:, 6:], L.qvel[g, 6:],
                               env.end_effectors)
        dist = body_distances(sim, ref)
        fell = tracking_failure(dist, c.termination, c.termination_distance) if c.early_termination \
            else np.zeros(N, dtype=bool)
        rewards, terminated, truncated = end_of_step(imitation_reward(err, c.reward), fell, diverged, invalid,
                                                     self.steps, self.limit)
        info = {"clip": self.clip.copy(), "frame": self.frame.copy(), "max_body_error": dist.max(-1),
                "mean_body_error": dist.mean(-1), "diverged": diverged, "invalid_action": invalid,
                "episode_steps": self.steps.copy()}
        return rewards, terminated, truncated, info
