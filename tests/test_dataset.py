"""Windowing, normalisation round trips and splits by whole log."""

from __future__ import annotations

import numpy as np
import pytest

from envi_py.dataset import Dataset, Normaliser, log_pairs, split_logs, windows
from envi_py.logs import LANE_KEEPING_SCHEMA

from .conftest import make_log


def test_windows_are_views_in_time_order():
    v = np.arange(12, dtype=float).reshape(6, 2)
    w = windows(v, 3)
    assert w.shape == (4, 3, 2)
    np.testing.assert_array_equal(w[1], v[1:4])
    assert np.shares_memory(w, v)


def test_pairs_target_is_next_state():
    z = np.arange(20, dtype=np.float32).reshape(10, 2)  # column 0 state, 1 action
    x, y = log_pairs(z, 3, 1)
    assert x.shape == (7, 6) and y.shape == (7, 1)
    np.testing.assert_array_equal(x[0], z[0:3].ravel())
    np.testing.assert_array_equal(y[:, 0], z[3:, 0])


def test_normaliser_fit_round_trip_and_range():
    logs = [make_log(np.array([5.0, 40, 75, 60])), make_log(np.array([10.0, 80, 20]), x=50)]
    n = Normaliser.fit(logs)
    allv = np.concatenate([lg.values for lg in logs])
    z = n.encode(allv)
    assert z.min() == pytest.approx(-1) and z.max() == pytest.approx(1)
    np.testing.assert_allclose(n.decode(z), allv)
    back = Normaliser.from_json(n.to_json())
    np.testing.assert_array_equal(back.low, n.low)


def test_constant_column_does_not_divide_by_zero():
    n = Normaliser.fit([make_log(np.full(5, 70.0))])  # angle always +30
    z = n.encode(np.array([[70.0, 30.0]]))
    assert np.all(np.isfinite(z)) and z.tolist() == [[0.0, 0.0]]


def test_normaliser_from_declared_ranges():
    n = Normaliser.from_schema(LANE_KEEPING_SCHEMA)
    np.testing.assert_allclose(n.encode(np.array([[0.0, -90.0], [100.0, 90.0]])), [[-1, -1], [1, 1]])


def test_dataset_per_log_pairs_and_length_check():
    logs = [make_log(np.linspace(10, 70, 15)), make_log(np.linspace(70, 10, 12))]
    ds = Dataset.build(logs, history=10)
    assert [x.shape for x in ds.X] == [(5, 20), (2, 20)]
    with pytest.raises(ValueError, match="need more than the history"):
        Dataset.build([make_log(np.linspace(10, 70, 10))], history=10)


def test_split_is_by_whole_log_disjoint_and_seeded():
    logs = [make_log(np.full(12, 40.0), run=str(i)) for i in range(10)]
    a = split_logs(logs, [0.6, 0.2, 0.2], seed=3)
    b = split_logs(logs, [0.6, 0.2, 0.2], seed=3)
    ids = [[lg.meta.run_id for lg in part] for part in a]
    assert ids == [[lg.meta.run_id for lg in part] for part in b]
    flat = sum(ids, [])
    assert sorted(flat, key=int) == [str(i) for i in range(10)] and len(set(flat)) == 10
    assert [len(p) for p in a] == [6, 2, 2]
