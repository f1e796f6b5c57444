"""Controllers: the lane-keeping rule against every row of the real data, PID, user plug-ins."""

from __future__ import annotations

import numpy as np
import pytest

from envi_py.controllers import ControllerSpec, parse_params
from envi_py.logs import group_by_controller

from .conftest import make_log


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
    ctrl = ControllerSpec(
        "pid", {"kp": 1.0, "ki": 10.0, "setpoint": 0.0, "dt": 0.1, "out_min": -5.0, "out_max": 5.0}
    ).build()
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


@pytest.mark.parametrize("value", ["nan", "NaN", "inf", "-inf", "Infinity", "1e999"])
def test_parse_params_refuses_a_non_finite_value_naming_the_parameter(value):
    """A NaN gain once simulated logs full of NaN; only the CLIs refused it, not the library."""
    with pytest.raises(ValueError, match=rf"parameter 'gain={value}': gain is non-finite"):
        parse_params(["x=30", f"gain={value}"])
    with pytest.raises(ValueError, match=rf"^--param 'gain={value}': gain is non-finite"):
        parse_params([f"gain={value}"], "--param")


# ------------------------------------------------------------ the protocol: widths, memory, warm-up


def test_a_one_output_controller_on_a_two_action_model_is_an_error_naming_it():
    from envi_py.controllers import WidthError

    with pytest.raises(WidthError, match="'pid\\(kp=1\\)' drives 1 action channel\\(s\\), the model has 2"):
        ControllerSpec("pid", {"kp": 1}).build(n_state=2, n_action=2)
    with pytest.raises(WidthError, match="reads state channel 3"):
        ControllerSpec("pid", {"input": 3}).build(n_state=2, n_action=1)
    ctrl = ControllerSpec("tests.test_controllers:user_controller").build(n_state=1, n_action=2)
    with pytest.raises(WidthError, match="answered shape \\(2, 1\\) for 2 run\\(s\\); the model needs \\(2, 2\\)"):
        ctrl(np.array([[1.0], [2.0]]))


def test_combine_drives_one_action_per_loop_from_its_own_input():
    spec = ControllerSpec(
        "combine",
        {
            "loops": [
                {"name": "bang-bang", "params": {"x": 20, "threshold": 40}},
                {
                    "name": "pid",
                    "params": {"input": 1, "kp": 2.0, "setpoint": 30, "offset": 100, "out_min": 0, "out_max": 720},
                },
            ]
        },
    )
    ctrl = spec.build(n_state=2, n_action=2, period_ms=40)
    ctrl.reset(2)
    out = ctrl(np.array([[50.0, 40.0], [30.0, 10.0]]))
    np.testing.assert_allclose(out, [[20.0, 120.0], [-20.0, 60.0]])


def test_warm_up_on_sigma0_gives_the_memory_of_a_controller_that_ran_from_the_start():
    rng = np.random.default_rng(0)
    states = rng.uniform(0, 100, (3, 12, 1))
    spec = ControllerSpec("pid", {"kp": 0.7, "ki": 3.0, "kd": 0.05, "out_min": -30, "out_max": 30})
    whole = spec.build(1, 1, 40.0)
    whole.reset(3)
    answers = [whole(states[:, t]) for t in range(12)]
    warm = spec.build(1, 1, 40.0)
    warm.reset(3)
    warm.warmup(states[:, :10], np.zeros((3, 10, 1)))
    np.testing.assert_array_equal(warm(states[:, 10]), answers[10])
    np.testing.assert_array_equal(warm(states[:, 11]), answers[11])
    cold = spec.build(1, 1, 40.0)
    cold.reset(3)
    assert not np.array_equal(cold(states[:, 10]), answers[10])  # without warm-up: empty integral, no derivative


def test_pid_dt_defaults_to_the_period_it_is_built_for():
    fast = ControllerSpec("pid", {"kp": 0.0, "ki": 1.0, "setpoint": 0.0}).build(1, 1, period_ms=10.0)
    fast.reset(1)
    assert float(fast(np.array([[1.0]]))[0, 0]) == pytest.approx(0.01)


class CountingController:
    """A user's controller with memory, following the documented protocol."""

    def __init__(self, gain: float = 1.0) -> None:
        self.gain = gain

    def reset(self, n: int) -> None:
        self.seen = np.zeros((n, 1))

    def warmup(self, states: np.ndarray, actions: np.ndarray) -> None:
        self.seen += states.shape[1]

    def __call__(self, states: np.ndarray) -> np.ndarray:
        self.seen += 1
        return self.gain * self.seen


def test_rollout_warms_the_controller_up_on_sigma0(tmp_path):
    from envi_py.simulate import rollout
    from envi_py.train.common import model_config, new_checkpoint

    from .conftest import make_log

    logs = [make_log(np.linspace(20, 60, 30), run=str(i)) for i in range(2)]
    ck = new_checkpoint("bc", logs, [], model_config(logs, history=10, hidden=(8,)), 0, {})
    out = rollout(
        ck,
        ControllerSpec("tests.test_controllers:CountingController", {"gain": 2.0}),
        np.stack([lg.values[:10] for lg in logs]),
        steps=3,
    )
    assert out[:, 10:, 1].tolist() == [[22.0, 24.0, 26.0]] * 2  # 10 warm-up rows, then 11, 12, 13


@pytest.mark.parametrize(
    "params, why",
    [
        ({"kp": None}, "'kp' must be a number"),
        ({"input": 1.5}, "'input' must be"),
        ({"input": True}, "'input' must be"),
        ({"input": "1"}, "'input' must be"),
    ],
)
def test_bad_parameter_types_are_value_errors_naming_the_controller(params, why):
    with pytest.raises(ValueError, match=why):
        ControllerSpec("pid", params).build(n_state=2, n_action=1)


def test_a_version_is_keyed_by_its_numbers_values():
    """``x=30`` from a command line and ``30.0`` from a log were two versions (a report showed x = 30
    twice); nested loops too. A boolean is not the number 1, and 30.5 is not 30."""
    assert ControllerSpec("lane-keeping", {"x": 30}) == ControllerSpec("lane-keeping", {"x": 30.0})
    assert len({ControllerSpec("lane-keeping", {"x": 30}), ControllerSpec("lane-keeping", {"x": 30.0})}) == 1
    loops = [{"name": "pid", "params": {"kp": 2, "out_max": 40.0}}]
    assert ControllerSpec("combine", {"loops": loops}) == ControllerSpec(
        "combine", {"loops": [{"name": "pid", "params": {"kp": 2.0, "out_max": 40}}]}
    )
    assert ControllerSpec("pid", {"kp": 1}) != ControllerSpec("pid", {"kp": True})
    assert ControllerSpec("lane-keeping", {"x": 30}) != ControllerSpec("lane-keeping", {"x": 30.5})
    a, b = make_log([40.0] * 12, x=30), make_log([41.0] * 12, x=30)
    b.meta.controller = {"name": "lane-keeping", "params": {"x": 30.0}}
    assert list(map(len, group_by_controller([a, b]).values())) == [2]
