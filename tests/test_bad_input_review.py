"""Regressions of the second bad-input review (stop 26): each input here once gave a traceback, a
hang, a silently ignored option, lost output, or a message naming no file. Each must now be one line
on stderr naming the file (or option) and the problem, exit code 2, with earlier output intact."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import pytest

from envi_py.atomic import atomic_write_text
from envi_py.controllers import ControllerSpec
from envi_py.experiments.run import _journal_line, _read_journal
from envi_py.logs import LogError, load_logs
from envi_py.system import load_system, shipped
from envi_py.train import train
from envi_py.twin import generate, write_logs
from tests.test_bad_input_audit import assert_one_line, run_cli

CONTROLLERS = """
import numpy as np

def raising(states):
    raise RuntimeError("boom at step 3")

def nan(states):
    return np.full((states.shape[0], 1), np.nan)

def huge(states):
    return np.full((states.shape[0], 1), 1e9)

def exits(states):
    raise SystemExit(0)
"""


@pytest.fixture(scope="module")
def setup(tmp_path_factory: pytest.TempPathFactory) -> dict[str, Path]:
    d = tmp_path_factory.mktemp("review")
    logs = d / "logs"
    write_logs(generate(ControllerSpec("lane-keeping", {"x": 30}), 4, 40, seed=1), logs)
    ckpt = train("bc", load_logs(logs), [], epochs=2, hidden=(8, 8), history=5, seed=0)
    ckpt.save(d / "m.pt")
    (d / "review_ctl.py").write_text(CONTROLLERS)
    return {"dir": d, "logs": logs, "model": d / "m.pt"}


@pytest.fixture
def user_controllers(setup: dict[str, Path], monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.syspath_prepend(str(setup["dir"]))


def _simulate(setup: dict[str, Path], out: Path, *extra: str) -> tuple[int, str]:
    return run_cli(
        ["simulate", "--model", str(setup["model"]), "--init-logs", str(setup["logs"]), "--out", str(out), *extra]
    )


def test_a_failed_simulate_force_keeps_the_earlier_logs(setup, user_controllers, tmp_path):
    """``--force`` once deleted the earlier logs before simulating, so a controller that raised
    left an empty folder; the new run is now written aside and moved in only when it is whole."""
    out = tmp_path / "sim"
    assert _simulate(setup, out, "--engine", "torch")[0] == 0
    before = {p.name: p.read_bytes() for p in out.iterdir()}
    assert any(n.endswith(".csv") for n in before)
    code, err = _simulate(setup, out, "--force", "--engine", "torch", "--controller", "review_ctl:raising")
    line = assert_one_line(code, err, "simulate", "review_ctl:raising")
    assert "RuntimeError" in line and "boom at step 3" in line
    assert {p.name: p.read_bytes() for p in out.iterdir()} == before  # nothing lost, nothing half-written


def test_a_controller_calling_sys_exit_is_a_controller_error(setup, user_controllers, tmp_path):
    """A user's controller that called ``sys.exit(0)`` once ended ``envi simulate`` with exit 0 and no
    word, as if the simulation had succeeded; it is a failed controller like any other."""
    code, err = _simulate(setup, tmp_path / "sim", "--engine", "torch", "--controller", "review_ctl:exits")
    line = assert_one_line(code, err, "simulate", "review_ctl:exits")
    assert "SystemExit" in line
    assert not (tmp_path / "sim").exists() or not list((tmp_path / "sim").glob("*.csv"))


def test_a_successful_simulate_force_replaces_the_earlier_logs(setup, tmp_path):
    out = tmp_path / "sim"
    assert _simulate(setup, out, "--engine", "torch")[0] == 0
    (out / "notes.txt").write_text("mine")
    assert _simulate(setup, out, "--force", "--engine", "torch", "--runs", "2")[0] == 0
    assert len(list(out.glob("*.csv"))) == 8 and (out / "notes.txt").read_text() == "mine"
    assert not [p for p in out.iterdir() if p.name.startswith(".")]  # no staging folder left behind


@pytest.mark.parametrize(
    "controller, why",
    [("review_ctl:nan", "non-finite action (nan)"), ("review_ctl:huge", "outside its declared range")],
)
def test_a_controller_answering_nan_or_beyond_the_action_range_is_refused(
    setup, user_controllers, tmp_path, controller, why
):
    """Such answers were once written into the simulated log, which then could not be read back."""
    code, err = _simulate(setup, tmp_path / "sim", "--engine", "torch", "--controller", controller)
    assert why in assert_one_line(code, err, "simulate", controller)
    assert not list((tmp_path / "sim").glob("*.csv"))


def test_param_without_controller_is_refused(setup, tmp_path):
    """``--param x=abc`` without ``--controller`` was silently ignored."""
    code, err = _simulate(setup, tmp_path / "sim", "--param", "x=45")
    assert_one_line(code, err, "simulate", "--param")


def test_demo_refuses_zero_epochs(tmp_path):
    """``--epochs 0`` once trained the size's default silently."""
    code, err = run_cli(["demo", "--fast", "--epochs", "0", "--out", str(tmp_path / "demo")])
    assert_one_line(code, err, "demo", "--epochs")


