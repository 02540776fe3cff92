"""Evaluation of the in-betweening and HMD-tracking policies (hybrid-latent paper, Tables 2 and 3).

``act(obs, goal) -> actions`` (numpy, every environment at once) runs on the ``mdp`` from fresh
episodes (the task's generator draws the windows and keyframes) until ``episodes`` have ended, a
fixed share per environment (``nav_eval.episode_quota``: stopping at the first ``episodes`` to end
would over-count short, failed ones).

Every episode plays its whole window or trajectory: early termination is off while evaluating, as
in the fork's test mode. With it on, a failed episode would count only the frames before it
failed, where the errors are small by construction, and the keyframe columns would leave out the
episodes that failed before their first target keyframe: the policies that fail more would look
closer. An episode **succeeds** when the task's failure test (``info["off_track"]``: the mean body
distance above 0.5 m for in-betweening, the head more than 1 m off for HMD) never fired and the
simulation did not diverge; ``seconds`` is the time until that test first fired (the whole
episode if never).

Per episode, over all its frames (the start state included), the errors of the fork's
``compute_metrics_lite`` (PHC's evaluation, all bodies): **MPJPE** (root-relative) and
**G-MPJPE** (global) in mm, **velocity** (mm/frame) and **acceleration** (mm/frame^2) errors of
the global body positions (first and second differences ending at each frame), with the helpers
of ``motok.eval.metrics``. ``motok.control.tasks.imitation_eval`` reports the root's velocity and acceleration
errors instead. In-betweening also reports them at the target keyframes only (``keyframe_*``: the
frames of keyframes 2..K; the start keyframe is the initial state, which the fork's keyframe
metrics include). HMD also reports the head's global error and the share of frames with the head
within the termination distance (the fork's "success rate").
Results: ``<metric>_mean`` / ``<metric>_std`` over episodes (population std; NaN-free episodes
only), ``success_rate``, ``seconds_mean`` and the per-episode values under ``per_episode``.
"""

from __future__ import annotations

from contextlib import contextmanager
from typing import Callable

import numpy as np

from motok.control.tasks.nav_eval import episode_quota
from motok.control.mdp.task_env import TaskEnv
from motok.control.tasks.hmd import HMDTask
from motok.control.tasks.inbetween import InbetweenTask
from motok.errors import UserError
from motok.eval.metrics import acceleration_error, mpjpe, velocity_error

METRICS = ("mpjpe_mm", "g_mpjpe_mm", "vel_err_mm", "acc_err_mm")

Act = Callable[[np.ndarray, np.ndarray], np.ndarray]


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


def _summary(names: list[str], rows: np.ndarray, success: np.ndarray, seconds: np.ndarray) -> dict:
    out = {"episodes": int(len(success)), "success_rate": float(success.mean()),
           "seconds_mean": float(seconds.mean())}
    for j, k in enumerate(names):
        v = rows[:, j][np.isfinite(rows[:, j])]
        out[f"{k}_mean"] = float(v.mean()) if len(v) else float("nan")
        out[f"{k}_std"] = float(v.std()) if len(v) else float("nan")
    out["per_episode"] = {"success": success.tolist(), "seconds": seconds.tolist(),
                          **{k: rows[:, j].tolist() for j, k in enumerate(names)}}
    return out


def _run(mdp: TaskEnv, act: Act, episodes: int, acc: EpisodeErrors) -> dict:
    if int(episodes) < 1:
        raise UserError(f"episodes must be >= 1, got {episodes}")
    task, env, lib = mdp.task, mdp.env, mdp.task.lib
    N = mdp.num_envs
    quota = episode_quota(int(episodes), N)
    done = np.zeros(N, dtype=np.int64)
    rows, success, seconds = [], [], []

    def ref_pos():
        return lib.body_pos[lib.frame_index(task.clip, task.frame)]

    off_at = np.zeros(N, dtype=np.int64)  # the step the failure test first fired in the episode, 0: not yet
    obs, goal = mdp.reset()
    acc.clear(slice(None))
    acc.record(env.bodies.pos, ref_pos(), done < quota)
    while (done < quota).any():
        live = done < quota
        obs, goal, _, term, trunc, info = mdp.step(act(obs, goal))
        acc.record(env.bodies.pos, ref_pos(), live, info.get("at_keyframe"))
        steps = np.asarray(info["episode_steps"])
        off_at = np.where((off_at == 0) & np.asarray(info["off_track"]), steps, off_at)
        ended = np.flatnonzero(term | trunc)
        if not len(ended):
            continue
        counted = ended[live[ended]]
        rows.append(acc.means(counted))
        success.append(trunc[counted] & (off_at[counted] == 0))  # term: a diverged simulation or invalid action
        seconds.append(np.where(off_at[counted] > 0, off_at[counted], steps[counted]) * env.dt)
        done[counted] += 1
        obs, goal = mdp.reset(ended)
        acc.clear(ended)
        off_at[ended] = 0
        fresh = np.zeros(N, bool)
        fresh[ended] = done[ended] < quota[ended]
        acc.record(env.bodies.pos, ref_pos(), fresh)
    return _summary(acc.names, np.concatenate(rows), np.concatenate(success), np.concatenate(seconds))


@contextmanager
def whole_episodes(task):
    """Early termination off on ``task`` (its config) for the duration, restored afterwards."""
    before = task.cfg.early_termination
    task.cfg.early_termination = False
    try:
        yield
    finally:
        task.cfg.early_termination = before


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
            out = _run(mdp, act, episodes, EpisodeErrors(mdp.num_envs))
    finally:
        task.set_keyframe_count(before)
        mdp.reset()
    return {"keyframes_per_window": int(task.cfg.eval_keyframes), **out}


def evaluate_hmd(mdp: TaskEnv, act: Act, episodes: int) -> dict:
    """Table 3 protocol: ``episodes`` 5 s head trajectories, played to their end, full-body errors
    over all frames plus the head's own error and the share of frames it stayed within the
    termination distance. Early termination is restored afterwards."""
    task = mdp.task
    if not isinstance(task, HMDTask):
        raise UserError(f"evaluate_hmd needs a TaskEnv around an HMDTask, got {type(task).__name__}")
    with whole_episodes(task):
        out = _run(mdp, act, episodes, EpisodeErrors(mdp.num_envs, head=task.head,
                                                     within=task.cfg.termination_distance))
    return {k: v for k, v in out.items() if not k.startswith("keyframe_")} | \
        {"per_episode": {k: v for k, v in out["per_episode"].items() if not k.startswith("keyframe_")}}
