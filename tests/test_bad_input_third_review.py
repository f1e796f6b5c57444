"""Regressions of the third bad-input review (stop 39): each input here once passed silently (a command
beyond its actuator's range written by the native engine and the twin, a sidecar read as a manifest of
its whole folder, a fielded version checked as never field-tested), hung toward a full disk, or failed
late or with torch's own advice. Each must now be one line naming the file or option, exit code 2."""

from __future__ import annotations

import json
import time

import pytest

from envi_py import native
from tests.test_bad_input_audit import assert_one_line, run_cli
from tests.test_envi_sim_bad_input import run_sim
from tests.test_native import envi_sim

RANGE = "outside its declared range [-90, 90]"


ENGINES = ["torch", pytest.param("native", marks=pytest.mark.skipif(not native.available(), reason="not built"))]


@pytest.mark.parametrize("engine", ENGINES)
def test_both_engines_refuse_a_command_beyond_the_actuator_range_alike(mini, tmp_path, engine):
    """The native engine once wrote angle = 1e6 into the logs (exit 0), which envi then could not
    read back; PyTorch refused it. Both now refuse with the same words, and write nothing."""
    code, err = run_cli(
        ["simulate", "--model", str(mini["model"]), "--init-logs", str(mini["logs"]), "--out", str(tmp_path / "s")]
        + ["--controller", "lane-keeping", "--param", "x=1e6", "--engine", engine]
    )
    line = assert_one_line(code, err, "simulate", "lane-keeping(x=1000000)")
    assert "commanded angle = " in line and RANGE in line, line
    assert not list((tmp_path / "s").glob("*.csv"))


@pytest.mark.skipif(envi_sim() is None, reason="envi_sim binary not built")
def test_envi_sim_refuses_a_command_beyond_the_actuator_range(mini, tmp_path):
    init = sorted(mini["logs"].glob("*.csv"))[:1]
    done = run_sim(mini["onnx"], init, tmp_path, "--controller", "lane-keeping", "--param", "x=1e6")
    assert done.returncode == 2, done.stderr
    lines = done.stderr.splitlines()
    assert len(lines) == 1 and "controller 'lane-keeping' commanded angle = " in lines[0] and RANGE in lines[0]
    assert not (tmp_path / "sim").exists() or not list((tmp_path / "sim").glob("*.csv"))
    (tmp_path / "ok").mkdir()  # the same model and controller within range run
    assert run_sim(mini["onnx"], init, tmp_path / "ok", "--controller", "lane-keeping").returncode == 0


def test_the_twin_refuses_a_command_beyond_the_actuator_range(tmp_path):
    """``envi twin generate --param x=1e6`` once wrote logs with angle = +-1e6 that envi's own reader refused."""
    code, err = run_cli(
        ["twin", "generate", "--runs", "2", "--steps", "10", "--param", "x=1e6", "--out", str(tmp_path)]
    )
    assert RANGE in assert_one_line(code, err, "twin generate", "lane-keeping(x=1000000)")
    assert not list(tmp_path.glob("*.csv"))


def test_a_sidecar_given_as_logs_is_not_read_as_its_folder(mini, tmp_path):
    """A ``.meta.json`` once read as a manifest of its whole folder: ``envi split`` split all 4 logs."""
    sidecar = sorted(mini["logs"].glob("*.meta.json"))[0]
    code, err = run_cli(["split", "--logs", str(sidecar), "--out", str(tmp_path / "split")])
    assert "sidecar" in assert_one_line(code, err, "split", sidecar.name)
    other = tmp_path / "notes.json"
    other.write_text(json.dumps({"author": "me"}))
    code, err = run_cli(["split", "--logs", str(other), "--out", str(tmp_path / "split")])
    assert "none of the keys" in assert_one_line(code, err, "split", other.name)
    assert not (tmp_path / "split").exists() or not any((tmp_path / "split").iterdir())


def test_check_refuses_to_call_a_fielded_version_unseen(mini, tmp_path):
    """``--unseen x=30`` with real x = 30 runs once gave a second, contradictory x = 30 row ("never
    field-tested") beside the real-system one."""
    code, err = run_cli(
        ["check", "--model", str(mini["model"]), "--real", str(mini["logs"]), "--unseen", "x=30"]
        + ["--require", "max_abs_dev(color, 40) <= 35", "--max-runs", "40", "--out", str(tmp_path / "c")]
    )
    line = assert_one_line(code, err, "check", "--unseen")
    assert "4 run(s) of this version" in line, line


def test_check_names_an_out_of_range_probability_first(mini):
    code, err = run_cli(["check", "--model", str(mini["model"]), "--real", str(mini["logs"]), "--probability", "2"])
    assert "strictly between 0 and 1" in assert_one_line(code, err, "check", "--probability 2")


def test_a_foreign_model_file_never_passes_on_torchs_advice(mini, tmp_path):
    """torch's message for a file it will not unpickle advises ``weights_only=False``, which would run
    the file's code; the one line says what is wrong, not that."""
    bad = tmp_path / "rand.pt"
    bad.write_bytes(bytes(range(256)) * 8)
    code, err = run_cli(
        ["simulate", "--model", str(bad), "--init-logs", str(mini["logs"]), "--out", str(tmp_path / "s")]
    )
    line = assert_one_line(code, err, "simulate", bad.name)
    assert "weights_only" not in line and len(line) < 400, line


def test_train_refuses_an_output_it_cannot_write_before_training(mini, tmp_path):
    """``envi train -o /proc/x.pt`` once trained to the end, then failed on its state file."""
    blocker = tmp_path / "file.txt"
    blocker.write_text("a file, not a folder")
    out = blocker / "m.pt"
    start = time.perf_counter()
    code, err = run_cli(["train", "--logs", str(mini["logs"]), "--epochs", "1000", "-o", str(out)])
    assert "cannot write in" in assert_one_line(code, err, "train", "--output")
    assert time.perf_counter() - start < 30  # refused up front, not after 1000 epochs


def test_simulate_refuses_more_rows_than_it_can_write_as_logs(mini, tmp_path):
    """``--runs 100000000`` once ran silently toward a full disk."""
    code, err = run_cli(
        ["simulate", "--model", str(mini["model"]), "--init-logs", str(mini["logs"]), "--out", str(tmp_path / "s")]
        + ["--runs", "100000000"]
    )
    line = assert_one_line(code, err, "simulate", "--runs 100000000")
    assert "envi_sim --metrics" in line
    assert not (tmp_path / "s").exists() or not list((tmp_path / "s").glob("*.csv"))
