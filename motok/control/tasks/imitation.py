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

from motok.arrays import copy, is_tensor, like, xp
from motok.control.mdp.observations import imitation_goal
from motok.control.mdp.resets import (ClipProbabilities, check_rate, check_start_frames, given_starts, host_lengths,
                                      reference_bodies, reference_state, sample_starts)
from motok.control.mdp.rewards import ImitationConfig, feet_error, imitation_errors, imitation_reward
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
    """Episode state: ``clip``, ``frame`` (the reference frame the simulation is at), ``steps``, ``limit``.

    With a library moved to a device (``ReferenceLibrary.to``), an ``on_device`` environment and a
    ``torch.Generator`` on that device as ``rng``, the episode state and every term are device
    tensors (the same code, :mod:`motok.arrays`)."""

    reward_key = "r_im"
    clip_p = ClipProbabilities()  # start-clip probabilities (None: by usable length)

    def __init__(self, cfg: ImitationTaskConfig, env: HumanoidEnv, lib: ReferenceLibrary, rng):
        check_rate(lib, env.control_hz)
        if is_tensor(lib.starts) != env.on_device:
            raise UserError("the reference library and the environment must both be on the device or both on the host")
        self.cfg, self.env, self.lib, self.rng = cfg, env, lib, rng
        N, K, S = env.num_envs, cfg.goal_frames, lib.starts
        self.max_steps = max(1, int(round(cfg.max_episode_seconds * env.control_hz)))
        self.goal_dim = K * len(env.hum.skeleton.joints) * 15
        self.clip, self.frame = like(S, np.zeros(N, dtype=np.int64)), like(S, np.zeros(N, dtype=np.int64))
        self.steps, self.limit = like(S, np.zeros(N, dtype=np.int64)), like(S, np.ones(N, dtype=np.int64))
        self._goal = like(lib.qpos, np.zeros((N, self.goal_dim)))
        self._window = like(S, np.arange(K + 1))  # the reference frame reached and the K the goal looks ahead to
        self._host_lengths = host_lengths(lib)  # to check given starts on the host
        sk = env.hum.skeleton
        self._feet = [*sk.feet_left, *sk.feet_right]  # ankles and toes: the foot-velocity term's bodies

    def reference(self, clips, frames) -> Bodies:
        """Reference body states at ``frames`` of ``clips`` (clamped to each clip's last frame)."""
        return reference_bodies(self.lib, clips, frames)

    def _ahead(self, ids):
        return self.frame[ids, None] + self._window[1:]

    def reset(self, ids, clips=None, frames=None) -> None:
        """Random clips (by ``clip_p``) and frames from the task's generator, unless
        ``clips``/``frames`` (names or indices) are given."""
        K, L = self.cfg.goal_frames, self.lib
        if clips is None:
            c, f = sample_starts(L, len(ids), self.rng, K + 1, self.clip_p)
        else:
            c, f = given_starts(L, clips, frames, len(ids))
            check_start_frames(L, c, f, K, self._host_lengths)
            c, f = like(L.starts, c), like(L.starts, f)
        self.env.set_state(ids, *reference_state(L, c, f))
        self.clip[ids], self.frame[ids], self.steps[ids] = c, f, 0
        # The last step's goal still needs K frames ahead: frame + K <= last frame of the clip.
        self.limit[ids] = xp(f).clip(L.lengths[c] - 1 - f - K, None, self.max_steps)
        self._goal[ids] = imitation_goal(self.env.bodies.take(ids), self.reference(self.clip[ids, None], self._ahead(ids)))

    def goal(self):
        return copy(self._goal)

    def next_reference(self):
        """``(qpos, qvel)`` of the reference frame the coming step should reach (the action base)."""
        g = self.lib.frame_index(self.clip, self.frame + 1)
        return self.lib.qpos[g], self.lib.qvel[g]

    def current_reference_qpos(self):
        return self.lib.qpos[self.lib.frame_index(self.clip, self.frame)]

    def update(self, diverged, invalid):
        env, L, c = self.env, self.lib, self.cfg
        self.frame += 1
        self.steps += 1
        refs = self.reference(self.clip[:, None], self.frame[:, None] + self._window)
        sim = env.bodies
        self._goal = imitation_goal(sim, refs.take((slice(None), slice(1, None))))
        ref = refs.take((slice(None), 0))
        g = L.frame_index(self.clip, self.frame)
        err = imitation_errors(sim.pos, ref.pos, env.qpos[:, 7:], L.qpos[g, 7:], env.qvel[:, 6:], L.qvel[g, 6:],
                               env.end_effectors)
        if c.reward.k_feet > 0:
            err["feet"] = feet_error(sim.vel, ref.vel, self._feet)
        dist = body_distances(sim, ref)
        fell = tracking_failure(dist, c.termination, c.termination_distance) if c.early_termination \
            else xp(dist).zeros_like(diverged)
        rewards, terminated, truncated = end_of_step(imitation_reward(err, c.reward), fell, diverged, invalid,
                                                     self.steps, self.limit)
        info = {"clip": copy(self.clip), "frame": copy(self.frame), "max_body_error": xp(dist).amax(dist, -1),
                "mean_body_error": dist.mean(-1), "diverged": diverged, "invalid_action": invalid,
                "episode_steps": copy(self.steps)}
        return rewards, terminated, truncated, info
