"""The epoch a training keeps: smoothed closed-loop score, one-step tie-break, early stopping, resume."""

from __future__ import annotations

import math
from types import SimpleNamespace

import pytest
import torch

from envi_py.goals.selection import SelectionScore
from envi_py.train import common
from envi_py.train.common import SelectionSettings, Selector


def _score(distance: float, diverged: bool = False) -> SelectionScore:
    return SelectionScore(float("inf") if diverged else distance, distance, {}, 0.0, 0.0, diverged, 3, 15)


def _run(monkeypatch, distances, settings, one_step=None, diverged=()):
    """Feed scripted validation distances (one per evaluation, epochs 10, 20, ...) to a Selector; the
    model's single weight is set to the epoch, so the kept weights say which epoch was kept."""
    scores = iter([_score(d, i in diverged) for i, d in enumerate(distances)])
    monkeypatch.setattr(common, "closed_loop_score", lambda ckpt, logs, runs=1: next(scores))
    model = torch.nn.Linear(1, 1, bias=False)
    ckpt = SimpleNamespace(model=model, record=SimpleNamespace(selection={}))
    losses = iter(one_step or [])
    sel = Selector(["val"], settings, (lambda c: next(losses)) if one_step else None)
    last = 0
    for i in range(len(distances)):
        last = 10 * (i + 1)
        with torch.no_grad():
            model.weight.fill_(last)
        sel.consider(ckpt, last)
        if sel.should_stop():
            break
    sel.finish(ckpt, last)
    return sel, ckpt


def test_a_lone_lucky_evaluation_loses_to_a_good_stretch(monkeypatch):
    curve = [0.9, 0.5, 0.5, 0.5, 0.9, 0.1, 0.9, 0.6]
    raw, _ = _run(monkeypatch, curve, SelectionSettings(runs=1, smooth=1, patience=0))
    smooth, ckpt = _run(monkeypatch, curve, SelectionSettings(smooth=3, patience=0))
    assert raw.best_epoch == 60  # the raw minimum is the lone dip
    assert smooth.best_epoch == 30  # the middle of the stretch 0.5, 0.5, 0.5
    assert ckpt.model.weight.item() == 30  # and its weights are the ones restored
    assert ckpt.record.selection["best_epoch"] == 30
    assert ckpt.record.selection["best_score"] == pytest.approx(0.5)


def test_a_tie_goes_to_the_lower_one_step_loss(monkeypatch):
    curve = [0.50, 0.51, 0.90]
    losses = [2.0, 1.0, 0.5]
    plain, _ = _run(monkeypatch, curve, SelectionSettings(smooth=1, patience=0), losses)
    tied, ckpt = _run(monkeypatch, curve, SelectionSettings(smooth=1, tie=0.05, patience=0), losses)
    assert plain.best_epoch == 10
    assert tied.best_epoch == 20  # within 5 % of 0.50, and its one-step loss is lower
    assert ckpt.record.selection["best_one_step"] == 1.0


def test_training_stops_after_patience_evaluations_without_improvement(monkeypatch):
    curve = [0.9, 0.5, 0.4, 0.6, 0.7, 0.8, 0.9, 0.95, 0.99, 0.2]
    sel, ckpt = _run(monkeypatch, curve, SelectionSettings(smooth=1, patience=3))
    assert sel.best_epoch == 30
    assert sel.evaluations[-1].epoch == 60  # three evaluations after the best: stop, never seeing the late 0.2
    assert "than epoch 30's" in ckpt.record.selection["stopped"]
    assert ckpt.record.selection["last_epoch"] == 60


def test_a_diverged_evaluation_is_never_kept(monkeypatch):
    sel, ckpt = _run(monkeypatch, [0.9, 0.1, 0.8], SelectionSettings(smooth=1, patience=0), diverged={1})
    assert sel.best_epoch == 30
    assert ckpt.record.selection["diverged_epochs"] == [20]


def test_a_selector_restored_mid_run_chooses_as_an_uninterrupted_one(monkeypatch):
    curve = [0.9, 0.5, 0.45, 0.6, 0.3, 0.35, 0.8]
    settings = SelectionSettings(smooth=3, patience=0)
    whole, whole_ckpt = _run(monkeypatch, curve, settings)
    scores = iter([_score(d) for d in curve])
    monkeypatch.setattr(common, "closed_loop_score", lambda ckpt, logs, runs=1: next(scores))
    model = torch.nn.Linear(1, 1, bias=False)
    ckpt = SimpleNamespace(model=model, record=SimpleNamespace(selection={}))
    first = Selector(["val"], settings)
    for epoch in (10, 20, 30, 40):
        with torch.no_grad():
            model.weight.fill_(epoch)
        first.consider(ckpt, epoch)
    second = Selector(["val"], settings)
    second.load_state(first.to_state())
    for epoch in (50, 60, 70):
        with torch.no_grad():
            model.weight.fill_(epoch)
        second.consider(ckpt, epoch)
    second.finish(ckpt, 70)
    assert whole.best_epoch == 50  # smoothed 0.417 around 0.3
    assert second.best_epoch == whole.best_epoch
    assert ckpt.model.weight.item() == whole_ckpt.model.weight.item() == 50
    assert ckpt.record.selection == whole_ckpt.record.selection


def test_training_losses_are_recorded_and_an_older_state_still_loads(monkeypatch):
    scores = iter([_score(d) for d in (0.5, 0.4)])
    monkeypatch.setattr(common, "closed_loop_score", lambda ckpt, logs, runs=1: next(scores))
    ckpt = SimpleNamespace(model=torch.nn.Linear(1, 1, bias=False), record=SimpleNamespace(selection={}))
    sel = Selector(["val"], SelectionSettings(smooth=1, patience=0))
    sel.consider(ckpt, 10, 2.5)
    sel.consider(ckpt, 20)  # a caller without a training loss (GAIL)
    state = sel.to_state()
    older = {**state, "evaluations": [row[:4] for row in state["evaluations"]]}  # saved before the field
    restored = Selector(["val"], SelectionSettings(smooth=1, patience=0))
    restored.load_state(older)
    assert math.isnan(restored.evaluations[0].train_loss) and restored.evaluations[0].distance == 0.5
    sel.finish(ckpt, 20)
    assert ckpt.record.selection["train_loss_curve"] == [[10, 2.5], [20, None]]


@pytest.mark.parametrize("bad", [{"runs": 0}, {"smooth": 0}, {"patience": -1}, {"tie": 1.5}])
def test_bad_settings_are_one_clear_error(bad):
    with pytest.raises(ValueError, match="selection settings"):
        SelectionSettings(**bad)
