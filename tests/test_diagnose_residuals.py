"""One-step residuals compare the real reading with the model's expected reading: clamped to the
model's range, but not rounded to the sensor's resolution. A rounded prediction adds its own rounding
error to every residual, an error of no world that drowns small effects (a delay of two ticks)."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from envi_py.controllers import ControllerSpec
from envi_py.diagnose.residuals import one_step_residuals
from envi_py.train import train
from envi_py.twin import TwinProfile, generate

LANE = ControllerSpec("lane-keeping", {"x": 30})


@pytest.fixture(scope="module")
def rounding_model():
    fit = generate(LANE, 12, 100, {}, seed=31, profile=TwinProfile())
    ckpt = train("bc", fit[:10], fit[10:], seed=0, epochs=10, lr=1e-3, history=4, members=1)  # one model steps
    assert ckpt.config.round_to == (1.0,) and ckpt.config.clamp  # what envi train does by default
    return ckpt, generate(LANE, 6, 100, {"delay": 2}, seed=32, profile=TwinProfile())


def test_residuals_of_a_rounding_model_are_those_of_its_unrounded_mean(rounding_model):
    ckpt, logs = rounding_model
    res = one_step_residuals(ckpt, logs).view(0, 0)
    off_lattice = np.abs(res.predicted - np.round(res.predicted)) > 1e-6
    assert off_lattice.mean() > 0.9  # the expected reading, between the sensor's steps
    low, high = ckpt.limits()
    assert res.predicted.min() >= low[0] and res.predicted.max() <= high[0]
    np.testing.assert_allclose(res.r, res.real_next - res.predicted)
    ckpt.config.round_to = None
    try:
        unrounded = one_step_residuals(ckpt, logs).view(0, 0)
    finally:
        ckpt.config.round_to = (1.0,)
    np.testing.assert_array_equal(res.r, unrounded.r)


def test_a_simulated_step_is_still_rounded_to_the_resolution(rounding_model):
    ckpt, logs = rounding_model
    x = torch.from_numpy(np.ascontiguousarray(ckpt.dataset(logs[:1]).X[0]))
    s = ckpt.next_state(x)
    np.testing.assert_array_equal(s, np.round(s))
