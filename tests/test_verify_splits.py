"""The fair reference's average over random splits: one near-singular split must not be the figure."""

from __future__ import annotations

import math

import numpy as np

from envi_py.metrics import Distances
from envi_py.verify import split_average


def _d(kld: float, w1: float = 0.1) -> Distances:
    return Distances(np.array([w1]), np.array([0.2]), np.array([0.5]), 0.9, kld)


def test_the_kld_over_splits_is_a_geometric_mean():
    """Nine splits at 1.0 and one whose Gaussian fit is nearly singular (1000): the arithmetic mean, 100.9,
    reports that one split; the geometric mean, as in the authors' analysis, says 2.0."""
    avg = split_average([_d(1.0)] * 9 + [_d(1000.0)])
    assert math.isclose(avg.kld, 1000 ** (1 / 10), rel_tol=1e-9)
    assert math.isclose(float(avg.w1[0]), 0.1)  # the other distances stay arithmetic means


def test_a_kld_that_does_not_apply_stays_missing():
    assert math.isnan(split_average([_d(math.nan)] * 3).kld)
