"""Effect layers around a learnt model: their semantics, their rollout, their fit on logs that show a
gap and the shrink they give on confirmation logs."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from envi_py.diagnose.layers import (
    confirm,
    fit_and_confirm,
    fit_layer,
    layers_path,
    load_layers,
    own_level,
    save_layers,
    simulate_layered,
)
from envi_py.diagnose.gap import cut_logs
from envi_py.diagnose.validate import LANE, PID, validation_training, world_logs
from envi_py.effect_layers import Layer, layered_commands
from envi_py.simulate import initial_windows, rollout
from envi_py.train import train


@pytest.fixture(scope="module")
def clean_logs():
    """Logs of the clean steered twin: 12 to train on, 3 to validate on."""
    return world_logs("steered", LANE, 15, 100, {}, 0)


@pytest.fixture(scope="module")
def clean_model(clean_logs):
    """A small BC model of the clean steered twin, trained as the validation trains (its tiny size)."""
    torch.set_num_threads(1)
    return train(
        "bc",
        clean_logs[:12],
        clean_logs[12:],
        seed=0,
        epochs=80,
        lr=1e-3,
        history=4,
        head="deterministic",
        **validation_training(),
    )


def test_action_layers_do_what_they_say():
    a = np.array([0.0, 10, 10, 10, -10, -10, 10])[:, None]
    assert layered_commands((Layer("delay", 2),), a)[:, 0].tolist() == [0, 0, 0, 10, 10, 10, -10]
    play = layered_commands((Layer("play", 8),), a)[:, 0]
    assert play.tolist() == [0, 6, 6, 6, -6, -6, 6]  # the output lags the command by half the play
    lag = layered_commands((Layer("lag", 1),), a)[:, 0]
    assert lag[1] == pytest.approx(10 * (1 - np.exp(-1))) and np.all(np.diff(lag[1:4]) > 0)
    assert layered_commands((Layer("gain_drift", 0.5),), a)[-1, 0] == pytest.approx(10 * (1 + 0.5 * 6 / 7))
    assert np.array_equal(layered_commands((Layer("delay", 0),), a), a)


def test_bad_layers_are_refused():
    with pytest.raises(ValueError, match="unknown effect layer 'wind'"):
        Layer("wind", 1)
    with pytest.raises(ValueError, match="must be finite and not negative"):
        Layer("delay", -1)
    with pytest.raises(ValueError, match="must be finite"):
        Layer("noise", float("nan"))


def test_the_identity_layer_rolls_out_as_the_model_alone(clean_model):
    logs = cut_logs(world_logs("steered", LANE, 3, 40, {}, 5), 34)
    init = initial_windows(logs, clean_model.config.history)
    plain = rollout(clean_model, LANE, init, 30, runs=2, seed=3)
    for kind in ("delay", "noise", "play"):
        assert np.array_equal(rollout(clean_model.with_layers([Layer(kind)]), LANE, init, 30, runs=2, seed=3), plain)
    delayed = rollout(clean_model.with_layers([Layer("delay", 1)]), LANE, init, 30, runs=2, seed=3)
    assert not np.array_equal(delayed, plain)
    sims = simulate_layered(clean_model, LANE, logs, Layer("delay", 1), runs=2, seed=3)
    assert len(sims) == 6 and np.array_equal(sims[1].states, delayed[1, :, :1])
    assert np.array_equal(sims[1].actions, delayed[1, :, 1:]) and np.array_equal(sims[1].time, logs[0].time)


def test_a_fitted_noise_layer_recovers_the_injected_noise_and_shrinks_the_gap_on_confirmation_logs(clean_model):
    """Sensor noise of sd 3 in the logs that show the gap; a model of the clean robot. The noise
    layer's fitted sd covers 3, and on other logs (neither fitted on nor chosen on) the gap shrinks
    with a bootstrap interval above zero."""
    fit = fit_layer(clean_model, "noise", world_logs("steered", LANE, 12, 100, {"noise": 3.0}, 1), boot=100)
    low, high = fit.interval
    assert low <= 3.0 <= high and high - low < 3.0, fit.text()
    c = confirm(clean_model, fit.layer, world_logs("steered", LANE, 12, 100, {"noise": 3.0}, 2), boot=200)
    assert c["shrink"] > 0.3 and c["shrink_ci"][0] > 0, c
    assert c["after"] < c["before"]


def test_a_layer_fitted_on_a_world_without_the_effect_changes_nothing(clean_model):
    fit = fit_layer(clean_model, "delay", world_logs("steered", LANE, 12, 100, {}, 1), boot=100)
    assert fit.layer.identity and fit.interval == [0.0, 0.0], fit.text()
    c = confirm(clean_model, fit.layer, world_logs("steered", LANE, 12, 100, {}, 2), boot=100)
    assert c["shrink"] == 0 and c["shrink_ci"] == [0.0, 0.0] and c["within_1.5_floor"]


def test_a_delay_fitted_where_the_model_never_went_is_said_to_be_a_guess(clean_model, clean_logs):
    """A 2-tick delay drives the loop into states the clean model never saw: the one-step fit still
    picks some delay, but its windows lie outside the training windows, so it is reported as not
    identifiable and its interval is the whole grid. The clean world's own logs are within them."""
    train_logs = clean_logs[:12]
    affected = world_logs("steered", LANE, 12, 100, {"delay": 2}, 1)
    delayed = fit_layer(clean_model, "delay", affected, 2, 0, 50, train_logs)
    assert delayed.support is not None and delayed.support["outside_share"] > 0.9, delayed.support
    assert not delayed.identifiable and delayed.interval == [0.0, 10.0]
    assert "not identifiable with this model (any value in [0, 10])" in delayed.text()
    assert delayed.to_json()["short"] == f"{delayed.layer.text()}, not identifiable"
    clean = fit_layer(clean_model, "delay", world_logs("steered", LANE, 12, 100, {}, 1), 2, 0, 50, train_logs)
    assert clean.identifiable and clean.support["outside_share"] <= 0.5 and clean.interval == [0.0, 0.0]
    # without training logs the support is not checked, and a fit by simulation has none to check
    assert fit_layer(clean_model, "delay", affected, boot=20).support is None
    noise = fit_layer(clean_model, "noise", world_logs("steered", LANE, 6, 100, {}, 1), 2, 0, 20, train_logs)
    assert noise.support is None and noise.identifiable


