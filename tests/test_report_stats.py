"""The numbers behind the report's plots: MATLAB compare's fit and resid's correlations with bands."""

from __future__ import annotations

import math

import numpy as np
import pytest

from envi_py.report.stats import Z99, fit_percent, residual_correlations


def test_fit_is_100_for_a_perfect_simulation_and_0_for_the_mean() -> None:
    y = np.sin(np.linspace(0, 6, 200)) * 3 + 1
    assert fit_percent(y, y) == pytest.approx(100.0)
    assert fit_percent(y, np.full_like(y, y.mean())) == pytest.approx(0.0, abs=1e-12)
    # half the error norm of the mean's: 50; twice it: -100 (worse than the mean)
    half = y.mean() + 0.5 * (y - y.mean())
    assert fit_percent(y, half) == pytest.approx(50.0)
    assert fit_percent(y, y.mean() - (y - y.mean())) == pytest.approx(-100.0)


def test_fit_of_a_constant_or_broken_trace_is_undefined_not_a_number() -> None:
    assert math.isnan(fit_percent(np.ones(10), np.zeros(10)))
    assert math.isnan(fit_percent(np.array([1.0, np.nan, 2.0]), np.zeros(3)))
    with pytest.raises(ValueError, match="equal length"):
        fit_percent(np.ones(3), np.ones(4))


def test_white_residual_stays_inside_the_99_percent_band() -> None:
    rng = np.random.default_rng(0)
    n = 4000
    c = residual_correlations(rng.normal(size=n), rng.normal(size=n), max_lag=25)
    assert c.band == pytest.approx(Z99 / math.sqrt(n)) and c.n == n
    assert c.auto[0] == pytest.approx(1.0) and len(c.auto) == 26 and len(c.cross) == 51
    # 25 + 51 tests at 1 % each: about 0.8 expected outside by chance
    assert c.auto_outside <= 2 and c.cross_outside <= 3


def test_coloured_residual_and_an_input_dependence_leave_the_band_at_the_right_lags() -> None:
    rng = np.random.default_rng(1)
    n = 3000
    w, u = rng.normal(size=n), rng.normal(size=n)
    e = np.zeros(n)
    for t in range(1, n):
        e[t] = 0.8 * e[t - 1] + w[t]
    c = residual_correlations(e, u, max_lag=10)
    assert c.auto[1] == pytest.approx(0.8, abs=0.05) and c.auto_outside >= 5
    lagged = np.roll(u, 3) + 0.5 * rng.normal(size=n)  # the residual follows the input 3 steps later
    d = residual_correlations(lagged, u, max_lag=10)
    peak = int(d.cross_lags[np.argmax(np.abs(d.cross))])
    assert peak == 3 and abs(d.cross[d.cross_lags == 3][0]) > 0.8 > d.band


def test_bad_residuals_are_one_clear_error() -> None:
    with pytest.raises(ValueError, match="NaN"):
        residual_correlations(np.array([1.0, np.nan, 2.0]), np.zeros(3))
    with pytest.raises(ValueError, match="constant"):
        residual_correlations(np.ones(20), np.arange(20.0))
    with pytest.raises(ValueError, match="equal length"):
        residual_correlations(np.ones(20), np.ones(19))
