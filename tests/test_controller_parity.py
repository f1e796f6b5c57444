"""The C++ controllers against envi_py.controllers, with warm-up, on real and synthetic traces; and
the native engine against the simulator's protocol on a 2-state/2-action model with a combine."""

from __future__ import annotations

import inspect
import json

import numpy as np
import pytest
import torch

from envi_py import native, simulate
from envi_py.controllers import ControllerSpec, WidthError
from envi_py.dataset import Normaliser
from envi_py.export import post_processing
from envi_py.model import Checkpoint, EnvModel, ModelConfig, TrainingRecord
from envi_py.system import Channel, LogSchema

pytestmark = pytest.mark.skipif(not native.available(), reason="native engine not built")

HISTORY = 10
PID_FULL = ControllerSpec(
    "pid", {"kp": 0.8, "ki": 6.0, "kd": 0.05, "setpoint": 42.0, "out_min": -25.0, "out_max": 25.0, "offset": 3.0}
)
PID_SLOW = ControllerSpec("pid", {"kp": 0.3, "ki": 40.0, "out_min": -5, "out_max": 20, "dt": 0.1})
LANE = ControllerSpec("lane-keeping", {"x": 30})
COMBINE = ControllerSpec(
    "combine",
    {
        "loops": [
            {
                "name": "pid",
                "params": {
                    "kp": 0.5,
                    "ki": 4.0,
                    "kd": 0.02,
                    "setpoint": 45.0,
                    "out_min": -20,
                    "out_max": 20,
                    "input": 1,
                    "offset": -1.5,
                },
            },
            {"name": "bang-bang", "params": {"x": 12.0, "threshold": 38.0, "input": 0}},
        ]
    },
)
SINGLE = [
    PID_FULL,
    PID_SLOW,
    LANE,
    ControllerSpec("lane-keeping", {"x": 10, "threshold": 55}),
    ControllerSpec("bang-bang", {"x": 7, "threshold": 30, "input": 0}),
    ControllerSpec("pid", {"kp": 2.0, "ki": 5.0, "kd": 0.05, "setpoint": 45.0, "out_min": -40, "out_max": 40}),
    ControllerSpec("pid", {"kd": 0.2, "setpoint": 30}),
]


def python_actions(
    spec: ControllerSpec, states: np.ndarray, n_action: int, period_ms: float | None = None
) -> np.ndarray:
    """The reference: reset, warm up on the first HISTORY rows, then one call per row after them."""
    ctrl = spec.build(states.shape[2], n_action, period_ms)
    ctrl.reset(states.shape[0])
    ctrl.warmup(states[:, :HISTORY], np.zeros(states.shape[:2] + (n_action,))[:, :HISTORY])
    return np.stack([ctrl(states[:, t]) for t in range(HISTORY, states.shape[1])], axis=1)


def native_actions(
    spec: ControllerSpec, states: np.ndarray, n_action: int, period_ms: float | None = None
) -> np.ndarray:
    return native._native().controller_actions(
        json.dumps(spec.to_json()), np.ascontiguousarray(states), HISTORY, n_action, period_ms or 0.0
    )


def real_colours(real_logs, length: int = 100) -> np.ndarray:
    """The real lane-keeping logs' colour rows, (N, length, 1), logs shorter than that left out."""
    return np.stack([lg.states[:length] for lg in real_logs if len(lg) >= length])


def two_channels(colours: np.ndarray) -> np.ndarray:
    """A 2-channel trace made from real ones: each log's colour and another log's colour."""
    return np.concatenate([colours, np.roll(colours, 1, axis=0)], axis=2)


def random_traces(n_state: int, seed: int = 0) -> np.ndarray:
    rng = np.random.default_rng(seed)
    walk = np.clip(40 + np.cumsum(rng.normal(0, 9, (64, 100, n_state)), axis=1), 0, 100)
    uniform = rng.uniform(0, 100, (64, 100, n_state))
    flat = np.full((2, 100, n_state), 40.0)  # on the threshold and the setpoint-free PID's zero
    return np.concatenate([walk, uniform, flat])


@pytest.mark.parametrize("spec", SINGLE, ids=lambda s: s.label())
def test_single_loop_controllers_match_python_on_real_logs(spec, real_logs):
    states = real_colours(real_logs)
    assert len(states) >= 20
    want = python_actions(spec, states, 1, 40.0)
    got = native_actions(spec, states, 1, 40.0)
    assert got.shape == want.shape == (len(states), states.shape[1] - HISTORY, 1)
    np.testing.assert_array_equal(got, want)


@pytest.mark.parametrize("spec", SINGLE, ids=lambda s: s.label())
def test_single_loop_controllers_match_python_on_random_traces(spec):
    states = random_traces(1)
    np.testing.assert_array_equal(native_actions(spec, states, 1), python_actions(spec, states, 1))


