"""Exact Clopper-Pearson intervals against hand-computed beta/binomial values, and the verdict's edges."""

from __future__ import annotations

import numpy as np
import pytest

from envi_py.verdicts import Verdict, clopper_pearson, decide


def test_zero_and_all_successes_have_closed_form_bounds():
    # k = 0: upper solves (1 - p)^10 = 0.025; k = n: lower solves p^10 = 0.025
    assert clopper_pearson(0, 10) == pytest.approx((0.0, 1 - 0.025**0.1), abs=1e-12)
    assert clopper_pearson(10, 10) == pytest.approx((0.025**0.1, 1.0), abs=1e-12)


def test_one_success_and_one_failure_have_closed_form_bounds():
    # k = 1: lower solves 1 - (1 - p)^10 = 0.025; k = 9: upper solves 1 - p^10 = 0.025
    lo, _ = clopper_pearson(1, 10)
    _, hi = clopper_pearson(9, 10)
    assert lo == pytest.approx(1 - 0.975**0.1, abs=1e-12)
    assert hi == pytest.approx(0.975**0.1, abs=1e-12)


def test_seven_of_ten_matches_the_tabulated_interval():
    lo, hi = clopper_pearson(7, 10)
    assert (round(lo, 4), round(hi, 4)) == (0.3475, 0.9333)  # the textbook table value for 7/10
    # and each bound is where the one-sided binomial tail equals alpha/2, summed by hand
    from math import comb

    def tail_at_least(k: int, p: float) -> float:
        return sum(comb(10, j) * p**j * (1 - p) ** (10 - j) for j in range(k, 11))

    assert tail_at_least(7, lo) == pytest.approx(0.025, abs=1e-9)
    assert 1 - tail_at_least(8, hi) == pytest.approx(0.025, abs=1e-9)


def test_interval_narrows_with_runs_and_holds_the_estimate():
    widths = []
    for n in (10, 100, 1000):
        lo, hi = clopper_pearson(int(0.8 * n), n)
        assert lo < 0.8 < hi
        widths.append(hi - lo)
    assert widths[0] > widths[1] > widths[2]


def test_decide_edges():
    lo10 = clopper_pearson(10, 10)[0]
    assert decide(10, 10, lo10).verdict is Verdict.PASS  # lower bound == required: PASS
    assert decide(10, 10, lo10 + 1e-9).verdict is Verdict.UNDECIDED
    hi0 = clopper_pearson(0, 10)[1]
    assert decide(0, 10, hi0).verdict is Verdict.UNDECIDED  # upper bound == required: not below it
    assert decide(0, 10, hi0 + 1e-9).verdict is Verdict.FAIL
    d = decide(7, 10, 0.5)
    assert d.verdict is Verdict.UNDECIDED and d.n == 10 and d.k == 7 and d.p_hat == 0.7
    assert d.to_json()["interval"] == [d.low, d.high]


def test_no_runs_is_vacuous():
    assert clopper_pearson(0, 0) == (0.0, 1.0)
    assert decide(0, 0, 0.5).verdict is Verdict.UNDECIDED


def test_exact_interval_never_undercovers():
    rng = np.random.default_rng(3)
    bounds = np.array([clopper_pearson(k, 10) for k in range(11)])
    for p in (0.05, 0.5, 0.93):
        ks = rng.binomial(10, p, 4000)
        cover = np.mean((bounds[ks, 0] <= p) & (p <= bounds[ks, 1]))
        assert cover >= 0.95 - 3 * np.sqrt(0.05 * 0.95 / 4000)


@pytest.mark.parametrize(
    "args, match",
    [
        ((11, 10), "k must be <= n"),
        ((-1, 10), "k must be >= 0"),
        ((2.5, 10), "k must be an integer"),
        ((True, 10), "k must be an integer"),
    ],
)
def test_bad_counts(args, match):
    with pytest.raises(ValueError, match=match):
        clopper_pearson(*args)


@pytest.mark.parametrize(
    "p, alpha, match",
    [(float("nan"), 0.05, "p_required"), (1.5, 0.05, "p_required"), (0.5, 0.0, "alpha"), (0.5, "x", "alpha")],
)
def test_bad_levels(p, alpha, match):
    with pytest.raises(ValueError, match=match):
        decide(5, 10, p, alpha)
