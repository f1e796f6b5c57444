"""Controllers: the lane-keeping rule against every row of the real data, PID, user plug-ins."""

from __future__ import annotations

import numpy as np
import pytest

from envi_py.controllers import ControllerSpec, parse_params


def test_lane_keeping_matches_every_real_row(real_logs):
    mismatches = 0
    for lg in real_logs:
        ctrl = ControllerSpec("lane-keeping", {"x": lg.param["x"]}).build()
        mismatches += int(np.sum(ctrl(lg.states) != lg.actions))
    assert mismatches == 0


def test_lane_keeping_on_threshold_goes_straight():
    ctrl = ControllerSpec("lane-keeping", {"x": 30}).build()
    out = ctrl(np.array([[39.9], [40.0], [40.1]]))
    assert out.ravel().tolist() == [-30.0, 0.0, 30.0]


def test_pid_clamps_and_stops_integrating_when_saturated():
    ctrl = ControllerSpec("pid", {"kp": 1.0, "ki": 10.0, "setpoint": 0.0, "dt": 0.1,
                                  "out_min": -5.0, "out_max": 5.0}).build()
    ctrl.reset(1)
    outs = [float(ctrl(np.array([[100.0]]))[0, 0]) for _ in range(5)]
    assert outs == [5.0] * 5
    # after saturation the integral did not wind up: a negative error acts at once
    assert float(ctrl(np.array([[-1.0]]))[0, 0]) < 0


def test_pid_proportional_and_derivative():
    ctrl = ControllerSpec("pid", {"kp": 2.0, "kd": 0.5, "setpoint": 1.0, "dt": 0.5}).build()
    ctrl.reset(2)
    first = ctrl(np.array([[2.0], [0.0]]))
    np.testing.assert_allclose(first.ravel(), [2.0, -2.0])
    second = ctrl(np.array([[3.0], [0.0]]))  # error 2 (was 1): kp*2 + kd*(1/0.5)
    np.testing.assert_allclose(second.ravel(), [4.0 + 1.0, -2.0])


def user_controller(states: np.ndarray, gain: float = 1.0) -> np.ndarray:
    return -gain * states[:, :1]


def test_user_controller_by_import_path():
    ctrl = ControllerSpec("tests.test_controllers:user_controller", {"gain": 2.0}).build()
    np.testing.assert_allclose(ctrl(np.array([[1.0], [-3.0]])).ravel(), [-2.0, 6.0])


def test_unknown_controller_and_parameters_are_errors():
    with pytest.raises(ValueError, match="unknown controller"):
        ControllerSpec("nope").build()
    with pytest.raises(ValueError, match="unknown parameter"):
        ControllerSpec("lane-keeping", {"gain": 1}).build()
    with pytest.raises(ValueError, match="cannot import"):
        ControllerSpec("no_such_module:fn").build()
    assert parse_params(["x=30", "mode=fast"]) == {"x": 30.0, "mode": "fast"}
