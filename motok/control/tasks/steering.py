"""The steering task: walk in a commanded heading at a commanded speed, the command changing every
few seconds (the heading task of AMP and ASE, ProtoMotions' steering).

* reset: reference state initialisation (``mdp.resets``) at a random clip and frame; no reference
  motion is used after that. A first command: a heading uniform on the circle (world frame) and a
  speed uniform in ``[min_speed, max_speed]``;
* a new command every ``min_command_seconds`` to ``max_command_seconds`` (uniform), drawn as the
  first; the step's reward and ``info`` are those of the command the action was chosen for, the
  goal returned after it already shows the new one;
* goal: the command in the root's heading frame (yaw only), 3 numbers: the commanded direction's
  ``x`` (ahead) and ``y`` (left) and the speed (m/s);
* reward: ``w_vel exp(-k_vel |v* - v|^2) + w_face max(0, cos(psi* - psi))``, ``v*`` the commanded
  planar velocity, ``v`` the root's planar velocity, ``psi`` the root's heading, ``psi*`` the
  commanded one (:func:`steering_reward`); 0 after a diverged simulation or an invalid action;
* terminated: the head below ``fall_height`` (not on the first step), a diverged simulation or an
  invalid action; truncated: ``episode_seconds``.

Evaluation (:func:`evaluate_steering`): over every step at least ``settle_seconds`` after its
command appeared (time to turn and to reach the speed), the heading error (deg, the root's facing
to the commanded heading), the direction error (deg, the direction of travel to the commanded
heading, on steps moving faster than 0.2 m/s), the speed error (m/s, planar speed to commanded
speed) and the velocity error ``|v* - v|`` (m/s); falls per episode; the main reward per step.
A video draws the command as an arrow from the root, as long as the speed is fast (1 m per m/s).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from motok.arrays import copy, is_tensor, like, xp
from motok.control.mdp.navigation import head_fall, root_heading
from motok.control.mdp.resets import free_starts, reference_state
from motok.control.mdp.task_env import Task, TaskEnv
from motok.control.mdp.terminations import end_of_step
from motok.control.tasks.episodes import Act, Step, play_episodes
from motok.control.tasks.registry import TaskSpec
from motok.errors import UserError
from motok.ranges import In
from motok.sim.env import HumanoidEnv
from motok.sim.reference import ReferenceLibrary

MOVING = 0.2  # m/s: slower than this, the direction of travel is noise (the direction error skips the step)


@dataclass
class SteeringTaskConfig:
    episode_seconds: In[float, "> 0"] = 10.0  # an episode's length (several commands)
    min_command_seconds: In[float, "> 0"] = 2.0  # a command lasts between these (uniform) before the next
    max_command_seconds: In[float, "> 0"] = 5.0  # the longest a command lasts (>= min_command_seconds)
    min_speed: In[float, ">= 0"] = 0.5  # m/s, the commanded speed is uniform between these
    max_speed: In[float, ">= 0"] = 1.5  # the data's walks: about 1.1 m/s
    k_vel: In[float, ">= 0"] = 0.25  # exp(-k_vel |v* - v|^2), (s/m)^2 (ASE's heading task: 0.25)
    w_vel: In[float, ">= 0"] = 0.7  # weight of the velocity term
    w_face: In[float, ">= 0"] = 0.3  # weight of the facing term max(0, cos(psi* - psi))
    fall_height: In[float, "> 0"] = 0.5  # m, head height below which the character has fallen
    early_termination: bool = True  # a fall ends the episode
    settle_seconds: In[float, ">= 0"] = 1.0  # evaluation: errors count from this long after a command appeared

    def __post_init__(self):
        for name in ("episode_seconds", "min_command_seconds", "fall_height"):
            if not getattr(self, name) > 0:
                raise UserError(f"steering task: {name} must be > 0, got {getattr(self, name)}")
        for name in ("min_speed", "k_vel", "w_vel", "w_face", "settle_seconds"):
            if not getattr(self, name) >= 0:
                raise UserError(f"steering task: {name} must be >= 0, got {getattr(self, name)}")
        if self.max_command_seconds < self.min_command_seconds or self.max_speed < self.min_speed:
            raise UserError("steering task: need min_command_seconds <= max_command_seconds and "
                            "min_speed <= max_speed")


def command_goal(c, s, heading, speed):
    """``(N, 3)``: the commanded direction in the heading frame of a root whose heading has cosine
    ``c`` and sine ``s`` (``x`` ahead, ``y`` on its left), and the commanded speed."""
    x = xp(heading)
    ch, sh = x.cos(heading), x.sin(heading)
    return x.stack([c * ch + s * sh, c * sh - s * ch, speed], -1)


def steering_reward(root_vel, c, s, heading, speed, cfg) -> dict:
    """``{"r_task", "r_vel", "r_face"}``, each ``(N,)``: the velocity term against the commanded
    planar velocity and the facing term (the module docstring). ``root_vel`` world ``(N, >= 2)``."""
    x = xp(heading)
    ch, sh = x.cos(heading), x.sin(heading)
    err = (speed * ch - root_vel[:, 0]) ** 2 + (speed * sh - root_vel[:, 1]) ** 2
    r_vel = x.exp(-cfg.k_vel * err)
    r_face = x.clip(c * ch + s * sh, 0.0, None)
    return {"r_task": cfg.w_vel * r_vel + cfg.w_face * r_face, "r_vel": r_vel, "r_face": r_face}


def angle_between(c, s, heading):
    """``(N,)`` degrees in [0, 180] between a direction of cosine ``c`` and sine ``s`` and ``heading`` (rad)."""
    x = xp(heading)
    ch, sh = x.cos(heading), x.sin(heading)
    return x.abs(x.arctan2(c * sh - s * ch, c * ch + s * sh)) * (180.0 / math.pi)


def _uniform(rng, n: int, like_array):
    """``(n,)`` uniform draws in [0, 1) from numpy's generator, or a ``torch.Generator`` for tensors."""
    if is_tensor(like_array):
        import torch

        return torch.rand(n, generator=rng, device=like_array.device, dtype=like_array.dtype)
    return rng.random(n)


