"""``envi verify`` says when its inputs are not what each option takes, by their sidecars' source:
twin or field logs given as ``--sim``, simulated logs given as ``--real``. They once passed without
a word, so a mix-up of the two folders scored real against real and called it the model's fidelity."""

from __future__ import annotations

from pathlib import Path

import pytest

from envi_py.controllers import ControllerSpec
from envi_py.twin import generate, write_logs
from tests.test_bad_input_audit import run_cli


@pytest.fixture(scope="module")
def folders(mini: dict[str, Path], tmp_path_factory: pytest.TempPathFactory) -> dict[str, Path]:
    """The twin logs and model of ``mini``, other twin runs of the same version, and simulations."""
    d = tmp_path_factory.mktemp("sources")
    write_logs(generate(ControllerSpec("lane-keeping", {"x": 30}), 4, 40, seed=2), d / "other")
    sim = ["simulate", "--model", str(mini["model"]), "--init-logs", str(mini["logs"]), "--out", str(d / "sim")]
    code, err = run_cli(sim)
    assert code == 0, err
    return {"twin": mini["logs"], "other": d / "other", "sim": d / "sim"}


def notes(err: str) -> list[str]:
    return [ln for ln in err.splitlines() if ln.startswith("envi verify: note: ")]


def test_matching_inputs_get_no_note(folders):
    code, err = run_cli(["verify", "--real", str(folders["twin"]), "--sim", str(folders["sim"]), "--no-floor"])
    assert code == 0 and notes(err) == [], err


def test_twin_logs_given_as_sim_are_named(folders):
    code, err = run_cli(["verify", "--real", str(folders["twin"]), "--sim", str(folders["other"]), "--no-floor"])
    [line] = notes(err)
    assert code == 0 and "4 of the 4 --sim log(s)" in line and "source 'twin'" in line, err
    assert "not a simulation" in line


def test_simulated_logs_given_as_real_are_named(folders):
    code, err = run_cli(["verify", "--real", str(folders["sim"]), "--sim", str(folders["twin"]), "--no-floor"])
    lines = notes(err)
    assert code == 0 and any("--real log(s)" in ln and "source 'sim'" in ln for ln in lines), err
