"""A training killed at any validation and resumed ends with the very checkpoint of an uninterrupted run."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest
import torch

from envi_py.cli import main
from envi_py.logs import write_log
from envi_py.model import Checkpoint
from envi_py.train import train
from envi_py.train.state import TrainingState

from .conftest import make_log


def _logs(n: int, seed: int, rows: int = 40) -> list:
    rng = np.random.default_rng(seed)
    return [
        make_log(
            np.clip(40 + 25 * np.sin(np.arange(rows) / 3 + rng.uniform(0, 6)) + rng.normal(0, 2, rows), 0, 100),
            run=str(i),
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
    assert resumed.record.selection == whole.record.selection  # the training losses too, across the kill
    losses = whole.record.selection["train_loss_curve"]
    assert [e for e, _ in losses] == [e for e, _ in whole.record.selection["curve"]]
    assert all(isinstance(v, float) and math.isfinite(v) for _, v in losses)


def test_a_state_of_another_training_is_refused(tmp_path):
    train_logs, val_logs = _logs(4, 0), _logs(2, 1)
    state = tmp_path / "m.state"
    train("bc", train_logs, val_logs, state_path=state, **{**KW, "epochs": 3})
    with pytest.raises(ValueError, match=r"belongs to another training \(it differs in seed\)"):
        train("bc", train_logs, val_logs, state_path=state, resume=True, **{**KW, "epochs": 3, "seed": 4})
    with pytest.raises(ValueError, match=r"\(it differs in epochs\)"):  # the setting is named
        train("bc", train_logs, val_logs, state_path=state, resume=True, **{**KW, "epochs": 5})
    with pytest.raises(ValueError, match=r"\(it differs in hidden\)"):  # named once, though hyper and config hold it
        train("bc", train_logs, val_logs, state_path=state, resume=True, **{**KW, "epochs": 3, "hidden": (6,)})
    with pytest.raises(ValueError, match=r"\(it differs in (limits, )?training data\)"):  # limits follow the data
        train("bc", _logs(4, 7), val_logs, state_path=state, resume=True, **{**KW, "epochs": 3})
    with pytest.raises(ValueError, match="no training state"):
        train("bc", train_logs, val_logs, state_path=tmp_path / "none.state", resume=True, **KW)


#: GAIL at test size: tiny policy, critic and discriminator, a few PPO steps per epoch.
GAIL_KW = dict(
    seed=5,
    epochs=7,
    eval_every=2,
    hidden=(8,),
    history=4,
    horizon=8,
    stride=8,
    policy_iters=3,
    disc_iters=3,
    minibatch=32,
    disc_hidden=(8,),
    value_hidden=(8,),
    lr=1e-3,
)


def _kill_at_second_save(monkeypatch) -> list[int]:
    saves: list[int] = []
    real_save = TrainingState.save

    def save_then_die(self, epoch, *a, **k):
        real_save(self, epoch, *a, **k)
        saves.append(epoch)
        if len(saves) == 2:
            monkeypatch.setattr(TrainingState, "save", real_save)
            raise Killed

    monkeypatch.setattr(TrainingState, "save", save_then_die)
    return saves


@pytest.mark.parametrize("algorithm", ["gail", "bcxgail"])
def test_gail_resumed_after_a_kill_gives_the_uninterrupted_checkpoint(tmp_path, monkeypatch, algorithm):
    """Discriminator, critic, their optimisers, the rollout and global torch generators, numpy's
    generator, the reward scale and the curves all continue where they stopped: same weights,
    same selection, same curves.csv."""
    torch.set_num_threads(1)
    train_logs, val_logs = _logs(3, 0), _logs(2, 1)
    whole = train(algorithm, train_logs, val_logs, curves_dir=tmp_path / "whole", **GAIL_KW)
    state = tmp_path / "m.state"
    saves = _kill_at_second_save(monkeypatch)
    with pytest.raises(Killed):
        train(algorithm, train_logs, val_logs, state_path=state, **GAIL_KW)
    assert saves == [2, 4]
    resumed = train(
        algorithm, train_logs, val_logs, state_path=state, resume=True, curves_dir=tmp_path / "resumed", **GAIL_KW
    )
    for k, v in _weights(whole).items():
        assert torch.equal(v, _weights(resumed)[k]), k
    assert resumed.record.selection == whole.record.selection
    assert len(whole.record.selection["curve"]) == 4  # epochs 2, 4, 6 and the last, 7
    assert (tmp_path / "resumed" / "curves.csv").read_text() == (tmp_path / "whole" / "curves.csv").read_text()


def test_a_state_of_another_algorithm_is_refused_in_one_line(tmp_path):
    train_logs, val_logs = _logs(3, 0), _logs(2, 1)
    state = tmp_path / "m.state"
    train("bc", train_logs, val_logs, state_path=state, **{**KW, "epochs": 3})
    with pytest.raises(ValueError) as err:
        train("gail", train_logs, val_logs, state_path=state, resume=True, **GAIL_KW)
    assert str(err.value) == (
        f"{state}: the state is from a bc training, not gail; remove it or train without --resume"
    )
    train("gail", train_logs, val_logs, state_path=state, **{**GAIL_KW, "epochs": 2})
    with pytest.raises(ValueError, match="from a gail training, not bcxgail"):
        train("bcxgail", train_logs, val_logs, state_path=state, resume=True, **GAIL_KW)
    with pytest.raises(ValueError, match="belongs to another training"):
        train("gail", train_logs, val_logs, state_path=state, resume=True, **{**GAIL_KW, "seed": 6})


def _write_logs(folder: Path, logs: list) -> Path:
    folder.mkdir(parents=True)
    for i, lg in enumerate(logs):
        write_log(lg, folder / f"log_30_{i}.csv")
    return folder


def test_envi_train_resume_continues_a_killed_gail_training(tmp_path, monkeypatch, capsys):
    """``envi train --algorithm gail --resume`` ends with the uninterrupted run's checkpoint, and a
    state left by a bc training is refused with one line and exit code 2."""
    torch.set_num_threads(1)
    train_dir = _write_logs(tmp_path / "train", _logs(3, 0, rows=50))  # the CLI's horizon is 40 steps
    val_dir = _write_logs(tmp_path / "val", _logs(2, 1, rows=50))
    args = ["train", "--logs", str(train_dir), "--val-logs", *sorted(map(str, val_dir.glob("*.csv")))]
    args += ["--algorithm", "gail", "--epochs", "5", "--eval-every", "2", "--history", "4", "--hidden", "8"]
    args += ["--lr", "1e-3", "--quiet"]
    assert main([*args, "-o", str(tmp_path / "whole.pt")]) == 0
    saves = _kill_at_second_save(monkeypatch)
    with pytest.raises(Killed):
        main([*args, "-o", str(tmp_path / "m.pt")])
    assert saves == [2, 4] and (tmp_path / "m.pt.state").exists()
    assert main([*args, "--resume", "-o", str(tmp_path / "m.pt")]) == 0
    assert not (tmp_path / "m.pt.state").exists()  # finished: nothing left to resume
    whole, resumed = Checkpoint.load(tmp_path / "whole.pt"), Checkpoint.load(tmp_path / "m.pt")
    for k, v in _weights(whole).items():
        assert torch.equal(v, _weights(resumed)[k]), k
    assert resumed.record.selection == whole.record.selection

    bc_args = [*(a if a != "gail" else "bc" for a in args), "--jobs", "1"]  # in this process: the kill is patched here
    _kill_at_second_save(monkeypatch)
    with pytest.raises(Killed):
        main([*bc_args, "-o", str(tmp_path / "b.pt")])
    capsys.readouterr()
    assert main([*args, "--resume", "-o", str(tmp_path / "b.pt")]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert err == [
        f"envi train: error: {tmp_path / 'b.pt.state'}: the state is from a bc training, not gail; "
        "remove it or train without --resume"
    ]
