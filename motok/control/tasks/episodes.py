"""The episode-evaluation loop every task's evaluation shares, and the error sums of the tasks
that follow a reference (in-betweening, HMD tracking: the hybrid-latent paper's Tables 2 and 3).

``act(obs, goal) -> actions`` (numpy, every environment at once) runs on the ``mdp`` from fresh
episodes (the task's generator draws the starts, targets, windows or commands) until ``episodes``
have ended, a fixed share per environment (:func:`episode_quota`: stopping at the first
``episodes`` to end would over-count short, failed ones). :func:`play_episodes` is that loop; a
task's evaluation says what it counts after each step and after each reset.

**Reference errors** (:func:`reference_errors`). Every episode plays its whole window or
trajectory: early termination is off while evaluating (:func:`whole_episodes`), as in the
authors' fork's test mode. With it on, a failed episode would count only the frames before it
failed, where the errors are small by construction, and the keyframe columns would leave out the
episodes that failed before their first target keyframe: the policies that fail more would look
closer. An episode **succeeds** when the task's failure test (``info["off_track"]``: a body more
than 0.5 m from its reference for in-betweening (by default), the head more than 1 m off for HMD) never fired and the
simulation did not diverge; ``seconds`` is the time until that test first fired (the whole
episode if never).

Per episode, over all its frames (the start state included), the errors of the fork's
``compute_metrics_lite`` (PHC's evaluation, all bodies): **MPJPE** (root-relative) and
**G-MPJPE** (global) in mm, **velocity** (mm/frame) and **acceleration** (mm/frame^2) errors of
the global body positions (first and second differences ending at each frame), with the helpers
of ``motok.eval.metrics``. The imitation task's evaluation (``tasks.imitation``) reports the
root's velocity and acceleration errors instead. In-betweening also reports them at the target
keyframes only (``keyframe_*``: the frames of keyframes 2..K; the start keyframe is the initial
state, which the fork's keyframe metrics include). HMD also reports the head's global error and
the share of frames with the head within the termination distance (the fork's "success rate").
Results: ``<metric>_mean`` / ``<metric>_std`` over episodes (population std; NaN-free episodes
only), ``success_rate``, ``seconds_mean`` and the per-episode values under ``per_episode``.
"""

from __future__ import annotations

from contextlib import contextmanager
from dataclasses import dataclass
from typing import Callable

import numpy as np

from motok.control.mdp.task_env import TaskEnv
from motok.errors import UserError
from motok.eval.metrics import acceleration_error, mpjpe, velocity_error

METRICS = ("mpjpe_mm", "g_mpjpe_mm", "vel_err_mm", "acc_err_mm")

Act = Callable[[np.ndarray, np.ndarray], np.ndarray]


def episode_quota(episodes: int, num_envs: int) -> np.ndarray:
    """Episodes each environment contributes, ``episodes`` in all. A fixed share per environment,
    not the first ``episodes`` to end: those would over-count short (fallen) episodes."""
    return episodes // num_envs + (np.arange(num_envs) < episodes % num_envs)


@dataclass
class Step:
    """One control step of every environment, as :func:`play_episodes` hands it to a task's count."""

    rewards: dict
    terminated: np.ndarray
    truncated: np.ndarray
    info: dict
    live: np.ndarray  # (N,) the step belongs to an episode that counts
    ended: np.ndarray  # ids of the environments whose episode ended at this step
    counted: np.ndarray  # the ended ids whose episode counts (the live ones)


def play_episodes(mdp: TaskEnv, act: Act, episodes: int, on_step: Callable[[Step], None],
                  on_reset: Callable[[np.ndarray, np.ndarray], None] | None = None) -> None:
    """Reset every environment, then step ``act`` until each has ended its quota of episodes.
    ``on_step(step)`` sees every step before the ended environments restart; ``on_reset(ids,
    fresh)`` sees the environments ``ids`` just reset (all of them at the start), ``fresh`` the
    ``(N,)`` mask of those whose new episode counts."""
    if int(episodes) < 1:
        raise UserError(f"episodes must be >= 1, got {episodes}")
    N = mdp.num_envs
    quota = episode_quota(int(episodes), N)
    done = np.zeros(N, dtype=np.int64)
    obs, goal = mdp.reset()
    if on_reset is not None:
        on_reset(np.arange(N), done < quota)
    while (done < quota).any():
        live = done < quota
        obs, goal, rewards, term, trunc, info = mdp.step(act(obs, goal))
        ended = np.flatnonzero(term | trunc)
        counted = ended[live[ended]]
        on_step(Step(rewards, term, trunc, info, live, ended, counted))
        if not len(ended):
            continue
        done[counted] += 1
        obs, goal = mdp.reset(ended)
        if on_reset is not None:
            fresh = np.zeros(N, bool)
            fresh[ended] = done[ended] < quota[ended]
            on_reset(ended, fresh)


