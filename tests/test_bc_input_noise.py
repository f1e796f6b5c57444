"""BC's input-noise option: noise on the window's states only, seeded, and off by default."""

from __future__ import annotations

import numpy as np
import torch

from envi_py.model import ModelConfig
from envi_py.train.bc import state_columns, train_bc

from .conftest import make_log


def test_only_the_state_columns_of_each_window_row_are_perturbed():
    cfg = ModelConfig(n_state=1, n_action=1, history=3, extras=("dt",))
    np.testing.assert_array_equal(state_columns(cfg), [1, 0, 0, 1, 0, 0, 1, 0, 0])
    ctx = ModelConfig(n_state=2, n_action=1, history=2, context=True)
    mask = state_columns(ctx)
    assert mask.shape == (ctx.in_features,)
    np.testing.assert_array_equal(mask[:6], [1, 1, 0, 1, 1, 0])
    assert not mask[6:].any()  # the context is not a state of the window


def _weights(ckpt) -> list[torch.Tensor]:
    return [v.clone() for v in ckpt.model.state_dict().values()]


def test_input_noise_changes_training_and_repeats_exactly():
    logs = [make_log(np.linspace(10, 80, 30) + 5 * np.sin(np.arange(30) + k), run=f"r{k}") for k in range(2)]
    kw = {"epochs": 3, "hidden": (8,), "history": 4}
    plain = _weights(train_bc(logs, **kw))
    noisy = _weights(train_bc(logs, input_noise=0.1, **kw))
    again = _weights(train_bc(logs, input_noise=0.1, **kw))
    assert any(not torch.equal(a, b) for a, b in zip(plain, noisy))
    assert all(torch.equal(a, b) for a, b in zip(noisy, again))
