"""The fair floor: matched sizes, exact false-alarm rate when sim and real are one distribution, power when not."""

from __future__ import annotations

import numpy as np
import pytest
from scipy import stats

from envi_py.verdicts import fair_floor, kld_gaussian, ks_statistic, w1_normalised


def test_false_alarm_rate_at_nominal_level_when_sim_is_real():
    """Real and sim from one distribution: 'outside the floor' at level 0.1 happens 10 % of the time.

    Sizes 3, 5, 10, 20 runs per side, 100 data sets each. With 19 relabellings the p-value is a multiple
    of 1/20, so for a tie-free (continuous) distance P(p <= 0.1) is exactly 0.1 under H0; a distance with
    ties (KS on few runs) is conservative instead."""
    reps, level = 100, 0.1
    rates = []
    for per_side in (3, 5, 10, 20):
        rng = np.random.default_rng(per_side)
        alarms = 0
        for i in range(reps):
            real = rng.gamma(2.0, size=(2 * per_side, 1))
            sim = rng.gamma(2.0, size=(10 * per_side, 1))
            res = fair_floor(real, sim, w1_normalised(1.0), repetitions=2, permutations=19, level=level, seed=i)
            assert res.per_side == per_side and res.n_real == 2 * per_side
            alarms += not res.within_floor
        rates.append(alarms / reps)
        assert rates[-1] <= level + 3 * np.sqrt(level * (1 - level) / reps)
    assert abs(np.mean(rates) - level) <= 3 * np.sqrt(level * (1 - level) / (4 * reps))


def test_too_narrow_simulation_is_outside_the_floor_with_kld():
    rng = np.random.default_rng(0)
    real = rng.normal(size=(10, 2))
    sim = 0.3 * rng.normal(size=(100, 2))  # a model with a third of the real spread
    res = fair_floor(real, sim, kld_gaussian, repetitions=10, permutations=99)
    assert not res.within_floor and res.p_value <= 0.05 and res.statistic > res.statistic_null_band[1]
    assert res.ratio > res.ratio_null_band[1]
    assert res.per_side == 5 and res.n_sim == 100 and res.to_json()["per_side"] == 5


def test_faithful_simulation_is_within_the_floor_with_w1():
    rng = np.random.default_rng(1)
    res = fair_floor(
        rng.normal(size=(10, 2)), rng.normal(size=(200, 2)), w1_normalised(4.0), repetitions=10, permutations=99
    )
    assert res.within_floor and res.ratio_null_band[0] <= res.ratio <= res.ratio_null_band[1]
    assert res.statistic_null_band[0] <= res.statistic <= res.statistic_null_band[1]


def test_both_sides_have_the_same_size():
    seen = []

    def spy(a: np.ndarray, b: np.ndarray) -> float:
        seen.append((a.shape[0], b.shape[0]))
        return float(abs(a.mean() - b.mean()))

    fair_floor(np.arange(9.0), np.arange(50.0), spy, repetitions=3, permutations=4)
    # halves: sim and floor at 4 vs 4; the test statistic at 9 vs 9; 3 repetitions, 1 + 4 labellings
    assert set(seen) == {(4, 4), (9, 9)} and seen.count((9, 9)) == 3 * 5 and len(seen) == 3 * 3 * 5


def test_ks_statistic_equals_scipy():
    rng = np.random.default_rng(2)
    a, b = rng.normal(size=(7, 3)), rng.normal(size=(12, 3))
    expect = np.mean([stats.ks_2samp(a[:, j], b[:, j]).statistic for j in range(3)])
    assert ks_statistic(a, b) == pytest.approx(expect)


def test_bad_inputs():
    with pytest.raises(ValueError, match="at least 2 real runs"):
        fair_floor(np.ones((1, 2)), np.ones((5, 2)), ks_statistic)
    with pytest.raises(ValueError, match="real holds 1 NaN"):
        fair_floor(np.array([1.0, np.nan, 2.0]), np.ones(5), ks_statistic)
    with pytest.raises(ValueError, match="features per run"):
        fair_floor(np.ones((4, 2)), np.ones((5, 3)), ks_statistic)
    with pytest.raises(ValueError, match="at least as many simulated runs as real ones"):
        fair_floor(np.ones((6, 1)), np.ones((5, 1)), ks_statistic)