def test_pid_exercises_every_term_and_saturation(real_logs):
    states = np.concatenate([real_colours(real_logs), random_traces(1)[:, :100]])
    got = native_actions(PID_FULL, states, 1, 40.0)
    assert 0.05 < np.mean(np.abs(got) == 25.0) < 0.95  # saturated often, not always: anti-windup matters
    # warm-up matters: without it the first action differs (no integral, derivative 0)
    cold = PID_FULL.build(1, 1, 40.0)
    cold.reset(len(states))
    assert np.mean(cold(states[:, HISTORY]) != got[:, 0]) > 0.5
    # each term moves the answer: a PID without it answers otherwise
    for term in ("ki", "kd", "offset"):
        without = ControllerSpec("pid", {**PID_FULL.params, term: 0.0})
        assert np.mean(native_actions(without, states, 1, 40.0) != got) > 0.3, term


def test_pid_default_dt_is_the_model_period():
    spec = ControllerSpec("pid", {"ki": 3.0, "kd": 0.1, "out_min": -1e9, "out_max": 1e9})
    states = random_traces(1, seed=2)
    for period in (None, 25.0, 100.0):
        np.testing.assert_array_equal(native_actions(spec, states, 1, period), python_actions(spec, states, 1, period))
    assert not np.array_equal(native_actions(spec, states, 1, 25.0), native_actions(spec, states, 1, 100.0))


@pytest.mark.parametrize("source", ["real", "random"])
def test_combine_two_states_two_actions_matches_python(source, real_logs):
    states = two_channels(real_colours(real_logs)) if source == "real" else random_traces(2, seed=5)
    want = python_actions(COMBINE, states, 2, 40.0)
    got = native_actions(COMBINE, states, 2, 40.0)
    assert got.shape == want.shape and got.shape[2] == 2
    np.testing.assert_array_equal(got, want)
    assert not np.array_equal(got[..., 0], got[..., 1])  # each action its own loop, nothing broadcast


@pytest.mark.parametrize(
    "spec, n_state, n_action, match",
    [
        (PID_FULL, 1, 2, "pid"),  # one output for two actions: never broadcast
        (COMBINE, 2, 1, "combine"),  # two outputs for one action
        (COMBINE, 1, 2, "pid"),  # the pid loop reads state 1 of a 1-state model
        (ControllerSpec("bang-bang", {"input": 3}), 2, 1, "bang-bang"),
    ],
)
def test_wrong_widths_raise_in_both_naming_the_controller(spec, n_state, n_action, match):
    states = random_traces(n_state)
    with pytest.raises(WidthError, match=match):
        python_actions(spec, states, n_action)
    with pytest.raises(ValueError, match=match) as err:
        native_actions(spec, states, n_action)
    assert type(err.value).__name__ == "WidthError"


@pytest.mark.parametrize(
    "spec, match",
    [
        (ControllerSpec("pid", {"kq": 1}), "unknown parameter"),
        (ControllerSpec("pid", {"kp": "fast"}), "'kp' must be a number"),
        (ControllerSpec("pid", {"kp": True}), "'kp' must be a number"),
        (ControllerSpec("pid", {"out_min": 5, "out_max": 1}), "out_min"),
        (ControllerSpec("pid", {"dt": -0.1}), "dt must be positive"),
        (ControllerSpec("bang-bang", {"input": "left"}), "'input' must be a state channel"),
        (ControllerSpec("combine", {"loops": []}), "combine"),
        (ControllerSpec("combine", {"loops": [{"name": "combine", "params": {"loops": []}}]}), "is not one of"),
        (ControllerSpec("steer"), "unknown controller 'steer'"),
    ],
)
def test_bad_specs_raise_in_both(spec, match):
    states = random_traces(1)
    with pytest.raises(ValueError, match=match):
        python_actions(spec, states, 1)
    with pytest.raises(ValueError, match=match):
        native_actions(spec, states, 1)


# --------------------------------------------------------------------------- engine parity


def two_by_two_ckpt(seed: int = 0) -> Checkpoint:
    """A small deterministic MLP over 2 states and 2 actions with seeded random weights."""
    torch.manual_seed(seed)
    schema = LogSchema(
        states=(Channel("color", "%", 0.0, 100.0), Channel("distance", "cm", 0.0, 100.0)),
        actions=(Channel("angle", "deg", -90.0, 90.0), Channel("speed", "%", -90.0, 90.0)),
    )
    model = EnvModel(ModelConfig(n_state=2, n_action=2, history=HISTORY, hidden=(32, 32))).eval()
    with torch.no_grad():  # sizeable weights, so the states wander over the range and the loops act
        for p in model.parameters():
            p.mul_(2.0)
    return Checkpoint(model, Normaliser.from_schema(schema), schema, TrainingRecord("bc", seed, period_ms=40.0))


