"""A trained model rounds to the declared resolution and clamps to the observed range unless told otherwise."""

from __future__ import annotations

import numpy as np

from envi_py.train.common import model_config, new_checkpoint

from .conftest import make_log


def _logs():
    return [make_log(np.linspace(12, 71, 30), run="a"), make_log(np.linspace(70, 15, 30), run="b")]


def test_simulated_states_are_rounded_and_clamped_to_what_training_saw():
    logs = _logs()
    cfg = model_config(logs, history=4, hidden=(8,))
    assert cfg.round_to == (1.0,)  # the lane-keeping colour sensor declares resolution 1
    assert cfg.limits == ((12.0, 71.0),)
    ck = new_checkpoint("bc", logs, [], cfg, 0, {})
    out = ck.post_process(np.array([[3.2], [40.4], [40.6], [99.0]]))
    np.testing.assert_array_equal(out[:, 0], [12.0, 40.0, 41.0, 71.0])


def test_the_defaults_can_be_turned_off():
    cfg = model_config(_logs(), history=4, hidden=(8,), round_to=None, limits=None)
    assert cfg.round_to is None and cfg.limits is None
