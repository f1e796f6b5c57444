"""The command line on a few real logs: split -> train (BC, random) -> simulate -> verify."""

from __future__ import annotations

import json

import pytest

from envi_py import native
from envi_py.cli import main


def test_tovk_on_real_logs(real_dir, tmp_path, capsys):
    split = tmp_path / "split"
    assert (
        main(
            [
                "split",
                "--logs",
                str(real_dir),
                "--pattern",
                "log_{x}_{run}.csv",
                "--where",
                "x=30",
                "--train",
                "6",
                "--val",
                "2",
                "--test",
                "12",
                "--seed",
                "1",
                "--out",
                str(split),
            ]
        )
        == 0
    )
    test_logs = json.loads((split / "test.json").read_text())["logs"]
    train_logs = json.loads((split / "train.json").read_text())["logs"]
    assert len(test_logs) == 12 and not set(test_logs) & set(train_logs)
    accs = {}
    for alg in ("bc", "random"):
        model = tmp_path / f"{alg}.pt"
        assert (
            main(
                [
                    "train",
                    "--logs",
                    str(split / "train.json"),
                    "--val-logs",
                    str(split / "val.json"),
                    "--algorithm",
                    alg,
                    "--epochs",
                    "60",
                    "--lr",
                    "1e-3",
                    "--quiet",
                    "-o",
                    str(model),
                ]
            )
            == 0
        )
        sim = tmp_path / f"sim_{alg}"
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
        engine = "native" if alg == "bc" and native.available() else "torch"  # auto: native where it can
        assert f"({engine} engine)" in capsys.readouterr().out
        report = tmp_path / f"report_{alg}"
        assert main(["verify", "--real", str(split / "test.json"), "--sim", str(sim), "--out", str(report)]) == 0
        data = json.loads((report / "report.json").read_text())
        group = data["groups"][0]
        assert group["n_real"] == 12 and group["n_sim"] == 24
        # the floor and the simulation it is compared with rest on equal numbers of runs
        assert group["tests"]["per_side"] == 6 and group["tests"]["kld"]["per_side"] == 6
        assert group["tests"]["goals_w1"]["n_real"] == 12 and 0 < group["tests"]["goals_w1"]["p_value"] <= 1
        accs[alg] = group["sim_vs_real"]["acc"]
        assert "## x=30" in (report / "report.md").read_text()
    assert accs["bc"] > accs["random"] + 0.03
    assert accs["bc"] > 0.93


def test_bad_input_exits_2_with_one_line(tmp_path, capsys):
    bad = tmp_path / "bad.csv"
    bad.write_text("time,color\n0,1\n")
    assert main(["train", "--logs", str(bad), "-o", str(tmp_path / "m.pt")]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "bad.csv" in err[0] and "missing column(s) angle" in err[0]
    assert main(["simulate", "--model", str(bad), "--init-logs", str(bad), "--out", str(tmp_path / "sim")]) == 2
    assert "bad.csv" in capsys.readouterr().err  # the model refused, not the folder (tmp_path holds bad.csv)
    with pytest.raises(SystemExit):
        main(["train", "--help"])


def test_a_diagnosed_fix_can_be_trained_and_simulated_from_the_command_line(real_dir, tmp_path, capsys):
    """What a diagnosis proposes (here backlash's play channel) is a training option; the model
    then simulates on the PyTorch engine, and a play channel without a width is refused."""
    logs = [str(p) for p in sorted(real_dir.glob("log_30_*.csv"))[:6]]
    model = tmp_path / "play.pt"
    assert (
        main(
            [
                "train",
                "--logs",
                *logs[:4],
                "--pattern",  # the real logs carry no sidecar: the file name says the version
                "log_{x}_{run}.csv",
                "--epochs",
                "5",
                "--history",
                "4",
                "--extras",
                "play",
                "dt",
                "--play-width",
                "0.3",
                "--quiet",
                "-o",
                str(model),
            ]
        )
        == 0
    )
    from envi_py.model import Checkpoint

    cfg = Checkpoint.load(model).config
    assert cfg.extras == ("play", "dt") and cfg.play_width == 0.3 and cfg.in_features == 4 * 4
    capsys.readouterr()
    simulate = ["simulate", "--model", str(model), "--init-logs", *logs[4:], "--pattern", "log_{x}_{run}.csv"]
    assert main([*simulate, "--out", str(tmp_path / "sim")]) == 0
    assert "(torch engine)" in capsys.readouterr().out
    assert main(["train", "--logs", *logs[:4], "--extras", "play", "-o", str(tmp_path / "bad.pt")]) == 2
    assert "play_width" in capsys.readouterr().err