class EpisodeErrors:
    """Running sums of per-frame errors over each environment's episode in progress, vectorised
    over environments: ``record`` one frame of every environment, ``clear`` at a reset, ``means``
    at an episode's end. Columns: ``METRICS``, then ``key_`` + ``METRICS`` (frames flagged as
    keyframes), then the head columns when ``head`` is given."""

    def __init__(self, n: int, head: int | None = None, within: float = 1.0):
        self.head, self.within = head, within
        self.names = list(METRICS) + [f"keyframe_{m}" for m in METRICS] + \
            (["head_error_mm", "head_within_share"] if head is not None else [])
        self.sum, self.count = np.zeros((n, len(self.names))), np.zeros((n, len(self.names)))
        self.age = np.zeros(n, dtype=np.int64)  # frames recorded in the episode
        self.prev: tuple[np.ndarray, ...] | None = None  # sim and reference positions at t - 1 and t - 2

    def clear(self, ids) -> None:
        self.sum[ids], self.count[ids], self.age[ids] = 0.0, 0.0, 0

    def record(self, sim: np.ndarray, ref: np.ndarray, live: np.ndarray, key: np.ndarray | None = None) -> None:
        """One frame: body positions ``(N, J, 3)`` (m) of the simulation and the reference; only the
        ``live`` rows count; ``key`` flags frames at a target keyframe."""
        if self.prev is None:
            self.prev = (sim.copy(), ref.copy(), sim.copy(), ref.copy())
        p1, r1, p2, r2 = self.prev
        n = len(sim)
        vals = np.zeros((n, len(self.names)))
        vals[:, 0], vals[:, 1] = mpjpe(sim, ref), mpjpe(sim, ref, root_relative=False)
        vals[:, 2] = velocity_error(np.stack([p1, sim]), np.stack([r1, ref]))[0]
        vals[:, 3] = acceleration_error(np.stack([p2, p1, sim]), np.stack([r2, r1, ref]))[0]
        ok = np.stack([np.ones(n, bool), np.ones(n, bool), self.age >= 1, self.age >= 2], 1) & live[:, None]
        vals[:, 4:8] = vals[:, :4]
        ok = np.concatenate([ok, ok & (np.zeros(n, bool) if key is None else key)[:, None]], 1)
        if self.head is not None:
            d = np.linalg.norm(sim[:, self.head] - ref[:, self.head], axis=-1)
            vals[:, 8], vals[:, 9] = d * 1000.0, d <= self.within
            ok = np.concatenate([ok, np.repeat(live[:, None], 2, 1)], 1)
        self.sum += np.where(ok, vals, 0.0)
        self.count += ok
        keep = ~live[:, None, None]
        self.prev = (np.where(keep, p1, sim), np.where(keep, r1, ref), np.where(keep, p2, p1), np.where(keep, r2, r1))
        self.age += live

    def means(self, ids) -> np.ndarray:
        """``(len(ids), columns)`` per-episode means, NaN where a column had no frame."""
        c = self.count[ids]
        return np.where(c > 0, self.sum[ids] / np.maximum(c, 1), np.nan)


def summary(names: list[str], rows: np.ndarray, success: np.ndarray, seconds: np.ndarray) -> dict:
    out = {"episodes": int(len(success)), "success_rate": float(success.mean()),
           "seconds_mean": float(seconds.mean())}
    for j, k in enumerate(names):
        v = rows[:, j][np.isfinite(rows[:, j])]
        out[f"{k}_mean"] = float(v.mean()) if len(v) else float("nan")
        out[f"{k}_std"] = float(v.std()) if len(v) else float("nan")
    out["per_episode"] = {"success": success.tolist(), "seconds": seconds.tolist(),
                          **{k: rows[:, j].tolist() for j, k in enumerate(names)}}
    return out


def reference_errors(mdp: TaskEnv, act: Act, episodes: int, acc: EpisodeErrors) -> dict:
    """``episodes`` whole episodes of a task that follows a reference (its ``clip`` and ``frame``),
    with the errors of ``acc`` (the module docstring)."""
    task, env, lib = mdp.task, mdp.env, mdp.task.lib
    rows, success, seconds = [], [], []
    off_at = np.zeros(mdp.num_envs, dtype=np.int64)  # the step the failure test first fired, 0: not yet

    def ref_pos():
        return lib.body_pos[lib.frame_index(task.clip, task.frame)]

    def on_step(s: Step) -> None:
        nonlocal off_at
        acc.record(env.bodies.pos, ref_pos(), s.live, s.info.get("at_keyframe"))
        steps = np.asarray(s.info["episode_steps"])
        off_at = np.where((off_at == 0) & np.asarray(s.info["off_track"]), steps, off_at)
        c = s.counted
        if len(s.ended):
            rows.append(acc.means(c))
            success.append(s.truncated[c] & (off_at[c] == 0))  # terminated: a diverged simulation or invalid action
            seconds.append(np.where(off_at[c] > 0, off_at[c], steps[c]) * env.dt)

    def on_reset(ids, fresh) -> None:
        acc.clear(ids)
        off_at[ids] = 0
        acc.record(env.bodies.pos, ref_pos(), fresh)

    play_episodes(mdp, act, episodes, on_step, on_reset)
    return summary(acc.names, np.concatenate(rows), np.concatenate(success), np.concatenate(seconds))


@contextmanager
def whole_episodes(task):
    """Early termination off on ``task`` (its config) for the duration, restored afterwards."""
    before = task.cfg.early_termination
    task.cfg.early_termination = False
    try:
        yield
    finally:
        task.cfg.early_termination = before
