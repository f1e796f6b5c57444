"""The multi-step loss unrolls the model on its own predictions, with logged actions and limit readings.

Pinned here: one step of it is exactly behaviour cloning's loss; later steps see the model's own
prediction in the window, not the logged state; a limit reading (the car's 255) enters the window
as logged; a run too short to unroll contributes nothing; training with it is recorded.
"""

from __future__ import annotations

import numpy as np
import pytest
import torch

from envi_py.train.bc import bc_loss, head_loss, train_bc
from envi_py.train.multistep import MultiStepLoss
from envi_py.twin.car import generate_car_versions


@pytest.fixture(scope="module")
def car_logs():
    # frequent drop-outs: single 255 readings (limit events) in the middle of runs
    return generate_car_versions(3, seed=5, versions=[0, 2], dropout_prob=0.05)


@pytest.fixture(scope="module")
def car_ckpt(car_logs):
    torch.manual_seed(0)
    return train_bc(car_logs, epochs=2, seed=0, hidden=(16,), history=4)


def _unrolled(ckpt, logs, horizon, stride):
    data = ckpt.dataset(logs)
    events = [ckpt.limit_event_targets(y) for y in data.Y]
    return data, events, MultiStepLoss(data, ckpt.config.context, events, horizon, stride)


def test_one_step_is_behaviour_cloning(car_ckpt, car_logs):
    data, events, loss = _unrolled(car_ckpt, car_logs, horizon=1, stride=1)
    for i in range(len(car_logs)):
        want = bc_loss(car_ckpt.model, torch.tensor(data.X[i]), torch.tensor(data.Y[i]), torch.tensor(events[i]))
        torch.testing.assert_close(loss(car_ckpt.model, i, head_loss), want)


def _by_hand(ckpt, z, ev, start, horizon, force=True):
    """The unroll of one start window written out: the predicted mean enters the window, except
    where the logged next state is a limit reading."""
    hist, ns, model = ckpt.config.history, ckpt.config.n_state, ckpt.model
    window = torch.from_numpy(z[start : start + hist]).clone()
    total = torch.zeros(())
    for k in range(horizon):
        row = z[start + hist + k]
        heads = model.heads(window.reshape(1, -1))
        e = torch.from_numpy(ev[start + k : start + k + 1])
        total = total + head_loss(model, heads, torch.from_numpy(row[None, :ns]), e)
        state = heads[0][0].detach().clone()
        for j, (s, _) in enumerate(ckpt.config.limit_events):
            if force and ev[start + k, j]:
                state[s] = float(row[s])
        window = torch.cat([window[1:], torch.cat([state, torch.from_numpy(row[ns:])])[None]])
    return total / horizon


def test_later_steps_see_the_models_own_predictions(car_ckpt, car_logs):
    horizon = 6
    data, events, loss = _unrolled(car_ckpt, car_logs, horizon=horizon, stride=100)  # one start per log
    hist = car_ckpt.config.history
    for i, z in enumerate(data.z):
        got = loss(car_ckpt.model, i, head_loss)
        torch.testing.assert_close(got, _by_hand(car_ckpt, z, events[i], 0, horizon))
        # teacher forcing every step (windows of logged rows) would be the mean one-step loss instead
        forced = bc_loss(
            car_ckpt.model,
            torch.tensor(data.X[i][:horizon]),
            torch.tensor(data.Y[i][:horizon]),
            torch.tensor(events[i][:horizon]),
        )
        assert not torch.allclose(got, forced)
        assert len(z) >= hist + horizon


def test_a_limit_reading_enters_the_window_as_logged(car_ckpt, car_logs):
    data, events, _ = _unrolled(car_ckpt, car_logs, horizon=1, stride=1)
    # a start whose unroll meets a limit reading before its last step (so a later step sees it)
    horizon = 5
    found = None
    for i, ev in enumerate(events):
        for o in range(len(ev) - horizon):
            if ev[o + 2 : o + horizon - 1, 0].any() and not ev[o : o + 2, 0].any():
                found = (i, o)
                break
        if found:
            break
    assert found is not None, "the fixture's logs must hold limit readings"
    i, o = found
    loss = MultiStepLoss(data, False, events, horizon, stride=1)
    torch.testing.assert_close(_sliced(loss, car_ckpt, i, o), _by_hand(car_ckpt, data.z[i], events[i], o, horizon))
    # and it matters: feeding the predicted value there instead gives another loss
    assert not torch.allclose(
        _sliced(loss, car_ckpt, i, o), _by_hand(car_ckpt, data.z[i], events[i], o, horizon, force=False)
    )


def _sliced(loss: MultiStepLoss, ckpt, i: int, o: int) -> torch.Tensor:
    """Log ``i``'s unroll loss from its start ``o`` alone (stride 1: start o is row o of the batch)."""
    keep = slice(o, o + 1)
    one = MultiStepLoss.__new__(MultiStepLoss)
    one.horizon, one.n_state = loss.horizon, loss.n_state
    one.windows, one.future = [loss.windows[i][keep]], [loss.future[i][keep]]
    one.context, one.events = [None], [loss.events[i][keep]]
    return one(ckpt.model, 0, head_loss)


def test_a_run_too_short_to_unroll_adds_nothing(car_ckpt, car_logs):
    data, events, _ = _unrolled(car_ckpt, car_logs, horizon=1, stride=1)
    loss = MultiStepLoss(data, False, events, horizon=len(data.z[0]), stride=1)
    assert loss(car_ckpt.model, 0, head_loss).item() == 0.0
    with pytest.raises(ValueError, match="horizon and stride must be positive"):
        MultiStepLoss(data, False, events, horizon=0)


def test_training_with_it_is_recorded_and_changes_the_model(car_logs):
    a = train_bc(car_logs, epochs=2, seed=0, hidden=(16,), history=4)
    b = train_bc(car_logs, epochs=2, seed=0, hidden=(16,), history=4, multistep=3)
    assert b.record.hyper["multistep"] == 3 and a.record.hyper["multistep"] == 0
    wa, wb = a.model.state_dict(), b.model.state_dict()
    assert any(not torch.equal(wa[k], wb[k]) for k in wa)
    assert np.isfinite([v.sum().item() for v in wb.values()]).all()
