"""Metric mean intervals and exact order-statistic quantile intervals."""

from __future__ import annotations

import numpy as np
import pytest
from scipy import stats

from envi_py.verdicts import mean_interval, quantile_interval, summarise
from envi_py.verdicts.metric_summary import order_statistic_ranks


def test_median_ranks_for_ten_runs_by_hand():
    # P(Bin(10, 1/2) <= 1) = 11/1024 <= 0.025 < P(<= 2) = 56/1024: the 2nd and 9th order statistics
    assert order_statistic_ranks(10, 0.5) == (2, 9, pytest.approx(1 - 22 / 1024))


def test_high_quantile_from_few_runs_is_unbounded_above():
    q = quantile_interval(np.arange(10.0), 0.95)
    assert q.high == np.inf and q.rank_high == 11 and q.to_json()["interval"][1] is None and q.n == 10


def test_quantile_interval_covers_for_a_skewed_metric():
    rng, reps = np.random.default_rng(0), 2000
    true_q90 = stats.expon.ppf(0.9)
    intervals = [quantile_interval(rng.exponential(size=60), 0.9) for _ in range(reps)]
    cover = np.mean([s.low <= true_q90 <= s.high for s in intervals])
    assert cover >= 0.95 - 3 * np.sqrt(0.05 * 0.95 / reps)


def test_t_interval_by_formula_and_bca_runs():
    x = np.array([2.0, 4.0, 4.0, 5.0, 7.0, 9.0])
    m = mean_interval(x)
    half = stats.t.ppf(0.975, 5) * x.std(ddof=1) / np.sqrt(6)
    assert (m.low, m.high) == pytest.approx((x.mean() - half, x.mean() + half)) and m.n == 6
    b = mean_interval(np.random.default_rng(1).exponential(size=40), method="bca", n_resamples=2000)
    assert b.low < b.mean < b.high and b.method == "bca"


def test_constant_metric_gives_zero_width_and_summary_says_n():
    assert mean_interval([3.0, 3.0, 3.0]).low == 3.0 == mean_interval([3.0, 3.0, 3.0]).high
    s = summarise("over_count", np.arange(20.0))
    assert s.n == 20 and [q.q for q in s.quantiles] == [0.05, 0.5, 0.95] and s.to_json()["mean"]["n"] == 20


def test_bad_inputs():
    with pytest.raises(ValueError, match="NaN"):
        mean_interval([1.0, np.nan, 2.0])
    with pytest.raises(ValueError, match="at least 2"):
        mean_interval([1.0])
    with pytest.raises(ValueError, match="q must lie"):
        quantile_interval([1.0, 2.0], 1.0)
