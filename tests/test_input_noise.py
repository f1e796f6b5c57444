"""Noisy training windows perturb the states only, by a multiple of their typical logged step."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from envi_py.train.bc import train_bc
from envi_py.train.input_noise import InputNoise, step_spread
from envi_py.train.state import TrainingState
from envi_py.twin.car import generate_car_versions


@pytest.fixture(scope="module")
def car_ckpt_and_data():
    logs = generate_car_versions(2, seed=3, versions=[0, 2])
    ckpt = train_bc(logs, epochs=1, seed=0, hidden=(8,), history=3, context=True)
    return ckpt, ckpt.dataset(logs)


def test_only_the_states_of_each_row_are_perturbed(car_ckpt_and_data):
    ckpt, data = car_ckpt_and_data
    cfg = ckpt.config
    x = torch.from_numpy(np.concatenate(data.X))
    assert x.shape[1] == cfg.in_features and cfg.context_dim > 0
    moved = InputNoise(data, cfg.row_width, 2.0)(x, np.random.default_rng(1)) != x
    per_row = moved[:, : cfg.history * cfg.row_width].reshape(len(x), cfg.history, cfg.row_width)
    assert per_row[..., : cfg.n_state].all()  # every state entry of every row moves
    assert not per_row[..., cfg.n_state :].any()  # actions (and derived channels) do not
    assert not moved[:, cfg.history * cfg.row_width :].any()  # nor does the run context


def test_the_noise_is_scale_times_the_robust_step_spread(car_ckpt_and_data):
    ckpt, data = car_ckpt_and_data
    cfg = ckpt.config
    spread = step_spread(data)
    # by hand: 1.4826 x median |change| of each state over every log (the 255 jumps do not count much)
    steps = np.concatenate([np.diff(z[:, : cfg.n_state], axis=0) for z in data.z])
    np.testing.assert_allclose(spread, 1.4826 * np.median(np.abs(steps), axis=0))
    x = torch.zeros(20000, cfg.in_features)
    noise = InputNoise(data, cfg.row_width, 3.0)(x, np.random.default_rng(0)).numpy()
    for j in range(cfg.n_state):
        sd = noise[:, j].std()
        assert sd == pytest.approx(3.0 * spread[j], rel=0.05)
    assert not np.array_equal(noise[:, 0], noise[:, cfg.row_width])  # independent per row


def test_zero_scale_changes_nothing_and_a_bad_scale_is_an_error(car_ckpt_and_data):
    ckpt, data = car_ckpt_and_data
    x = torch.from_numpy(data.X[0])
    assert torch.equal(InputNoise(data, ckpt.config.row_width, 0.0)(x, np.random.default_rng(0)), x)
    for bad in (-1.0, float("nan")):
        with pytest.raises(ValueError, match="scale must be a non-negative number"):
            InputNoise(data, ckpt.config.row_width, bad)


def test_training_with_noise_is_recorded_and_repeatable():
    logs = generate_car_versions(2, seed=3, versions=[0])
    a = train_bc(logs, epochs=2, seed=0, hidden=(8,), history=3, input_noise=1.0)
    b = train_bc(logs, epochs=2, seed=0, hidden=(8,), history=3, input_noise=1.0)
    c = train_bc(logs, epochs=2, seed=0, hidden=(8,), history=3)
    assert a.record.hyper["input_noise"] == 1.0 and c.record.hyper["input_noise"] == 0.0
    wa, wb, wc = a.model.state_dict(), b.model.state_dict(), c.model.state_dict()
    assert all(torch.equal(wa[k], wb[k]) for k in wa)
    assert any(not torch.equal(wa[k], wc[k]) for k in wa)


class Killed(Exception):
    pass


def test_a_resumed_training_draws_the_same_noise(tmp_path, monkeypatch):
    logs = generate_car_versions(2, seed=3, versions=[0])
    kw = {"seed": 0, "hidden": (8,), "history": 3, "input_noise": 1.0, "eval_every": 2, "epochs": 4}
    whole = train_bc(logs, **kw)
    real_save = TrainingState.save

    def save_then_die(self, epoch, *a):  # the process dies right after the state of epoch 2 is written
        real_save(self, epoch, *a)
        raise Killed

    monkeypatch.setattr(TrainingState, "save", save_then_die)
    with pytest.raises(Killed):
        train_bc(logs, state_path=tmp_path / "m.state", **kw)
    monkeypatch.setattr(TrainingState, "save", real_save)
    resumed = train_bc(logs, state_path=tmp_path / "m.state", resume=True, **kw)
    wa, wb = whole.model.state_dict(), resumed.model.state_dict()
    assert all(torch.equal(wa[k], wb[k]) for k in wa)
