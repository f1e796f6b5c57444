"""``envi verify`` says when its inputs are not what each option takes, by their sidecars' source:
twin or field logs given as ``--sim``, simulated logs given as ``--real``. They once passed without
a word, so a mix-up of the two folders scored real against real and called it the model's fidelity."""

from __future__ import annotations

from pathlib import Path

import pytest

from envi_py.controllers import ControllerSpec
from envi_py.logs import load_logs
from envi_py.train import train
from envi_py.twin import generate, write_logs
from tests.test_bad_input_audit import run_cli


@pytest.fixture(scope="module")
def folders(tmp_path_factory: pytest.TempPathFactory) -> dict[str, Path]:
    d = tmp_path_factory.mktemp("sources")
    twin, other = d / "twin", d / "other"
    write_logs(generate(ControllerSpec("lane-keeping", {"x": 30}), 4, 40, seed=1), twin)
    write_logs(generate(ControllerSpec("lane-keeping", {"x": 30}), 4, 40, seed=2), other)
    ckpt = train("bc", load_logs(twin), [], epochs=2, hidden=(8, 8), history=5, seed=0, members=1)
    ckpt.save(d / "m.pt")
    code, err = run_cli(["simulate", "--model", str(d / "m.pt"), "--init-logs", str(twin), "--out", str(d / "sim")])
    assert code == 0, err
    return {"twin": twin, "other": other, "sim": d / "sim"}


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