def test_a_damaged_journal_record_is_not_reused_and_named(tmp_path, capsys):
    """A record edited by hand once crashed the report (``TypeError``); now it is not reused."""
    journal = tmp_path / "jobs.jsonl"
    good = _journal_line("a", {"train_seconds": 1.5, "evals": {}})
    tampered = json.loads(_journal_line("b", {"train_seconds": 2.0}))
    tampered["result"]["train_seconds"] = "2.0"
    journal.write_text(good + "[1, 2]\n" + json.dumps(tampered) + "\n" + '{"fingerprint": "c", "res')
    done = _read_journal(journal)
    assert done == {"a": {"train_seconds": 1.5, "evals": {}}}
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and str(journal) in err[0] and "2 damaged" in err[0] and "line 2, 3" in err[0]


@pytest.mark.parametrize("option", ["--layers", "--system"])
def test_a_named_pipe_is_refused_at_once(setup, tmp_path, option):
    """A FIFO given as a layers file or description made the command wait for ever."""
    fifo = tmp_path / "fifo"
    os.mkfifo(fifo)
    argv = ["simulate", "--model", str(setup["model"]), "--init-logs", str(setup["logs"]), "--out", str(tmp_path / "o")]
    proc = subprocess.run(
        [sys.executable, "-m", "envi_py.cli", *argv, option, str(fifo)], capture_output=True, text=True, timeout=120
    )
    assert_one_line(proc.returncode, proc.stderr, "simulate", fifo)
    assert "not a regular file" in proc.stderr


