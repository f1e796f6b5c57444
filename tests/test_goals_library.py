"""Standard goal metrics on hand-made traces with known answers, the registry and user metrics."""

from __future__ import annotations

import math
import textwrap

import numpy as np
import pytest

from envi_py.goals import library as lib
from envi_py.goals.library import STANDARD
from envi_py.goals.registry import metric

PERIOD = 40.0


def second_order_step(zeta: float, wn: float = 1.0, dt: float = 0.001, t_end: float = 40.0) -> np.ndarray:
    """Unit step response of wn^2 / (s^2 + 2 zeta wn s + wn^2), underdamped, sampled every dt seconds."""
    t = np.arange(0.0, t_end, dt)
    wd = wn * math.sqrt(1 - zeta**2)
    return 1 - np.exp(-zeta * wn * t) * (np.cos(wd * t) + zeta / math.sqrt(1 - zeta**2) * np.sin(wd * t))


@pytest.mark.parametrize("zeta", [0.1, 0.3, 0.5, 0.7])
def test_overshoot_of_a_step_response_matches_its_damping(zeta: float) -> None:
    y = second_order_step(zeta)[None, :]
    expected = math.exp(-math.pi * zeta / math.sqrt(1 - zeta**2))
    assert metric("overshoot")(y, 1.0, setpoint=1.0)[0] == pytest.approx(expected, abs=1e-5)
    # mirrored: the same response going down undershoots by the same amount
    assert metric("undershoot")(-y, 1.0, setpoint=-1.0)[0] == pytest.approx(expected, abs=1e-5)


def test_overshoot_and_undershoot_are_zero_when_never_beyond() -> None:
    y = np.array([[0.0, 0.5, 1.0, 1.0]])
    assert lib.overshoot(y, 1.0)[0] == 0.0
    assert lib.undershoot(y, 0.0)[0] == 0.0
    assert lib.undershoot(y, 1.0)[0] == 1.0


def test_deviations_of_a_step() -> None:
    y = np.array([[0.0] * 5 + [10.0] * 5])
    assert lib.max_abs_dev(y, 4.0)[0] == 6.0
    assert lib.mean_abs_dev(y, 4.0)[0] == 5.0


def test_time_in_band_of_a_ramp_is_its_share_of_samples() -> None:
    y = np.arange(100.0)[None, :]
    assert lib.time_in_band(y, 50.0, 10.0)[0] == pytest.approx(21 / 100)  # 40..60 inclusive


def test_settling_time_is_the_end_of_the_last_excursion() -> None:
    y = np.array(
        [
            [5.0, 5, 0, 0, 5, 0, 0, 0],  # last outside at index 4 -> settled from 5
            [0.0, 0, 0, 0, 0, 0, 0, 0],  # never outside
            [0.0, 0, 0, 0, 0, 0, 0, 5],
        ]
    )  # still outside at the end: never settles
    assert metric("settling_time")(y, PERIOD, setpoint=0.0, band=1.0).tolist() == [5 * PERIOD, 0.0, 8 * PERIOD]


def test_settling_time_of_a_step_response_is_where_the_envelope_stays_in_band() -> None:
    zeta, dt = 0.3, 0.001
    y = second_order_step(zeta, dt=dt)
    ts = lib.settling_time(y[None, :], dt, 1.0, 0.02)[0]
    k = round(ts / dt)
    assert np.all(np.abs(y[k:] - 1) <= 0.02) and abs(y[k - 1] - 1) > 0.02
    # the classic estimate 4 / (zeta wn) bounds it from above (the envelope reaches 2% there)
    assert ts <= 4 / zeta


def test_rise_time_of_ramps() -> None:
    up = np.arange(101.0)[None, :]  # 0..100: 10% at sample 10, 90% at sample 90
    assert lib.rise_time(up, PERIOD)[0] == 80 * PERIOD
    assert lib.rise_time(100 - up, PERIOD)[0] == 80 * PERIOD  # falling the same way
    assert lib.rise_time(up, PERIOD, 0.2, 0.5)[0] == 30 * PERIOD
    # towards a setpoint it never reaches: never rises
    assert lib.rise_time(up, PERIOD, setpoint=200.0)[0] == 101 * PERIOD
    assert lib.rise_time(np.full((1, 5), 3.0), PERIOD)[0] == 0.0
    with pytest.raises(ValueError, match="low_frac < high_frac"):
        lib.rise_time(up, PERIOD, 0.9, 0.1)


def test_integrals_of_a_constant_error() -> None:
    t, e = 50, 3.0
    y = np.full((2, t), 10.0 + e)
    assert lib.iae(y, PERIOD, 10.0).tolist() == [e * t * PERIOD] * 2
    assert lib.ise(y, PERIOD, 10.0).tolist() == [e * e * t * PERIOD] * 2


