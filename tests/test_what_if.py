"""What-if tests: the command transforms, and the actuator-lag what-if on a model of a clean twin,
fed logs of the same twin with and without an actuator lag (the known answer)."""

from __future__ import annotations

import numpy as np
import pytest

from envi_py.diagnose.effects import WHAT_IF_BAR
from envi_py.diagnose.validate import LANE
from envi_py.diagnose.residuals import one_step_residuals
from envi_py.diagnose.what_if import ACTUATOR_LAGS, delayed, input_what_if, lagged
from envi_py.train import train
from envi_py.twin import TwinProfile, generate


def test_delayed_holds_the_first_command_and_shifts_the_rest():
    a = np.array([[1.0], [2.0], [3.0], [4.0]])
    np.testing.assert_array_equal(delayed(a, 2)[:, 0], [1, 1, 1, 2])
    np.testing.assert_array_equal(delayed(a, 0), a)


def test_lagged_is_a_first_order_step_response():
    a = np.concatenate([np.zeros((1, 1)), np.ones((20, 1))])
    y = lagged(a, 3.0)[:, 0]
    np.testing.assert_allclose(y[1:], 1 - np.exp(-np.arange(1, 21) / 3.0))


@pytest.fixture(scope="module")
def clean_model():
    logs = generate(LANE, 15, 100, {}, seed=0, profile=TwinProfile())
    return train("bc", logs[:12], logs[12:], seed=0, epochs=80, lr=1e-3, history=4, head="deterministic")


def test_a_lagging_actuator_is_found_by_feeding_the_model_lagged_commands(clean_model):
    """A longer actuator lag is fitted by a longer first-order lag, and each removes most of the
    residual. (The fitted time constant runs about 1.5x the twin's: the model of the clean twin
    already holds the response of its own actuator, which the lag comes on top of.)"""
    fitted = []
    for tau_ms in (60.0, 120.0, 240.0):
        lagging = generate(LANE, 12, 100, {"lag": tau_ms}, seed=1, profile=TwinProfile())
        (w,) = input_what_if(clean_model, lagging, one_step_residuals(clean_model, lagging), ACTUATOR_LAGS)
        assert w.share > 0.5 and w.p < 1e-3, (tau_ms, w)
        assert "first-order lag" in w.label, (tau_ms, w)
        fitted.append(float(w.label.split("lag of ")[1].split()[0]))
    assert fitted[0] < fitted[1] < fitted[2], fitted


def test_logs_of_the_world_the_model_knows_gain_nothing_from_a_what_if(clean_model):
    same = generate(LANE, 12, 100, {}, seed=1, profile=TwinProfile())
    (w,) = input_what_if(clean_model, same, one_step_residuals(clean_model, same), ACTUATOR_LAGS)
    assert w.share < WHAT_IF_BAR and w.p > 0.05, w
