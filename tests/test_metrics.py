"""Goal metrics on hand-made traces with known answers, accuracy, distances and the KLD."""

from __future__ import annotations

import numpy as np
import pytest

from envi_py.metrics import (
    MetricConfig,
    accuracy,
    distances,
    driving_metrics,
    gaussian_kld,
    metric_bounds,
    safety_comfort,
)

CFG = MetricConfig(centre=40, band=10, skip=0)


def test_hand_made_trace():
    #            steady  over(55,60)  steady  under(25,20,28) steady
    c = np.array([40, 45, 55, 60, 45, 40, 25, 20, 28, 35])
    m = driving_metrics(c, CFG)[0]
    # steady: 3 episodes (40,45 | 45,40 | 35) = 5 samples
    assert m.tolist() == [3, 5, 1, 10, 2, 1, 10, 3]


def test_ideal_run_is_one_steady_episode():
    m = driving_metrics(np.full((2, 25), 40.0), CFG)
    assert m.tolist() == [[1, 25, 0, 0, 0, 0, 0, 0]] * 2


def test_skip_ignores_initial_window():
    c = np.concatenate([np.full(10, 90.0), np.full(5, 40.0)])
    m = driving_metrics(c, MetricConfig(skip=10))[0]
    assert m.tolist() == [1, 5, 0, 0, 0, 0, 0, 0]


def test_band_edges_are_steady():
    m = driving_metrics(np.array([30.0, 50.0, 50.0001, 29.999]), CFG)[0]
    assert m[0] == 1 and m[1] == 2 and m[2] == 1 and m[5] == 1


def test_bounds_contain_alternating_extremes():
    t = 9
    c = np.array([100, 0] * 5)[:t].astype(float)
    lo, hi = metric_bounds(t, CFG)
    m = driving_metrics(c, CFG)[0]
    assert np.all(m >= lo) and np.all(m <= hi)
    assert m[2] == hi[2] and m[3] == hi[3]  # overshoot count and amplitude reach their maximum


def test_accuracy_identical_is_one_and_extremes_lower():
    a = driving_metrics(np.tile([40, 60, 20, 40], (3, 5)).astype(float), CFG)
    assert accuracy(a, a, 20, CFG) == pytest.approx(1.0)
    b = driving_metrics(np.full((3, 20), 40.0), CFG)
    assert accuracy(a, b, 20, CFG) < 0.9


def test_safety_comfort():
    c = np.array([[40, 41, 43, 40, 90, 40.0]])
    sc = safety_comfort(c, CFG)[0]
    assert sc[0] == 50
    d3 = np.diff(c[0], 3)
    assert sc[1] == np.abs(d3).max()


@pytest.mark.filterwarnings("error")  # numpy's "Degrees of freedom <= 0" once reached verify's user
def test_gaussian_kld_of_a_single_run_is_nan_without_warnings():
    one, many = np.array([[3.0, 4.0]]), np.random.default_rng(0).normal(size=(5, 2))
    assert np.isnan(gaussian_kld(one, many)) and np.isnan(gaussian_kld(many, one))
    assert np.isfinite(gaussian_kld(many, many + 1))


def test_gaussian_kld_zero_for_same_and_positive_for_shifted():
    rng = np.random.default_rng(0)
    p = rng.normal(size=(500, 2))
    assert gaussian_kld(p, p) == pytest.approx(0.0, abs=1e-9)
    # same covariance S, means apart by d: KL = d' S^-1 d / 2
    d = np.array([2.0, 0.0])
    q = p + d
    expected = 0.5 * d @ np.linalg.inv(np.cov(p, rowvar=False)) @ d
    assert gaussian_kld(p, q, ridge=0.0) == pytest.approx(expected, rel=1e-9)
    assert 1.5 < expected < 2.5  # about |d|^2 / 2 for unit-variance samples


def test_distances_on_known_difference():
    rng = np.random.default_rng(1)
    base = 40 + 30 * np.sin(np.arange(60) / 2.0)
    real = base + rng.normal(0, 2, size=(40, 60))
    same = base + rng.normal(0, 2, size=(40, 60))
    shifted = base + 12 + rng.normal(0, 2, size=(40, 60))
    d_same, d_shift = distances(real, same, CFG), distances(real, shifted, CFG)
    assert d_shift.w1.mean() > 3 * d_same.w1.mean()
    assert d_shift.acc < d_same.acc
    assert d_shift.ks_p.min() < 1e-3
