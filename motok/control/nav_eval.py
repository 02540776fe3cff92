"""Evaluation of a navigation policy (hybrid-latent paper, appendix C.3): how many targets are
reached before they change, how fast, how often the character falls, and how still it stands
once there (the idle phase)."""

from __future__ import annotations

from typing import Callable

import numpy as np

from motok.control.tasks.base import TaskEnv
from motok.control.tasks.navigation import NavigationTask
from motok.errors import UserError


def episode_quota(episodes: int, num_envs: int) -> np.ndarray:
    """Episodes each environment contributes, ``episodes`` in all. A fixed share per environment,
    not the first ``episodes`` to end: those would over-count short (fallen) episodes."""
    return episodes // num_envs + (np.arange(num_envs) < episodes % num_envs)


def evaluate_navigation(mdp: TaskEnv, act: Callable[[np.ndarray, np.ndarray], np.ndarray], episodes: int) -> dict:
    """Run ``act(obs, goal) -> actions`` (numpy, all environments at once) on ``mdp`` from fresh
    episodes until ``episodes`` have ended; the task's generator draws the starts and targets.

    A target counts as reached if the root came within the reach radius while it was current; one
    cut short by a fall counts as missed. Returns ``episodes``, ``targets``, ``reached_share``,
    ``time_to_reach_mean_s`` / ``_median_s`` (over reached targets, NaN if none),
    ``falls_per_episode`` (head falls), ``diverged``, ``mean_reward`` (the main term per step),
    ``goal_speeds`` (planar root speed, m/s, of every step spent within the radius) and its
    ``goal_speed_mean`` / ``goal_speed_median``."""
    if not isinstance(mdp.task, NavigationTask):
        raise UserError(f"evaluate_navigation needs a TaskEnv around a NavigationTask, got {type(mdp.task).__name__}")
    if int(episodes) < 1:
        raise UserError(f"episodes must be >= 1, got {episodes}")
    key = mdp.task.reward_key
    quota = episode_quota(int(episodes), mdp.num_envs)
    done = np.zeros(mdp.num_envs, dtype=np.int64)
    targets = reached = falls = diverged = steps = 0
    reward, times, speeds = 0.0, [], []
    obs, goal = mdp.reset()
    while (done < quota).any():
        obs, goal, rewards, term, trunc, info = mdp.step(act(obs, goal))
        live = done < quota  # this step belongs to an episode that counts
        ends = info["target_ends"] & live
        targets += int(ends.sum())
        hit = ends & info["target_reached"]
        reached += int(hit.sum())
        times.append(info["time_to_reach"][hit])
        speeds.append(info["root_speed"][info["reached"] & live])
        falls += int((info["fell"] & term & live).sum())
        diverged += int((info["diverged"] & live).sum())
        reward += float(rewards[key][live].sum())
        steps += int(live.sum())
        ended = np.flatnonzero(term | trunc)
        if len(ended):
            done[ended] += 1
            obs, goal = mdp.reset(ended)
    times, speeds = np.concatenate(times), np.concatenate(speeds)

    def stat(f, a):
        return float(f(a)) if len(a) else float("nan")

    return {"episodes": int(episodes), "targets": targets, "reached_share": reached / max(targets, 1),
            "time_to_reach_mean_s": stat(np.mean, times), "time_to_reach_median_s": stat(np.median, times),
            "falls_per_episode": falls / int(episodes), "diverged": diverged, "mean_reward": reward / max(steps, 1),
            "goal_speeds": speeds, "goal_speed_mean": stat(np.mean, speeds),
            "goal_speed_median": stat(np.median, speeds)}
