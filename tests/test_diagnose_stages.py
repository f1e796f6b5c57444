"""Stage 1 stays silent where the model class is right: a deterministic model of a world without
run-to-run randomness, and any Gaussian model, are diagnosed as they are."""

from __future__ import annotations

from envi_py.controllers import ControllerSpec
from envi_py.diagnose.residuals import one_step_residuals
from envi_py.diagnose.run import _gaps
from envi_py.diagnose.stages import spread_check
from envi_py.train import train
from envi_py.twin import TwinProfile, generate

LANE = ControllerSpec("lane-keeping", {"x": 30})


def test_a_deterministic_model_of_a_world_without_randomness_is_not_refitted():
    fit = generate(LANE, 12, 100, {}, seed=5, profile=TwinProfile())
    logs = generate(LANE, 12, 100, {}, seed=6, profile=TwinProfile())
    for head in ("deterministic", "gaussian"):
        ckpt = train("bc", fit, [], seed=0, epochs=20, lr=1e-3, history=4, head=head)
        _, gaps = _gaps(ckpt, logs, 2, 0)
        check = spread_check(ckpt, gaps, one_step_residuals(ckpt, logs))
        assert check["head"] == head and not check["too_certain"], check
        assert check["tested"] == 8 and len(check["scatter"]) == 1
