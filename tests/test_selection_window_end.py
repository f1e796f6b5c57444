"""The last evaluations' smoothing windows never complete: they are kept only when nothing else can be."""

from __future__ import annotations

from types import SimpleNamespace

import torch

from envi_py.goals.selection import SelectionScore
from envi_py.train import common
from envi_py.train.common import SelectionSettings, Selector


def _select(monkeypatch, distances: list[float], settings: SelectionSettings, diverged: set[int] = frozenset()):
    """Scripted validation distances at epochs 10, 20, ...; the model's weight records the epoch."""
    scores = iter(
        SelectionScore(float("inf") if i in diverged else d, d, {}, 0.0, 0.0, i in diverged, 3, 15)
        for i, d in enumerate(distances)
    )
    monkeypatch.setattr(common, "closed_loop_score", lambda ckpt, logs, runs=1: next(scores))
    model = torch.nn.Linear(1, 1, bias=False)
    ckpt = SimpleNamespace(model=model, record=SimpleNamespace(selection={}))
    sel = Selector(["val"], settings)
    for i in range(len(distances)):
        with torch.no_grad():
            model.weight.fill_(10 * (i + 1))
        sel.consider(ckpt, 10 * (i + 1))
    sel.finish(ckpt, 10 * len(distances))
    return sel, ckpt


def test_a_lucky_last_evaluation_does_not_win_on_half_a_window(monkeypatch):
    # centred windows: epoch 30 scores 0.40; the last one, averaged with its one neighbour, 0.375
    sel, ckpt = _select(monkeypatch, [0.9, 0.4, 0.4, 0.4, 0.5, 0.5, 0.5, 0.25], SelectionSettings(smooth=3, patience=0))
    assert sel.best_epoch == 30
    assert ckpt.model.weight.item() == 30
    assert abs(ckpt.record.selection["best_score"] - 0.4) < 1e-12


def test_the_last_evaluation_is_kept_when_every_other_diverged(monkeypatch):
    sel, ckpt = _select(monkeypatch, [0.2, 0.2, 0.9], SelectionSettings(smooth=3, patience=0), diverged={0, 1})
    assert sel.best_epoch == 30
    assert ckpt.model.weight.item() == 30


def test_without_smoothing_the_last_evaluation_competes_as_any_other(monkeypatch):
    sel, _ = _select(monkeypatch, [0.9, 0.5, 0.1], SelectionSettings(smooth=1, patience=0))
    assert sel.best_epoch == 30
