"""A saturating sensor's jump to its limit is an event of the model, the same in every engine.

The car's ultrasonic sensor reads 255 when it loses the echo. A Gaussian head fitted to such data
stretches its spread over the jumps (simulated distance steps of sd 14 cm against 1.2 cm real);
the model instead predicts the jump as an event with its own probability and fits the value head on
in-range readings only. These tests pin that design: detection from the description, the loss,
decoding, the export and the native engine's draws against PyTorch's.
"""

from __future__ import annotations

import numpy as np
import pytest
import torch
from scipy import stats

from envi_py import native
from envi_py.export import to_onnx
from envi_py.simulate import initial_windows, rollout
from envi_py.train.bc import bc_loss, train_bc
from envi_py.train.common import limit_events
from envi_py.twin.car import car_versions, generate_car_versions


@pytest.fixture(scope="module")
def car_logs():
    return generate_car_versions(6, seed=5, versions=[0, 2])


@pytest.fixture(scope="module")
def car_ckpt(car_logs):
    return train_bc(car_logs, epochs=3, lr=1e-3, seed=0, hidden=(32,))


def test_only_a_saturating_state_that_reaches_its_limit_gets_an_event(car_logs, real_logs):
    assert limit_events(car_logs) == ((1, 255.0),)  # distance saturates at 255 and some runs read it
    assert limit_events(real_logs[:20]) == ()  # the lane robot's colour is not declared saturating
    no_echo_lost = generate_car_versions(
        3, seed=5, versions=[0], dropout_prob=0, far_start_prob=0, echo_range=[900, 900]
    )
    assert limit_events(no_echo_lost) == ()


def test_event_targets_are_exactly_the_limit_readings(car_ckpt, car_logs):
    data = car_ckpt.dataset(car_logs)
    _, y = data.stacked()
    ev = car_ckpt.limit_event_targets(y)
    distance_next = np.concatenate([lg.states[car_ckpt.config.history :, 1] for lg in car_logs])
    assert ev.shape == (len(y), 1) and ev.any()
    np.testing.assert_array_equal(ev[:, 0], distance_next == 255)


def test_the_value_head_is_not_trained_on_limit_readings(car_ckpt, car_logs):
    x, y = car_ckpt.dataset(car_logs).stacked()
    x, y = torch.from_numpy(x), torch.from_numpy(y)
    ev = torch.from_numpy(car_ckpt.limit_event_targets(y.numpy()))
    moved = y.clone()
    moved[ev[:, 0], 1] = -0.9  # what the limit readings' value targets are must not matter
    a, b = bc_loss(car_ckpt.model, x, y, ev), bc_loss(car_ckpt.model, x, moved, ev)
    assert torch.equal(a, b)
    other = y.clone()
    other[~ev[:, 0], 1] += 0.05  # while the in-range ones do
    assert not torch.equal(a, bc_loss(car_ckpt.model, x, other, ev))
    # and without events the loss is the plain Gaussian NLL, as before
    mean, log_std = car_ckpt.model(x)
    plain = torch.nn.functional.gaussian_nll_loss(mean, y, (2 * log_std).exp(), full=False)
    assert torch.allclose(bc_loss(car_ckpt.model, x, y), plain)


def test_decoding_puts_the_limit_reading_where_an_event_happens(car_ckpt):
    rng = np.random.default_rng(0)
    z = rng.uniform(-0.9, 0.9, (50, 2))
    events = rng.random((50, 1)) < 0.3
    s = car_ckpt.decode_states(z, events)
    assert np.all(s[events[:, 0], 1] == 255.0) and np.all(s[~events[:, 0], 1] < 255.0)
    np.testing.assert_array_equal(s[:, 0], car_ckpt.decode_states(z)[:, 0])
    st = car_ckpt.decode_states_torch(torch.from_numpy(z), torch.from_numpy(events)).numpy()
    np.testing.assert_allclose(st, s, rtol=0, atol=1e-9)


