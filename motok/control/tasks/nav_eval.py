"""Evaluation of a navigation policy (hybrid-latent paper, appendix C.3): how many targets are
reached before they change, how fast, how often the character falls, and how it moves once
there (the idle phase: its root speed, and the body motion itself for the motion-matching
distance of ``motok.eval.motion_matching``, which the caller computes against the dataset)."""

from __future__ import annotations

from typing import Callable

import numpy as np

from motok.control.mdp.navigation import planar_distance
from motok.control.mdp.task_env import TaskEnv
from motok.control.tasks.navigation import NavigationTask
from motok.errors import UserError

MIN_IDLE_SECONDS = 0.5  # a stay at the target shorter than this is passing through, not idling
# Nor is walking through the 1 m circle (0.7 s at 1.4 m/s): idling is at most this root speed, m/s,
# under half the data's slowest walking pace (median 1.06 m/s for the turns of set 2).
IDLE_SPEED = 0.5


def episode_quota(episodes: int, num_envs: int) -> np.ndarray:
    """Episodes each environment contributes, ``episodes`` in all. A fixed share per environment,
    not the first ``episodes`` to end: those would over-count short (fallen) episodes."""
    return episodes // num_envs + (np.arange(num_envs) < episodes % num_envs)


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
    (``1 - closest / start``: 1 at the target, 0 for no step toward it; the paper's reached share
    is 0 for a policy that walks toward a 5-10 m target at the rewarded 1 m/s, which this tells
    from one that stands); and ``idle_bodies``: the body positions
    ``(T, J, 3)`` (MuJoCo frame, control rate) of every stay within the radius, slower than
    ``idle_speed`` (m/s), of at least :data:`MIN_IDLE_SECONDS`, for the idle phase's motion matching."""
    if not isinstance(mdp.task, NavigationTask):
        raise UserError(f"evaluate_navigation needs a TaskEnv around a NavigationTask, got {type(mdp.task).__name__}")
    if int(episodes) < 1:
        raise UserError(f"episodes must be >= 1, got {episodes}")
    key = mdp.task.reward_key
    quota = episode_quota(int(episodes), mdp.num_envs)
    done = np.zeros(mdp.num_envs, dtype=np.int64)
    targets = reached = falls = diverged = steps = 0
    reward, times, speeds, starts, closests = 0.0, [], [], [], []
    # Per step: who idles at its target, in which of its episodes, and the bodies of those idling.
    idling, episode, bodies = [], [], []
    obs, goal = mdp.reset()

    def to_target():
        return np.asarray(planar_distance(mdp.env.bodies.pos[:, 0], mdp.task.target), np.float64)

    start = to_target()
    closest = start.copy()
    while (done < quota).any():
        obs, goal, rewards, term, trunc, info = mdp.step(act(obs, goal))
        live = done < quota  # this step belongs to an episode that counts
        closest = np.fmin(closest, info["distance"])  # a diverged step (NaN) does not erase the approach
        at_goal = info["reached"] & live
        idling.append(at_goal & (info["root_speed"] < idle_speed))
        episode.append(done.copy())
        bodies.append(mdp.env.bodies.pos[idling[-1]].astype(np.float32))
        ends = info["target_ends"] & live
        targets += int(ends.sum())
        hit = ends & info["target_reached"]
        reached += int(hit.sum())
        times.append(info["time_to_reach"][hit])
        starts.append(start[ends])
        closests.append(closest[ends])
        speeds.append(info["root_speed"][at_goal])
        falls += int((info["fell"] & term & live).sum())
        diverged += int((info["diverged"] & live).sum())
        reward += float(rewards[key][live].sum())
        steps += int(live.sum())
        ended = np.flatnonzero(term | trunc)
        if len(ended):
            done[ended] += 1
            obs, goal = mdp.reset(ended)
        new = info["target_ends"]  # a new target (or a new episode) from the next step on
        if new.any():
            start[new] = to_target()[new]
            closest[new] = start[new]
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

    return {"episodes": int(episodes), "targets": targets, "reached_share": reached / max(targets, 1),
            "time_to_reach_mean_s": stat(np.mean, times), "time_to_reach_median_s": stat(np.median, times),
            "falls_per_episode": falls / int(episodes), "diverged": diverged, "mean_reward": reward / max(steps, 1),
            "goal_speeds": speeds, "goal_speed_mean": stat(np.mean, speeds),
            "goal_speed_median": stat(np.median, speeds), "start_distances": starts, "closest_distances": closests,
            "start_distance_mean_m": stat(np.mean, starts), "closest_distance_mean_m": stat(np.mean, closests),
            "approach_share": stat(np.mean, 1.0 - closests / np.maximum(starts, 1e-9)), "idle_bodies": idle}


def idle_matching(idle_bodies: list[np.ndarray], data, names, hz: float) -> dict:
    """The idle phase's naturalness: Eq. 8 motion matching (``motok.eval.motion_matching``) of
    the transitions of ``idle_bodies`` (from :func:`evaluate_navigation`, at the control rate
    ``hz``) against the clips ``names`` of the dataset ``data``: distance, filtered rate, coverage."""
    from motok.control.track import from_mj
    from motok.eval.motion_matching import match_joints, no_transitions, reference

    if not idle_bodies:  # no stay to match: no threshold to derive either
        return no_transitions()
    return match_joints(reference(data, list(names)), [from_mj(b) for b in idle_bodies], hz)
