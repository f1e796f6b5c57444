"""BC's step-size schedule: a cosine annealing that trains to its epoch cap and resumes exactly, set by the
system description's ``[training] lr_schedule`` (the car's) or ``envi train --lr-schedule``."""

from __future__ import annotations

import re

import pytest
import torch

from envi_py.cli import main
from envi_py.model import Checkpoint
from envi_py.system import SHIPPED_DIR, TrainingDefaults, load_system
from envi_py.train import train
from envi_py.train.bc import learning_rate
from envi_py.train.common import SelectionSettings
from envi_py.train.state import TrainingState

from .test_train_resume import Killed, _logs, _weights

KW = dict(seed=3, epochs=12, eval_every=3, hidden=(16,), lr=1e-3, history=4)


def test_the_cosine_step_starts_at_lr_and_falls_to_near_zero_at_the_cap():
    steps = [learning_rate(1e-3, "cosine", e, 300) for e in range(1, 301)]
    assert steps[0] == pytest.approx(1e-3) and steps[150] == pytest.approx(5e-4, rel=0.01)
    assert steps[-1] < 1e-6 and all(a > b for a, b in zip(steps, steps[1:]))
    assert {learning_rate(1e-3, "constant", e, 300) for e in (1, 150, 300)} == {1e-3}


def test_a_cosine_training_runs_to_its_cap_whatever_the_patience():
    train_logs, val_logs = _logs(4, 0), _logs(2, 1)
    ckpt = train("bc", train_logs, val_logs, lr_schedule="cosine", selection=SelectionSettings(patience=1), **KW)
    assert ckpt.record.selection["last_epoch"] == KW["epochs"]
    assert ckpt.record.hyper["lr_schedule"] == "cosine" and ckpt.record.hyper["selection"]["patience"] == 0
    with pytest.raises(ValueError, match="lr schedule must be one of constant, cosine"):
        train("bc", train_logs, val_logs, lr_schedule="linear", **KW)


def test_a_killed_cosine_training_resumes_to_the_uninterrupted_checkpoint(tmp_path, monkeypatch):
    """The step size is a function of the epoch, so the resumed epochs take the same steps."""
    train_logs, val_logs = _logs(4, 0), _logs(2, 1)
    whole = train("bc", train_logs, val_logs, lr_schedule="cosine", **KW)
    state, real_save = tmp_path / "m.state", TrainingState.save

    def save_then_die(self, epoch, *a):
        real_save(self, epoch, *a)
        if epoch == 6:
            raise Killed

    monkeypatch.setattr(TrainingState, "save", save_then_die)
    with pytest.raises(Killed):
        train("bc", train_logs, val_logs, lr_schedule="cosine", state_path=state, **KW)
    monkeypatch.setattr(TrainingState, "save", real_save)
    resumed = train("bc", train_logs, val_logs, lr_schedule="cosine", state_path=state, resume=True, **KW)
    for k, v in _weights(whole).items():
        assert torch.equal(v, _weights(resumed)[k]), k


def test_the_car_description_anneals_and_the_command_line_wins(car_dir, tmp_path):
    assert load_system("car").training.lr_schedule == "cosine"
    assert load_system("lane-keeping").training.lr_schedule == "constant"  # measured worse there (README)
    assert TrainingDefaults(lr_schedule="cosine").for_algorithm("bcxgail") == {}  # PPO keeps its own steps
    base = ["train", "--logs", str(car_dir), "--epochs", "2", "--eval-every", "1", "--hidden", "8", "--quiet"]
    for extra, schedule in (([], "cosine"), (["--lr-schedule", "constant"], "constant")):
        out = tmp_path / f"m{len(extra)}.pt"
        assert main([*base, *extra, "-o", str(out)]) == 0, extra
        assert Checkpoint.load(out).record.hyper["lr_schedule"] == schedule, extra


def test_a_bad_schedule_is_refused_naming_the_file_or_the_option(car_dir, tmp_path, capsys):
    text = (SHIPPED_DIR / "car.toml").read_text().replace('lr_schedule = "cosine"', 'lr_schedule = "step"')
    path = tmp_path / "car.toml"
    path.write_text(text)
    with pytest.raises(ValueError, match=re.escape("[training] lr_schedule must be one of constant, cosine")) as err:
        load_system(path)
    assert str(path) in str(err.value)
    argv = ["train", "--logs", str(car_dir), "--algorithm", "gail", "--lr-schedule", "cosine"]
    assert main([*argv, "-o", str(tmp_path / "m.pt")]) == 2
    assert (
        capsys.readouterr().err.strip()
        == "envi train: error: --lr-schedule is behaviour cloning's step size, not gail's"
    )
