"""How an ordering between two training setups is decided from runs on several seeds.

One training run is one draw: two seeds of one recipe can differ by more than two priors do. So
every cell (task x prior) is trained on at least :data:`MIN_SEEDS` seeds at the same budget, each
metric is reported as the mean over seeds with its 95 % Student-t interval, and an ordering is
read from the Welch interval of the difference of two cells' means (the seeds of two priors are
independent draws with variances that need not be equal):

- **holds** when the interval excludes zero in the direction the paper states;
- **does not hold** when it excludes zero the other way;
- **undecided** otherwise, and whenever a cell has fewer than :data:`MIN_SEEDS` seeds.

The t quantiles come from ``scipy.stats.t`` (scipy is already a dependency of motok); Welch's
degrees of freedom are fractional, which a small table would have to interpolate.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Sequence

from motok.errors import UserError

LEVEL = 0.95
MIN_SEEDS = 3
HOLDS, DOES_NOT_HOLD, UNDECIDED = "holds", "does not hold", "undecided"


def t_quantile(p: float, dof: float) -> float:
    """The p-quantile of Student's t with ``dof`` degrees of freedom (fractional allowed)."""
    if not 0 < p < 1:
        raise UserError(f"t_quantile: p must be in (0, 1), got {p}")
    if not dof > 0:
        raise UserError(f"t_quantile: degrees of freedom must be > 0, got {dof}")
    from scipy.stats import t  # only here: reading a table of runs needs no scipy import otherwise

    return float(t.ppf(p, dof))


def _clean(values: Sequence[float], what: str) -> list[float]:
    out = [float(v) for v in values]
    if any(not math.isfinite(v) for v in out):
        raise UserError(f"{what}: every value must be a finite number, got {out}")
    return out


def _var(xs: list[float]) -> float:
    """The sample variance (n - 1 in the denominator)."""
    m = sum(xs) / len(xs)
    return sum((x - m) ** 2 for x in xs) / (len(xs) - 1)


@dataclass(frozen=True)
class Interval:
    """``estimate`` and its two-sided interval [low, high] at ``level``; ``dof`` of the t used."""

    estimate: float
    low: float
    high: float
    dof: float
    level: float = LEVEL

    @property
    def half(self) -> float:
        return (self.high - self.low) / 2


def mean_interval(values: Sequence[float], level: float = LEVEL) -> Interval:
    """The mean of ``values`` (one per seed) with its Student-t interval, n - 1 degrees of freedom."""
    xs = _clean(values, "mean_interval")
    if len(xs) < 2:
        raise UserError(f"mean_interval: an interval needs at least 2 values, got {len(xs)}")
    m = sum(xs) / len(xs)
    half = t_quantile(0.5 + level / 2, len(xs) - 1) * math.sqrt(_var(xs) / len(xs))
    return Interval(m, m - half, m + half, len(xs) - 1, level)


def welch_interval(a: Sequence[float], b: Sequence[float], level: float = LEVEL) -> Interval:
    """mean(a) - mean(b) with Welch's interval: the standard error from each side's own variance,
    Welch-Satterthwaite degrees of freedom. Both sides constant: a zero-width interval."""
    xa, xb = _clean(a, "welch_interval"), _clean(b, "welch_interval")
    if len(xa) < 2 or len(xb) < 2:
        raise UserError(f"welch_interval: each side needs at least 2 values, got {len(xa)} and {len(xb)}")
    d = sum(xa) / len(xa) - sum(xb) / len(xb)
    va, vb = _var(xa) / len(xa), _var(xb) / len(xb)
    se2 = va + vb
    if se2 == 0:
        return Interval(d, d, d, math.inf, level)
    dof = se2 ** 2 / (va ** 2 / (len(xa) - 1) + vb ** 2 / (len(xb) - 1))
    half = t_quantile(0.5 + level / 2, dof) * math.sqrt(se2)
    return Interval(d, d - half, d + half, dof, level)


@dataclass(frozen=True)
class Verdict:
    """The decision on "a better than b": ``state`` is HOLDS, DOES_NOT_HOLD or UNDECIDED;
    ``diff`` the Welch interval of mean(a) - mean(b) (None with fewer than two seeds a side)."""

    state: str
    diff: Interval | None
    n_a: int
    n_b: int

    def __str__(self) -> str:
        seeds = f"{self.n_a} and {self.n_b} seeds" if self.n_a != self.n_b else f"{self.n_a} seeds each"
        if self.diff is None:
            return f"{self.state} ({seeds})"
        d = self.diff
        return f"{self.state} (diff {d.estimate:+.3g}, CI [{d.low:+.3g}, {d.high:+.3g}], {seeds})"


def verdict(a: Sequence[float], b: Sequence[float], better: str, level: float = LEVEL,
            min_seeds: int = MIN_SEEDS) -> Verdict:
    """Whether ``a`` beats ``b`` by the rule of this module; ``better`` is "lower" (errors, falls,
    times) or "higher" (success, targets reached)."""
    if better not in ("lower", "higher"):
        raise UserError(f"verdict: better must be 'lower' or 'higher', got {better!r}")
    xa, xb = _clean(a, "verdict"), _clean(b, "verdict")
    diff = welch_interval(xa, xb, level) if len(xa) >= 2 and len(xb) >= 2 else None
    if diff is None or min(len(xa), len(xb)) < min_seeds:
        return Verdict(UNDECIDED, diff, len(xa), len(xb))
    # the paper's direction as the sign of mean(a) - mean(b)
    sign = -1 if better == "lower" else 1
    if sign * diff.low > 0 and sign * diff.high > 0:
        state = HOLDS
    elif sign * diff.low < 0 and sign * diff.high < 0:
        state = DOES_NOT_HOLD
    else:
        state = UNDECIDED
    return Verdict(state, diff, len(xa), len(xb))
