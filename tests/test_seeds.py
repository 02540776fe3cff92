"""motok.eval.seeds: the rule that decides an ordering from several seeds, on hand-computed values."""

from __future__ import annotations

import math

import pytest

from motok.errors import UserError
from motok.eval.seeds import DOES_NOT_HOLD, HOLDS, UNDECIDED, mean_interval, t_quantile, verdict, welch_interval


def test_t_quantiles_match_the_closed_forms_and_the_printed_table():
    # closed forms: 1 dof is Cauchy, tan(pi (p - 1/2)); 2 dof: (2p - 1) / sqrt(2 p (1 - p))
    assert t_quantile(0.975, 1) == pytest.approx(math.tan(math.pi * 0.475), rel=1e-9)  # 12.706
    assert t_quantile(0.975, 2) == pytest.approx(0.95 / math.sqrt(2 * 0.975 * 0.025), rel=1e-9)  # 4.303
    # the two-sided 95 % column of a printed t table
    for dof, printed in ((3, 3.182), (4, 2.776), (5, 2.571), (10, 2.228), (30, 2.042)):
        assert t_quantile(0.975, dof) == pytest.approx(printed, abs=5e-4), dof
    assert t_quantile(0.975, 1e7) == pytest.approx(1.960, abs=5e-4)  # the normal's
    # fractional dof (Welch) lie between their integer neighbours
    assert t_quantile(0.975, 3) < t_quantile(0.975, 2.5) < t_quantile(0.975, 2)


def test_the_interval_of_a_mean_over_three_seeds():
    iv = mean_interval([1.0, 2.0, 3.0])  # mean 2, sample variance 1, standard error sqrt(1/3)
    half = 0.95 / math.sqrt(2 * 0.975 * 0.025) * math.sqrt(1 / 3)  # t(0.975, 2) = 4.303: 2.484
    assert iv.estimate == 2.0 and iv.dof == 2
    assert (iv.low, iv.high) == pytest.approx((2 - half, 2 + half), rel=1e-9)
    assert iv.half == pytest.approx(2.4841, abs=1e-4)
    with pytest.raises(UserError, match="at least 2 values"):
        mean_interval([1.0])


def test_welch_interval_by_hand():
    # a = 1, 2, 3 and b = 4, 5, 6: difference -3, each variance 1, standard error sqrt(2/3);
    # Welch dof (2/3)^2 / (2 (1/3)^2 / 2) = 4, t(0.975, 4) = 2.776: half-width 2.267
    iv = welch_interval([1.0, 2.0, 3.0], [4.0, 5.0, 6.0])
    assert iv.estimate == -3.0 and iv.dof == pytest.approx(4.0, rel=1e-12)
    assert iv.half == pytest.approx(2.776 * math.sqrt(2 / 3), abs=1e-3)
    # unequal variances: a = 1, 2, 3 (var 1) and b = 2, 5, 8 (var 9): dof (10/3)^2 / ((1/3)^2/2 + 3^2/2) = 200/82
    iv = welch_interval([1.0, 2.0, 3.0], [2.0, 5.0, 8.0])
    assert iv.dof == pytest.approx(200 / 82, rel=1e-12)
    # a pooled-variance t would use 4 dof; Welch's fewer make the interval wider than t(4) gives
    assert iv.half > 2.776 * math.sqrt(10 / 3)


def test_the_verdict_follows_the_paper_direction_and_flips_with_one_seed():
    a, b = [1.0, 2.0, 3.0], [4.0, 5.0, 6.0]  # a lower: the interval [-5.27, -0.73] excludes zero
    v = verdict(a, b, better="lower")
    assert v.state == HOLDS and (v.diff.low, v.diff.high) == pytest.approx((-5.267, -0.733), abs=1e-3)
    assert verdict(a, b, better="higher").state == DOES_NOT_HOLD  # the same numbers, the other claim
    assert verdict(b, a, better="lower").state == DOES_NOT_HOLD
    # one seed of b moved from 4 and 6 to 2 and 8 (same mean): the interval spans zero
    v = verdict(a, [2.0, 5.0, 8.0], better="lower")
    assert v.state == UNDECIDED and v.diff.low < 0 < v.diff.high
    # only b's third seed changed, from 6 to 12: undecided again
    assert verdict(a, [4.0, 5.0, 12.0], better="lower").state == UNDECIDED
    assert "holds (diff -3, CI [-5.27, -0.733], 3 seeds each)" == str(verdict(a, b, better="lower"))


def test_fewer_than_three_seeds_decide_nothing():
    # a clear gap over two seeds a side is still undecided: the rule asks for three
    v = verdict([1.0, 1.1], [5.0, 5.1], better="lower")
    assert v.state == UNDECIDED and v.diff.high < 0 and (v.n_a, v.n_b) == (2, 2)
    v = verdict([1.0], [5.0, 5.1, 5.2], better="lower")
    assert v.state == UNDECIDED and v.diff is None and str(v) == "undecided (1 and 3 seeds)"
    # constant seeds: a zero-width interval decides by the sign of the difference alone
    assert verdict([2.0] * 3, [3.0] * 3, better="lower").state == HOLDS
    assert verdict([2.0] * 3, [2.0] * 3, better="lower").state == UNDECIDED


def test_bad_inputs_say_what_is_wrong():
    with pytest.raises(UserError, match="better must be 'lower' or 'higher'"):
        verdict([1, 2, 3], [1, 2, 3], better="smaller")
    with pytest.raises(UserError, match="finite"):
        welch_interval([1.0, float("nan")], [1.0, 2.0])