@torch.no_grad()
def reference_rollout(ck: Checkpoint, spec: ControllerSpec, init: np.ndarray, steps: int, runs: int = 1) -> np.ndarray:
    """The simulator's protocol written out for a plain deterministic MLP: the controller is reset and
    warmed up on sigma_0's rows, then answers every predicted (post-processed) state."""
    cfg, norm = ck.config, ck.norm
    ns, hist, chans = cfg.n_state, cfg.history, cfg.channels
    post = post_processing(ck)
    low, high = np.array(post["limits"]).T
    batch = len(init) * runs
    ctrl = spec.build(ns, cfg.n_action, ck.record.period_ms)
    out = np.empty((batch, hist + steps, chans))
    out[:, :hist] = np.repeat(init, runs, axis=0)
    ctrl.reset(batch)
    ctrl.warmup(out[:, :hist, :ns], out[:, :hist, ns:])
    window = norm.encode(out[:, :hist]).astype(np.float32)
    for t in range(steps):
        z = ck.model.step(torch.from_numpy(window.reshape(batch, -1)), None)[0].numpy().astype(np.float64)
        s = norm.decode(np.concatenate([z, np.zeros((batch, chans - ns))], axis=1))[:, :ns]
        if post["clamp"]:
            s = np.clip(s, low, high)
        if post["round_to"] is not None:
            s = np.round(s / np.asarray(post["round_to"])) * np.asarray(post["round_to"])
        out[:, hist + t, :ns] = s
        out[:, hist + t, ns:] = ctrl(s)
        window = np.concatenate(
            [window[:, 1:], norm.encode(out[:, hist + t : hist + t + 1]).astype(np.float32)], axis=1
        )
    return out


def test_native_engine_runs_combine_on_two_states_two_actions_like_the_protocol(real_logs):
    ck = two_by_two_ckpt()
    colours = two_channels(real_colours(real_logs, HISTORY))[:12]
    ctrl = COMBINE.build(2, 2, 40.0)  # sigma_0's actions as the real loops would have logged them
    ctrl.reset(len(colours))
    init = np.concatenate([colours, np.stack([ctrl(colours[:, t]) for t in range(HISTORY)], axis=1)], axis=2)
    want = reference_rollout(ck, COMBINE, init, 80, runs=2)
    got = native.rollout(ck, COMBINE, init, 80, runs=2, threads=2)
    assert got.shape == want.shape == (24, HISTORY + 80, 4)
    np.testing.assert_array_equal(got[:, :HISTORY], want[:, :HISTORY])
    np.testing.assert_allclose(got, want, atol=1e-4, rtol=0)
    assert np.ptp(want[:, HISTORY:, :2]) > 10 and np.mean(np.abs(want[:, HISTORY:, 2]) == 20) < 0.9
    # the warm-up shows in the first simulated action: a cold PID answers otherwise
    cold = COMBINE.build(2, 2, 40.0)
    cold.reset(len(got))
    assert np.mean(cold(got[:, HISTORY, :2])[:, 0] != got[:, HISTORY, 2]) > 0.5


@pytest.mark.skipif(
    "warmup" not in inspect.getsource(simulate.rollout),
    reason="envi_py.simulate.rollout does not warm the controller up yet",
)
def test_native_engine_matches_the_pytorch_engine_with_combine(real_logs):
    ck = two_by_two_ckpt(seed=1)
    init = np.concatenate([two_channels(real_colours(real_logs, HISTORY))[:8], np.zeros((8, HISTORY, 2))], axis=2)
    want = simulate.rollout(ck, COMBINE, init, 60, runs=2)
    np.testing.assert_allclose(native.rollout(ck, COMBINE, init, 60, runs=2), want, atol=1e-4, rtol=0)
    np.testing.assert_allclose(reference_rollout(ck, COMBINE, init, 60, runs=2), want, atol=1e-4, rtol=0)


def test_native_engine_refuses_a_controller_of_the_wrong_width():
    ck = two_by_two_ckpt()
    init = np.full((1, HISTORY, 4), 40.0)
    with pytest.raises(ValueError, match="'pid' drives 1 action channel"):
        native.rollout(ck, PID_FULL, init, 5)
    with pytest.raises(ValueError, match="reads state channel 2"):
        native.rollout(
            ck,
            ControllerSpec("combine", {"loops": [{"name": "pid", "params": {"input": 2}}, {"name": "pid"}]}),
            init,
            5,
        )