@pytest.mark.parametrize("k", [1, 3, 7])
def test_oscillations_of_a_sine_count_its_periods(k: int) -> None:
    t = np.arange(400)
    y = 40 + 10 * np.sin(2 * np.pi * k * t / 400 + 0.5)  # crossings at n*pi - 0.5, n = 1..2k
    assert lib.oscillations(y[None, :], 40.0)[0] == k


def test_touching_the_setpoint_is_not_a_crossing() -> None:
    y = np.array([[1.0, 0, 1], [1.0, 0, -1], [0.0, 0, 1]])
    assert lib.oscillations(y, 0.0).tolist() == [0.0, 0.5, 0.0]


def test_summary_statistics() -> None:
    rng = np.random.default_rng(3)
    y = rng.normal(size=(4, 30))
    assert np.array_equal(metric("min")(y, PERIOD), y.min(axis=1))
    assert np.array_equal(metric("max")(y, PERIOD), y.max(axis=1))
    assert np.allclose(metric("mean")(y, PERIOD), y.mean(axis=1))
    assert np.allclose(metric("std")(y, PERIOD), y.std(axis=1))


def test_registry_parameters_units_and_scales() -> None:
    assert STANDARD["time_in_band"].params == ("setpoint", "band")
    assert STANDARD["rise_time"].params == ("low_frac", "high_frac", "setpoint")
    assert STANDARD["iae"].unit("%") == "%*ms"
    assert STANDARD["ise"].unit("cm") == "cm^2*ms"
    assert STANDARD["settling_time"].unit("cm") == "ms"
    assert STANDARD["time_in_band"].unit("cm") == ""
    assert STANDARD["max_abs_dev"].unit("cm") == "cm"
    assert STANDARD["max_abs_dev"].scale(0, 255, 100, PERIOD, {}) == 255
    assert STANDARD["settling_time"].scale(0, 255, 100, PERIOD, {}) == 100 * PERIOD
    assert STANDARD["iae"].scale(0, 100, 100, PERIOD, {}) == 100 * 100 * PERIOD
    assert STANDARD["time_in_band"].scale(0, 100, 100, PERIOD, {}) == 1
    assert STANDARD["std"].scale(-math.inf, math.inf, 100, PERIOD, {}) is None


@pytest.mark.parametrize(
    ("name", "params", "message"),
    [
        ("max_abs_dev", {}, "needs parameter 'setpoint'"),
        ("max_abs_dev", {"setpoint": 1, "band": 2}, "no parameter 'band'"),
        ("nonsense", {}, "unknown goal metric 'nonsense'"),
    ],
)
def test_bad_metric_use_is_a_value_error(name: str, params: dict, message: str) -> None:
    with pytest.raises(ValueError, match=message):
        metric(name)(np.zeros((2, 5)), PERIOD, **params)


def test_nan_trace_is_refused() -> None:
    y = np.zeros((2, 5))
    y[1, 2] = np.nan
    with pytest.raises(ValueError, match="NaN"):
        metric("mean")(y, PERIOD)


@pytest.fixture
def user_module(tmp_path, monkeypatch):
    (tmp_path / "my_goals.py").write_text(
        textwrap.dedent("""
        import numpy as np

        def peak_to_peak(trace, period_ms, scale=1.0):
            return np.ptp(trace, axis=1) * scale

        def first_sample(trace):
            return trace[:, 0]

        def wrong_shape(trace):
            return trace
    """)
    )
    monkeypatch.syspath_prepend(str(tmp_path))
    return "my_goals"


def test_user_metric_by_import_path(user_module: str) -> None:
    m = metric(f"{user_module}:peak_to_peak")
    assert m.params == ("scale",) and m.uses_period
    y = np.array([[0.0, 4, 1], [2.0, 2, 2]])
    assert m(y, PERIOD, scale=2.0).tolist() == [8.0, 0.0]
    assert metric(f"{user_module}:first_sample")(y, PERIOD).tolist() == [0.0, 2.0]


def test_user_metric_with_wrong_output_shape_names_the_function(user_module: str) -> None:
    with pytest.raises(ValueError, match=r"my_goals:wrong_shape.*expected one value per run: \(2,\)"):
        metric(f"{user_module}:wrong_shape")(np.zeros((2, 5)), PERIOD)


@pytest.mark.parametrize(
    ("path", "message"),
    [
        ("no_such_module_xyz:f", "cannot import module 'no_such_module_xyz'"),
        ("my_goals:missing", "has no function 'missing'"),
    ],
)
def test_user_metric_import_errors(user_module: str, path: str, message: str) -> None:
    with pytest.raises(ValueError, match=message):
        metric(path)