class SteeringTask(Task):
    """Episode state per environment: ``heading`` (rad, world) and ``speed`` (m/s) of the command,
    ``steps`` since the reset, ``command_steps`` since the command appeared, ``command_limit``
    (its length in steps). Device tensors with an on-device environment, a library moved to its
    device and a ``torch.Generator`` there (new commands are then drawn for every environment and
    kept where one is due, so no mask is read on the host)."""

    goal_dim = 3
    reward_key = "r_task"
    marker_radius = 0.04  # m: the arrow's dots
    joins_mid_episode = True  # a command needs no start state

    def __init__(self, cfg: SteeringTaskConfig, env: HumanoidEnv, lib: ReferenceLibrary, rng):
        self.cfg, self.env, self.lib, self.rng = cfg, env, lib, rng
        N, S, hz = env.num_envs, lib.starts, env.control_hz
        self.max_steps = max(1, int(round(cfg.episode_seconds * hz)))
        self.command_range = (max(1, int(round(cfg.min_command_seconds * hz))),
                              max(1, int(round(cfg.max_command_seconds * hz))))
        self.head = int(env.hum.skeleton.head)
        i64 = lambda v: like(S, np.full(N, v, dtype=np.int64))  # noqa: E731
        self.steps, self.command_steps, self.command_limit = i64(0), i64(0), i64(1)
        self.heading, self.speed = like(env.bodies.pos, np.zeros(N)), like(env.bodies.pos, np.zeros(N))
        self._goal = like(env.bodies.pos, np.zeros((N, 3)))

    def _draw(self, n: int):
        """``n`` commands: heading (rad), speed (m/s), length (steps)."""
        c, ref = self.cfg, self.heading
        heading = 2.0 * math.pi * _uniform(self.rng, n, ref)
        speed = c.min_speed + (c.max_speed - c.min_speed) * _uniform(self.rng, n, ref)
        lo, hi = self.command_range
        length = lo + xp(ref).floor((hi - lo + 1) * _uniform(self.rng, n, ref))
        return heading, speed, length.long() if is_tensor(length) else length.astype(np.int64)

    def _new_commands(self, ids) -> None:
        self.heading[ids], self.speed[ids], self.command_limit[ids] = self._draw(len(self.heading[ids]))
        self.command_steps[ids] = 0

    def _refresh_goal(self) -> None:
        c, s = root_heading(self.env.bodies.rot[:, 0])
        self._goal = command_goal(c, s, self.heading, self.speed)

    def set_commands(self, ids, heading, speed) -> None:
        """Command ``heading`` (rad, world) and ``speed`` (m/s) to ``ids`` (scripted evaluations,
        tests); their command clocks restart."""
        ids = like(self.steps, np.atleast_1d(np.asarray(ids, dtype=np.int64)))
        self.heading[ids], self.speed[ids] = like(self.heading, heading), like(self.speed, speed)
        self.command_steps[ids] = 0
        self._refresh_goal()

    def reset(self, ids, clips=None, frames=None) -> None:
        """Reference starts at random clips and frames from the task's generator (or the given
        ``clips``, frame ``frames`` or 0), then a first command."""
        L = self.lib
        c, f = free_starts(L, len(ids), self.rng, clips, frames, "steering task")
        self.env.set_state(ids, *reference_state(L, c, f))
        self.steps[ids] = 0
        self._new_commands(ids)
        self._refresh_goal()

    def join(self, ids) -> None:
        """A first command to ``ids``, their episode clock restarted."""
        ids = like(self.steps, np.atleast_1d(np.asarray(ids, dtype=np.int64)))
        self.steps[ids] = 0
        self._new_commands(ids)
        self._refresh_goal()

    def goal(self):
        return copy(self._goal)

    def step_limit(self) -> int:
        return self.max_steps

    def markers(self) -> np.ndarray:
        """``(N, 10, 3)``: the command as an arrow from the root just above the floor, 1 m long per
        m/s: a shaft of 8 dots and two barbs at the tip."""
        host = lambda a: a.cpu().numpy() if is_tensor(a) else np.asarray(a)  # noqa: E731
        h, v = host(self.heading), host(self.speed)
        root = host(self.env.bodies.pos[:, 0])[:, :2]
        d = np.stack([np.cos(h), np.sin(h)], -1)
        shaft = root[:, None] + np.linspace(0.2, 1.0, 8)[None, :, None] * (v[:, None] * d)[:, None]
        tip = root + v[:, None] * d
        barbs = np.stack([tip - 0.2 * np.stack([np.cos(h + a), np.sin(h + a)], -1) for a in (0.5, -0.5)], 1)
        pts = np.concatenate([shaft, barbs], 1)
        return np.concatenate([pts, np.full(pts.shape[:2] + (1,), 0.1)], -1)

    def update(self, diverged, invalid):
        env, c = self.env, self.cfg
        self.steps += 1
        self.command_steps += 1
        b = env.bodies
        x = xp(b.pos)
        ch, sh = root_heading(b.rot[:, 0])  # matrices: no quaternion conversion of every body
        vel = b.vel[:, 0]
        down, fell = head_fall(b.pos[:, self.head, 2], self.steps, c)
        rewards, terminated, truncated = end_of_step(steering_reward(vel, ch, sh, self.heading, self.speed, c), fell,
                                                     diverged, invalid, self.steps, self.max_steps)
        speed = x.hypot(vel[:, 0], vel[:, 1])
        moving = x.clip(speed, 1e-9, None)
        v_err = x.hypot(self.speed * x.cos(self.heading) - vel[:, 0], self.speed * x.sin(self.heading) - vel[:, 1])
        info = {"heading_error_deg": angle_between(ch, sh, self.heading),
                "direction_error_deg": angle_between(vel[:, 0] / moving, vel[:, 1] / moving, self.heading),
                "moving": speed > MOVING, "speed_error": x.abs(speed - self.speed), "velocity_error": v_err,
                "command_steps": copy(self.command_steps), "fell": down, "diverged": diverged,
                "invalid_action": invalid, "episode_steps": copy(self.steps)}
        # A command that has run its length is replaced, unless the episode ends: drawn for every
        # environment and kept where due, so a device rollout reads no mask on the host.
        due = (self.command_steps >= self.command_limit) & ~(terminated | truncated)
        heading, speed_new, length = self._draw(len(self.heading))
        self.heading = x.where(due, heading, self.heading)
        self.speed = x.where(due, speed_new, self.speed)
        self.command_limit = x.where(due, length, self.command_limit)
        self.command_steps = x.where(due, 0, self.command_steps)
        self._refresh_goal()
        return rewards, terminated, truncated, info


