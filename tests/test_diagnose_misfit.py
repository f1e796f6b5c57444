"""The misfit sentence ("as when these logs come from a world the training logs do not show") rests on
a test: the logs must fit worse than the model's own held-out logs of its training world. Logs drawn
from the training world do not; logs of a world with an actuator lag do."""

from __future__ import annotations

import pytest

from envi_py.controllers import ControllerSpec
from envi_py.diagnose.residuals import one_step_residuals
from envi_py.diagnose.effects import CANDIDATES, run_candidates
from envi_py.diagnose.run import OTHER_WORLD_RMS, Diagnosis, held_out_fit, own_shares
from envi_py.train import train
from envi_py.twin import TwinProfile, generate

LANE = ControllerSpec("lane-keeping", {"x": 30})
WORLD = "as when these logs come from a world the training logs do not show"


@pytest.fixture(scope="module")
def model():
    fit = generate(LANE, 18, 100, {}, seed=11, profile=TwinProfile())
    return train("bc", fit[:12], [], seed=0, epochs=20, lr=1e-3, history=4), fit[12:]


@pytest.mark.parametrize("seed", [21, 22])
def test_logs_of_the_training_world_do_not_fit_worse_than_its_held_out_logs(model, seed):
    ckpt, held_out = model
    logs = generate(LANE, 12, 100, {}, seed=seed, profile=TwinProfile())
    h = held_out_fit(ckpt, one_step_residuals(ckpt, logs), len(logs), held_out)
    assert h is not None and not h["worse"] and h["n_held_out"] == 6 and h["n_logs"] == 12


def test_logs_of_a_world_with_an_actuator_lag_fit_worse(model):
    ckpt, held_out = model
    logs = generate(LANE, 12, 100, {"lag": 200.0}, seed=23, profile=TwinProfile())
    h = held_out_fit(ckpt, one_step_residuals(ckpt, logs), len(logs), held_out)
    assert h["worse"] and h["p"] <= 0.05 and h["rms_ratio"] > 1.0


def test_the_sentence_follows_the_test():
    def said(held_out):
        d = Diagnosis([], [], [], [], [], {"outside_share": 0.0}, None, misfit=0.6, held_out=held_out)
        return d._misfit_text()

    base = {"rms_ratio": 1.0, "p": 0.5, "n_logs": 12, "n_held_out": 6}
    assert WORLD not in said({**base, "worse": False}) and "as imprecise on logs of its own" in said(
        {**base, "worse": False}
    )
    assert WORLD in said({**base, "rms_ratio": 3.0, "p": 0.001, "worse": True})
    # significantly but only slightly worse: logs of the training world do that now and then (the
    # held-out logs chose the epoch), so "another world" is one predicate with the held-out shares
    slightly = said({**base, "rms_ratio": 1.2, "p": 0.01, "worse": True})
    assert WORLD not in slightly and "about as imprecise on logs of its own" in slightly
    assert WORLD not in said(None) and "no held-out logs" in said(None)


def test_own_shares_are_measured_only_for_logs_of_another_world(model):
    """A candidate's share on the held-out logs is counted against it only when the diagnosed logs
    fit significantly and clearly worse (another world); on logs of the training world whatever the
    model misses is the finding."""
    ckpt, held_out = model
    lagged = generate(LANE, 12, 100, {"lag": 200.0}, seed=23, profile=TwinProfile())
    h = held_out_fit(ckpt, one_step_residuals(ckpt, lagged), len(lagged), held_out)
    own = own_shares(ckpt, h, held_out)
    on_held_out = run_candidates(one_step_residuals(ckpt, held_out), ckpt)
    assert h["worse"] and own == {f.effect: f.share for f in on_held_out}
    assert {c.name for c in CANDIDATES} <= set(own) and all(0 <= v <= 1 for v in own.values())
    assert own_shares(ckpt, {**h, "worse": False}, held_out) == {} and own_shares(ckpt, None, held_out) == {}
    assert h["rms_ratio"] >= OTHER_WORLD_RMS and own_shares(ckpt, {**h, "rms_ratio": 1.3}, held_out) == {}
