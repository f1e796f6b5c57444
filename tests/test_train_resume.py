"""A training killed at any validation and resumed ends with the very checkpoint of an uninterrupted run."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from envi_py.train import train
from envi_py.train.state import TrainingState

from .conftest import make_log


def _logs(n: int, seed: int) -> list:
    rng = np.random.default_rng(seed)
    return [
        make_log(
            np.clip(40 + 25 * np.sin(np.arange(40) / 3 + rng.uniform(0, 6)) + rng.normal(0, 2, 40), 0, 100), run=str(i)
        )
        for i in range(n)
    ]


KW = dict(seed=3, epochs=12, eval_every=3, hidden=(16,), lr=1e-3, history=4)


def _weights(ckpt) -> dict[str, torch.Tensor]:
    return {k: v.clone() for k, v in ckpt.model.state_dict().items()}


class Killed(Exception):
    pass


def test_resume_after_a_kill_gives_the_uninterrupted_checkpoint(tmp_path, monkeypatch):
    train_logs, val_logs = _logs(4, 0), _logs(2, 1)
    whole = train("bc", train_logs, val_logs, **KW)
    state = tmp_path / "m.state"
    saves = []
    real_save = TrainingState.save

    def save_then_die(self, epoch, *a):  # the process dies right after the second state is written
        real_save(self, epoch, *a)
        saves.append(epoch)
        if len(saves) == 2:
            raise Killed

    monkeypatch.setattr(TrainingState, "save", save_then_die)
    with pytest.raises(Killed):
        train("bc", train_logs, val_logs, state_path=state, **KW)
    monkeypatch.setattr(TrainingState, "save", real_save)
    resumed = train("bc", train_logs, val_logs, state_path=state, resume=True, **KW)
    assert saves == [3, 6]
    for k, v in _weights(whole).items():
        assert torch.equal(v, _weights(resumed)[k]), k
    assert resumed.record.selection == whole.record.selection


def test_a_state_of_another_training_is_refused(tmp_path):
    train_logs, val_logs = _logs(4, 0), _logs(2, 1)
    state = tmp_path / "m.state"
    train("bc", train_logs, val_logs, state_path=state, **{**KW, "epochs": 3})
    with pytest.raises(ValueError, match="belongs to another training"):
        train("bc", train_logs, val_logs, state_path=state, resume=True, **{**KW, "seed": 4})
    with pytest.raises(ValueError, match="no training state"):
        train("bc", train_logs, val_logs, state_path=tmp_path / "none.state", resume=True, **KW)