# ---------------------------------------------------------------------- evaluation

ERRORS = ("heading_error_deg", "direction_error_deg", "speed_error", "velocity_error")


def evaluate_steering(mdp: TaskEnv, act: Act, episodes: int) -> dict:
    """Run ``act`` on ``mdp`` from fresh episodes until ``episodes`` have ended (the task's
    generator draws the starts and commands). Returns ``episodes``, ``falls_per_episode``,
    ``diverged``, ``mean_reward`` (the main term per step), ``steps_measured`` and, over the steps
    at least ``settle_seconds`` into their command, ``<error>_mean`` and ``<error>_median`` of
    the heading, direction (moving steps only), speed and velocity errors (NaN with no step)."""
    task = mdp.task
    if not isinstance(task, SteeringTask):
        raise UserError(f"evaluate_steering needs a TaskEnv around a SteeringTask, got {type(task).__name__}")
    settle = int(round(task.cfg.settle_seconds * mdp.env.control_hz))
    vals = {k: [] for k in ERRORS}
    c = dict(falls=0, diverged=0, steps=0, measured=0, reward=0.0)

    def on_step(s: Step) -> None:
        info, live = s.info, s.live
        keep = live & (np.asarray(info["command_steps"]) > settle) & ~np.asarray(info["diverged"])
        for k in ERRORS:
            vals[k].append(np.asarray(info[k])[keep & (info["moving"] if k == "direction_error_deg" else True)])
        c["measured"] += int(keep.sum())
        c["falls"] += int((info["fell"] & s.terminated & live).sum())
        c["diverged"] += int((info["diverged"] & live).sum())
        c["reward"] += float(s.rewards[task.reward_key][live].sum())
        c["steps"] += int(live.sum())

    play_episodes(mdp, act, episodes, on_step)
    out = {"episodes": int(episodes), "falls_per_episode": c["falls"] / int(episodes), "diverged": c["diverged"],
           "mean_reward": c["reward"] / max(c["steps"], 1), "steps_measured": c["measured"]}
    for k in ERRORS:
        v = np.concatenate(vals[k])
        out[f"{k}_mean"] = float(v.mean()) if len(v) else float("nan")
        out[f"{k}_median"] = float(np.median(v)) if len(v) else float("nan")
    return out


SPEC = TaskSpec("steering", SteeringTaskConfig, SteeringTask, evaluate_steering)
