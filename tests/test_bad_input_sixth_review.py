"""Regressions of the fifth review's list of what was left alone (stop 43), fixed at stop 44. Each
input here once ran with a setting that did nothing, named the wrong thing, or failed after the work
with a message naming no file. Each must now be one line naming the option or file, exit code 2, and
nothing written."""

from __future__ import annotations

import json
import os
from pathlib import Path

import pytest

from envi_py.effect_layers import Layer
from envi_py.logs import load_logs
from envi_py.model import Checkpoint, ModelConfig
from envi_py.notes import one_line
from envi_py.train import train
from tests.test_bad_input_audit import assert_one_line, run_cli


def written(folder: Path) -> list[str]:
    return sorted(p.name for p in folder.iterdir())


@pytest.mark.parametrize(
    ("command", "flag", "name"),
    [
        ("train", "--output", "m\udcff.pt"),  # once saved the model, its state and curves, then failed on the report
        ("simulate", "--out", "sim\udcff"),
        ("verify", "--out", "report\udcff"),
        ("init", "--output", "d\udcff.toml"),  # once wrote its draft, then named it garbled in its note
    ],
)
def test_an_output_name_that_is_not_utf8_is_refused_before_any_work(mini, tmp_path, command, flag, name):
    out = tmp_path / "out"
    out.mkdir()
    target = str(out / name)
    argv = {
        "train": ["train", "--logs", str(mini["logs"]), "--epochs", "2", "--members", "1", "-o", target],
        "simulate": ["simulate", "--model", str(mini["model"]), "--init-logs", str(mini["logs"]), "--out", target],
        "verify": ["verify", "--real", str(mini["logs"]), "--sim", str(mini["logs"]), "--out", target],
        "init": ["init", "--logs", str(mini["logs"]), "-o", target],
    }[command]
    code, err = run_cli(argv)
    line = assert_one_line(code, err, command, flag)
    assert "\\xff" in line and "not UTF-8" in line  # the byte shown, escaped
    assert written(out) == []


def test_an_error_naming_a_file_with_a_line_break_stays_one_whole_line(tmp_path):
    bad = tmp_path / "log_30_1\nbad.csv"
    bad.write_text("time,color,angle\n0,40,30\n")
    code, err = run_cli(["train", "--logs", str(bad), "-o", str(tmp_path / "m.pt")])
    line = assert_one_line(code, err, "train", "bad.csv")  # the name after the break, once cut off
    assert "log_30_1\\nbad" in line
    assert one_line("a\nb\r\nc") == "a\\nb\\nc"


def test_a_play_width_without_the_play_channel_is_refused(mini, tmp_path):
    code, err = run_cli(
        ["train", "--logs", str(mini["logs"]), "--play-width", "0.1", "-o", str(tmp_path / "m.pt"), "--members", "1"]
    )
    assert "--extras play" in assert_one_line(code, err, "train", "--play-width")
    assert written(tmp_path) == []
    with pytest.raises(ValueError, match="play width"):  # the model's config owns it, for the API too
        ModelConfig(n_state=1, n_action=1, history=5, play_width=0.1)


def test_validation_logs_that_are_training_logs_are_refused(mini, tmp_path):
    logs = sorted(mini["logs"].glob("*.csv"))
    code, err = run_cli(["train", "--logs", *map(str, logs), "--val-logs", str(logs[0]), "-o", str(tmp_path / "m.pt")])
    assert "model selection needs logs the model was not fitted to" in assert_one_line(code, err, "train", logs[0])
    assert written(tmp_path) == []
    copy = tmp_path / "copy" / logs[1].name  # a copy is found by its rows, not its name
    copy.parent.mkdir()
    copy.write_bytes(logs[1].read_bytes())
    if logs[1].with_suffix(".meta.json").exists():
        os.link(logs[1].with_suffix(".meta.json"), copy.with_suffix(".meta.json"))
    with pytest.raises(ValueError, match=rf"holds the rows of {logs[1]}"):
        train("bc", load_logs(mini["logs"]), load_logs(copy.parent), epochs=1, hidden=(4,), history=5)


def test_an_unknown_car_gain_is_named(tmp_path):
    code, err = run_cli(["twin", "generate", "--system", "car", "--param", "bogus=1", "--out", str(tmp_path / "car")])
    assert "no version parameter 'bogus'" in assert_one_line(code, err, "twin generate", "bogus")
    assert not (tmp_path / "car").exists()


def test_a_saturation_layer_outside_a_states_range_is_refused(mini, tmp_path):
    layers = tmp_path / "layers.json"
    layers.write_text(json.dumps({"layers": [{"layer": Layer("saturation", 0, 300.0, 400.0).to_json()}]}))
    out = tmp_path / "sim"
    argv = ["simulate", "--model", str(mini["model"]), "--init-logs", str(mini["logs"]), "--layers", str(layers)]
    code, err = run_cli([*argv, "--out", str(out)])
    line = assert_one_line(code, err, "simulate", "saturation [300, 400]")
    assert "outside state 'color'" in line
    assert not out.exists()
    Checkpoint.load(mini["model"]).with_layers([Layer("saturation", 0, 90.0, 400.0)])  # overlapping: taken
