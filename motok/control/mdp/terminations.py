"""Termination and truncation terms, each a boolean ``(N,)`` (or the distances they test)."""

from __future__ import annotations

import numpy as np

from motok.errors import UserError
from motok.sim.obs import Bodies

MODES = ("any", "mean")


def body_distances(sim: Bodies, ref: Bodies) -> np.ndarray:
    """``(N, J)`` distance of each body to its reference (m)."""
    return np.sqrt(((sim.pos - ref.pos) ** 2).sum(-1))


def tracking_failure(dist: np.ndarray, mode: str, threshold: float) -> np.ndarray:
    """Imitation early termination: ``any`` body beyond ``threshold`` m of its reference, or the
    ``mean`` over bodies beyond it (PHC's failure test, which forgives one flung hand)."""
    if mode not in MODES:
        raise UserError(f"termination must be 'any' or 'mean', not {mode!r}")
    return (dist.mean(-1) if mode == "mean" else dist.max(-1)) > threshold


def fell(body_height: np.ndarray, min_height: float) -> np.ndarray:
    """A body (e.g. the head) below ``min_height`` m: the fall test of tasks with no reference."""
    return body_height < min_height


def time_limit(steps: np.ndarray, limit: np.ndarray) -> np.ndarray:
    """Episodes that have run their ``limit`` control steps (a truncation: bootstrapped)."""
    return steps >= limit


def end_of_step(rewards: dict, failed: np.ndarray, diverged: np.ndarray, invalid: np.ndarray, steps: np.ndarray,
                limit) -> tuple[dict, np.ndarray, np.ndarray]:
    """What every task does after a step: its reward terms zeroed after a diverged simulation or an
    invalid action; terminated = the task's own failure or either of those; truncated = the time
    limit in an episode that did not terminate. Returns ``(rewards, terminated, truncated)``."""
    bad = diverged | invalid
    terminated = failed | bad
    return ({k: np.where(bad, 0.0, v) for k, v in rewards.items()}, terminated,
            time_limit(steps, limit) & ~terminated)