def test_a_named_pipe_as_run_file_is_refused_at_once(tmp_path):
    fifo = tmp_path / "run.toml"
    os.mkfifo(fifo)
    proc = subprocess.run(
        [sys.executable, "-m", "envi_py.cli", "--config", str(fifo), "split", "--logs", str(tmp_path)],
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert proc.returncode == 2 and str(fifo) in proc.stderr and "not a regular file" in proc.stderr, proc.stderr


def test_a_file_named_twice_is_read_once_and_an_empty_folder_is_an_error(setup, tmp_path):
    logs = setup["logs"]
    one = sorted(logs.glob("*.csv"))[0]
    assert len(load_logs([logs, one])) == len(load_logs(logs)) == 4
    (tmp_path / "empty.csv").mkdir()  # a folder named like a log
    with pytest.raises(LogError, match="a folder holding no logs"):
        load_logs([logs, tmp_path / "empty.csv"])


def test_init_refuses_a_pattern_that_does_not_match_the_logs(tmp_path):
    logs = tmp_path / "logs"
    write_logs(generate(ControllerSpec("lane-keeping", {"x": 30}), 2, 20, seed=1), logs)
    out = tmp_path / "system.toml"
    code, err = run_cli(["init", "--logs", str(logs), "--pattern", "foo_{x}_{run}.csv", "-o", str(out)])
    assert "does not match --pattern" in assert_one_line(code, err, "init", logs)
    assert not out.exists()


def test_verify_names_the_log_too_short_to_score(setup, tmp_path):
    real = tmp_path / "real"
    write_logs(generate(ControllerSpec("lane-keeping", {"x": 30}), 4, 8, seed=2), real)
    code, err = run_cli(["verify", "--real", str(real), "--sim", str(setup["logs"]), "--skip", "10"])
    assert "leaves nothing to score" in assert_one_line(code, err, "verify", real)


def test_verify_says_which_simulated_runs_it_does_not_score(setup, tmp_path):
    """A simulated log whose sidecar went missing was once dropped without a word."""
    sim = tmp_path / "sim"
    assert _simulate(setup, sim, "--engine", "torch", "--runs", "2")[0] == 0
    lost = sorted(sim.glob("*.meta.json"))[0]
    lost.unlink()
    code, err = run_cli(["verify", "--real", str(setup["logs"]), "--sim", str(sim)])
    assert code == 0
    notes = [ln for ln in err.splitlines() if "not scored" in ln]
    assert len(notes) == 1 and lost.name.replace(".meta.json", ".csv") in notes[0]


def test_a_description_with_an_unknown_controller_is_refused_naming_the_file(tmp_path):
    f = tmp_path / "bad.toml"
    text = shipped()["lane-keeping"].read_text()
    f.write_text(text.replace('name = "lane-keeping"     #', 'name = "no-such-controller"  #'))
    with pytest.raises(ValueError, match="unknown controller 'no-such-controller'") as exc:
        load_system(f)
    assert str(exc.value).startswith(str(f))


def test_a_write_that_cannot_start_names_the_target_not_a_temporary_file(tmp_path):
    blocker = tmp_path / "file"
    blocker.write_text("x")
    with pytest.raises(OSError) as exc:
        atomic_write_text(blocker / "m.pt", "y")
    assert exc.value.filename == str(blocker / "m.pt") and ".tmp" not in str(exc.value)


def test_a_layers_file_missing_a_key_says_which(tmp_path):
    from envi_py.effect_layers import read_layers

    f = tmp_path / "layers.json"
    f.write_text(json.dumps({"layers": [{"kind": "delay"}]}))
    with pytest.raises(ValueError, match="no key 'layer'"):
        read_layers(f)


def test_probability_that_applies_to_no_requirement_is_refused():
    """``--probability`` was silently ignored when every requirement gave its own '@P'."""
    from envi_py.check import requirements_of

    system = load_system("lane-keeping")
    with pytest.raises(ValueError, match="would apply to no requirement: every --require gives its own"):
        requirements_of(system, ["max_abs_dev(color, 40) <= 35 @ 0.8"], 0.95)
    with pytest.raises(ValueError, match="the system description's requirements give theirs"):
        requirements_of(system, [], 0.95)
    mixed = requirements_of(system, ["max_abs_dev(color, 40) <= 35 @ 0.8", "max_abs_dev(color, 40) <= 30"], 0.95)
    assert [r.probability for r in mixed] == [0.8, 0.95]
    assert requirements_of(system, ["max_abs_dev(color, 40) <= 30"])[0].probability == 0.9


def test_a_training_state_is_named_after_the_whole_output(setup, tmp_path):
    """The state was ``output.with_suffix('.state')``: ``-o x.state`` deleted the model it had just
    saved, and ``-o m.other`` removed the resumable state of an interrupted ``-o m.pt``."""
    args = ["train", "--logs", str(setup["logs"]), "--algorithm", "bc", "--epochs", "2", "--hidden", "8"]
    args += ["--history", "4", "--quiet"]
    kept = tmp_path / "m.pt.state"
    kept.write_bytes(b"an interrupted training's state")
    assert run_cli([*args, "-o", str(tmp_path / "x.state")])[0] == 0
    assert run_cli([*args, "-o", str(tmp_path / "m.other")])[0] == 0
    assert (tmp_path / "x.state").is_file() and (tmp_path / "m.other").is_file()
    assert kept.read_bytes() == b"an interrupted training's state"
