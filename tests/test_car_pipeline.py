"""The generality test: the two-sensor, two-loop car goes init -> split -> train -> simulate -> verify
through the command line, on twin logs with extra (logged) columns, with no workaround."""

from __future__ import annotations

import json

import numpy as np
import pytest

from envi_py.cli import main
from envi_py.logs import load_logs
from envi_py.model import Checkpoint
from envi_py.system import SystemDescription
from envi_py.twin.car import generate_car_versions, write_car_logs


@pytest.fixture(scope="module")
def car_dir(tmp_path_factory):
    d = tmp_path_factory.mktemp("car")
    write_car_logs(generate_car_versions(10, 60, seed=5), d)
    return d


def test_car_end_to_end_through_the_cli(car_dir, tmp_path, capsys):
    system = tmp_path / "car.toml"
    assert main(["init", "--logs", str(car_dir), "-o", str(system)]) == 0
    drafted = SystemDescription.load(system)
    assert [c.name for c in drafted.schema.states] == ["color", "distance"]
    assert [c.name for c in drafted.schema.logged] == ["steer_p", "steer_i", "steer_d", "speed_p", "speed_i", "speed_d"]
    split = tmp_path / "split"
    assert (
        main(
            [
                "split",
                "--logs",
                str(car_dir),
                "--system",
                "car",
                "--train",
                "5",
                "--val",
                "2",
                "--test",
                "3",
                "--mode",
                "blocks",
                "--out",
                str(split),
            ]
        )
        == 0
    )
    model = tmp_path / "car.pt"
    assert (
        main(
            [
                "train",
                "--logs",
                str(split / "train.json"),
                "--val-logs",
                str(split / "val.json"),
                "--epochs",
                "4",
                "--eval-every",
                "2",
                "--hidden",
                "32,32",
                "--quiet",
                "-o",
                str(model),
            ]
        )
        == 0
    )
    ckpt = Checkpoint.load(model)
    assert ckpt.config.n_state == 2 and ckpt.config.n_action == 2 and ckpt.system.name == "car"
    assert not (tmp_path / "car.pt.state").exists()  # a finished training leaves no state to resume
    sim = tmp_path / "sim"
    assert (
        main(
            [
                "simulate",
                "--model",
                str(model),
                "--init-logs",
                str(split / "test.json"),
                "--runs",
                "2",
                "--out",
                str(sim),
            ]
        )
        == 0
    )
    sims = load_logs(sim)
    assert len(sims) == 5 * 3 * 2 and sims[0].actions.shape[1] == 2
    for lg in sims:  # the combine controller drove both actions, each within its loop's limits
        assert np.all(np.abs(lg.actions[10:, 0]) <= 60) and np.all(
            (lg.actions[10:, 1] >= 0) & (lg.actions[10:, 1] <= 720)
        )
    report = tmp_path / "report"
    assert main(["verify", "--real", str(split / "test.json"), "--sim", str(sim), "--out", str(report)]) == 0
    groups = json.loads((report / "report.json").read_text())["groups"]
    assert len(groups) == 5 and groups[0]["goals"] == ["lane deviation", "closest approach", "gap error"]
    assert groups[0]["version"].startswith("kp_steer=") and all(np.isfinite(g["sim_vs_real"]["acc"]) for g in groups)
    out = capsys.readouterr().out
    assert "kp_steer=0.8,kp_speed=18" in out


def test_a_one_loop_controller_for_the_two_action_car_is_refused(car_dir, tmp_path, capsys):
    logs = load_logs(car_dir)
    from envi_py.train import train

    ckpt = train("bc", logs[:4], [], epochs=1, hidden=(8,), history=4)
    path = ckpt.save(tmp_path / "m.pt")
    assert (
        main(
            [
                "simulate",
                "--model",
                str(path),
                "--init-logs",
                str(logs[0].path),
                "--controller",
                "pid",
                "--param",
                "kp=1",
                "--engine",
                "torch",
                "--out",
                str(tmp_path / "s"),
            ]
        )
        == 2
    )
    err = capsys.readouterr().err.strip()
    assert "drives 1 action channel(s), the model has 2" in err and "\n" not in err