def test_a_saturating_sensor_is_clamped_to_its_in_range_readings(car_ckpt, car_logs):
    """The value head draws an in-range reading, the event head the no-echo one: clamped to the full
    observed range (up to 255) a model started with the echo lost drew first readings of 190-250 cm,
    beyond any the sensor gives (real ones stop at 152)."""
    distance = np.concatenate([lg.states[:, 1] for lg in car_logs])
    in_range = distance[distance != 255]
    low, high = car_ckpt.limits()
    assert (low[1], high[1]) == (in_range.min(), in_range.max()) and high[1] < 255
    colour = np.concatenate([lg.states[:, 0] for lg in car_logs])
    assert (low[0], high[0]) == (colour.min(), colour.max())  # a state without events: its whole range
    z = np.full((4, 2), 0.99)  # near the normaliser's top: a distance above every in-range reading
    events = np.array([[False], [True], [False], [True]])
    s = car_ckpt.decode_states(z, events)
    np.testing.assert_array_equal(s[:, 1], [high[1], 255.0, high[1], 255.0])
    st = car_ckpt.decode_states_torch(torch.from_numpy(z), torch.from_numpy(events)).numpy()
    np.testing.assert_array_equal(st, s)


def _with_event_probability(ckpt, logit: float):
    """The checkpoint with its event head answering ``logit`` whatever the window, and a value head
    too sure to reach the limit by itself (so every limit reading is an event)."""
    with torch.no_grad():
        ckpt.model.event.weight.zero_()
        ckpt.model.event.bias.fill_(logit)
        ckpt.model.log_std.weight.zero_()
        ckpt.model.log_std.bias.fill_(-7.0)
    return ckpt


def test_the_export_carries_the_event_head_and_says_whose_it_is(car_ckpt):
    model = to_onnx(car_ckpt)
    assert [o.name for o in model.graph.output] == ["mean", "log_std", "event_logit"]
    meta = {p.key: p.value for p in model.metadata_props}
    assert meta["envi.limit_events"] == "[[1, 255.0]]"


@pytest.mark.skipif(not native.available(), reason="native engine not built")
@pytest.mark.parametrize("p", [0.0, 0.3, 1.0])
def test_native_and_pytorch_draw_events_at_the_same_rate(car_logs, p):
    ckpt = train_bc(car_logs, epochs=2, lr=1e-3, seed=1, hidden=(16,))
    logit = -30.0 if p == 0 else 30.0 if p == 1 else float(np.log(p / (1 - p)))
    _with_event_probability(ckpt, logit)
    init = initial_windows(car_logs[:4], ckpt.config.history)
    spec = car_versions()[0]
    steps, runs = 60, 50
    ns = ckpt.config.n_state
    h = ckpt.config.history
    got = native.rollout(native.load(ckpt), spec, init, steps, runs, seed=3)[:, h:, 1]
    want = rollout(ckpt, spec, init, steps, runs, seed=3)[:, h:, 1]
    assert got.shape == want.shape == (4 * runs, steps) and ns == 2
    n = got.size
    for sim in (got, want):
        k = int(np.sum(sim == 255.0))
        if p in (0.0, 1.0):
            assert k == n * p  # certain events: every reading, or none (the value head never reads 255 here)
        else:
            ci = stats.binomtest(k, n).proportion_ci(0.999)
            assert ci.low <= p <= ci.high, (k, n)


@pytest.mark.skipif(not native.available(), reason="native engine not built")
def test_the_loader_refuses_an_event_head_without_its_metadata(car_ckpt):
    model = to_onnx(car_ckpt)
    keep = [p for p in model.metadata_props if p.key != "envi.limit_events"]
    del model.metadata_props[:]
    model.metadata_props.extend(keep)
    with pytest.raises(Exception, match="limit_events"):
        native._native().Model(model.SerializeToString())
