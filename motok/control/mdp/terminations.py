"""Termination and truncation terms, each a boolean ``(N,)`` (or the distances they test); numpy
or torch (:mod:`motok.arrays`)."""

from __future__ import annotations

from motok.arrays import xp
from motok.errors import UserError
from motok.sim.obs import Bodies

MODES = ("any", "mean")


def body_distances(sim: Bodies, ref: Bodies):
    """``(N, J)`` distance of each body to its reference (m)."""
    return xp(sim.pos).sqrt(((sim.pos - ref.pos) ** 2).sum(-1))


def tracking_failure(dist, mode: str, threshold: float):
    """Imitation early termination: ``any`` body beyond ``threshold`` m of its reference, or the
    ``mean`` over bodies beyond it (PHC's failure test, which forgives one flung hand)."""
    if mode not in MODES:
        raise UserError(f"termination must be 'any' or 'mean', not {mode!r}")
    return (dist.mean(-1) if mode == "mean" else xp(dist).amax(dist, -1)) > threshold


def fell(body_height, min_height: float):
    """A body (e.g. the head) below ``min_height`` m: the fall test of tasks with no reference."""
    return body_height < min_height


def time_limit(steps, limit):
    """Episodes that have run their ``limit`` control steps (a truncation: bootstrapped)."""
    return steps >= limit


def end_of_step(rewards: dict, failed, diverged, invalid, steps, limit) -> tuple[dict, object, object]:
    """What every task does after a step: its reward terms zeroed after a diverged simulation or an
    invalid action; terminated = the task's own failure or either of those; truncated = the time
    limit in an episode that did not terminate. Returns ``(rewards, terminated, truncated)``."""
    bad = diverged | invalid
    terminated = failed | bad
    x = xp(bad)
    return ({k: x.where(bad, 0.0, v) for k, v in rewards.items()}, terminated,
            time_limit(steps, limit) & ~terminated)