def test_a_layered_gap_is_set_against_the_model_alone_on_held_out_logs_of_its_own_world(clean_model, clean_logs):
    """The model's own level is the gap :func:`confirm` measures with nothing added (one definition),
    on held-out clean logs. This small model is itself beyond 1.5x the floor there, which no layer
    adds; a noise layer comes within 1.5x of that level, a delay fitted where the model never went
    does not; fewer held-out logs than confirmation logs give no level (a floor depends on the runs
    per side), and held-out runs that do not vary (a floor of 0) no ratio."""
    held = world_logs("steered", LANE, 14, 100, {}, 3)
    like = world_logs("steered", LANE, 12, 100, {"noise": 3.0}, 2)  # as many as the confirmation logs
    own = own_level(clean_model, held, like)
    c = confirm(clean_model, Layer("delay"), held[:12], boot=20)
    assert own is not None and (own["gap"], own["floor"], own["logs"]) == (c["before"], c["floor"], 12)
    assert own["ratio"] == pytest.approx(c["before"] / c["floor"]) and own["ratio"] > 1.5, own
    assert own_level(clean_model, held[:11], like) is None  # fewer runs a side than the confirmation's
    pid = world_logs("steered", PID, 6, 100, {}, 3)
    settled = own_level(clean_model, pid, pid)  # PID runs that do not vary
    assert settled is not None and settled["floor"] == 0 and settled["ratio"] is None, settled

    def layered(candidate: str, effects: dict, own_logs: list) -> dict:
        shown, other = (world_logs("steered", LANE, 12, 100, effects, s) for s in (1, 2))
        r = fit_and_confirm(
            clean_model, candidate, shown, other, boot=20, train_logs=clean_logs[:12], own_logs=own_logs
        )
        assert r is not None
        return r

    noisy = layered("noise", {"noise": 3.0}, held)
    assert (
        noisy["own"]["within_1.5_own"] and noisy["confirm"]["after"] <= 1.5 * own["ratio"] * noisy["confirm"]["floor"]
    )
    delayed = layered("memory_delay", {"delay": 2}, held)
    assert not delayed["fit"]["identifiable"] and not delayed["own"]["within_1.5_own"]
    assert delayed["confirm"]["after"] > 1.5 * own["ratio"] * delayed["confirm"]["floor"], delayed["confirm"]
    assert layered("noise", {"noise": 3.0}, held[:3])["own"] is None


def test_fitted_layers_are_saved_beside_the_model_and_read_back(tmp_path):
    from envi_py.diagnose.layers import Fit

    model = tmp_path / "m.pt"
    fits = [Fit(Layer("delay", 2), [2.0, 2.0], []), Fit(Layer("saturation", 0, 29.0, 51.0), [50.0, 51.0], [])]
    path = save_layers(model, fits)
    assert path == layers_path(model) == tmp_path / "m.pt.layers.json"
    assert load_layers(model) == (Layer("delay", 2), Layer("saturation", 0, 29.0, 51.0))
    assert fits[0].text() == "delay 2 ticks [2, 2]"
    path.write_text("{not json")
    with pytest.raises(ValueError, match="m.pt.layers.json: a layers file is not valid JSON"):
        load_layers(model)
    assert load_layers(tmp_path / "other.pt") == ()


def test_a_fix_the_model_already_has_is_not_a_change(clean_model):
    from envi_py.diagnose.effects import Finding
    from envi_py.diagnose.shrink import changes_model

    def finding(fix):
        return Finding("noise", 1.0, 0.0, 0.5, "", fix)

    assert not changes_model(clean_model, finding({"head": "deterministic"}))
    assert changes_model(clean_model, finding({"head": "gaussian"}))
    assert changes_model(clean_model, finding({"history": 8}))
    assert not changes_model(clean_model, finding({"history": clean_model.config.history}))


def test_a_layer_interval_is_made_of_grid_values_and_an_unlimited_saturation_is_one():
    """Some resamples choose no saturation limit (inf): the interval says so, without NaN or a warning,
    and never names a value between two grid points that no resample chose."""
    import warnings

    from envi_py.diagnose.layers import grid_interval

    with warnings.catch_warnings():
        warnings.simplefilter("error")
        assert grid_interval([51.0] * 190 + [np.inf] * 10) == [51.0, np.inf]
        # the 97.5 % point falls between the last 2 and the first 4: linear interpolation said 2.05
        assert grid_interval([2.0] * 195 + [4.0] * 5) == [2.0, 4.0]
        assert grid_interval([4.0] * 3 + [5.0] * 197) == [5.0, 5.0]  # 3 of 200 lie below the 2.5 % point
