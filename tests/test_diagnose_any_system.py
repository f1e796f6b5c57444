"""``envi diagnose`` on a system other than lane keeping: the car twin (two states, two actions, three
declared goals). Gaps are scored on every goal against the project's fair floor, residuals on every state."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest

from envi_py.cli import main
from envi_py.diagnose.gap import VERSION_PERMUTATIONS, gap_rank
from envi_py.logs import load_logs
from envi_py.system import load_system
from envi_py.train import train
from envi_py.twin.car import generate_car_versions, write_car_logs
from envi_py.verdicts import fair_floor, w1_normalised
from envi_py.verify import fair_reference

SEED = 3


def test_car_diagnosis_scores_every_goal_against_the_fair_floor_and_every_state(tmp_path, capsys):
    write_car_logs(generate_car_versions(8, 100, seed=0, versions=[0, 1]), tmp_path / "fit")
    write_car_logs(generate_car_versions(8, 100, seed=1, versions=[0, 1]), tmp_path / "real")
    write_car_logs(generate_car_versions(2, 100, seed=2, versions=[0, 1]), tmp_path / "confirm")
    fit = load_logs(tmp_path / "fit")
    ckpt = train("bc", fit, [], seed=0, epochs=20, lr=1e-3, history=4, head="deterministic")
    ckpt.save(tmp_path / "car.pt")
    out = tmp_path / "diag"
    args = ["diagnose", "--model", str(tmp_path / "car.pt"), "--real", str(tmp_path / "real")]
    args += ["--confirm", str(tmp_path / "confirm"), "--train-logs", str(tmp_path / "fit")]
    args += ["--runs", "2", "--no-retrain", "--seed", str(SEED), "--out", str(out)]
    assert main(args) == 0
    captured = capsys.readouterr()
    verdict = captured.out
    # progress: each step announced on standard error as it starts (no retraining step here)
    steps = [line for line in captured.err.splitlines() if line.startswith("[diagnose] ")]
    labels = [line.split()[1] for line in steps]
    assert labels[:3] == ["1/6", "2/6", "3/6"] and labels[-2:] == ["4/6", "5/6"], captured.err
    d = json.loads((out / "diagnosis.json").read_text())
    car_goals = {g.name for g in load_system("car").goals}
    assert len(d["gaps"]) == 2 and d["system"] == "car"
    for version in d["gaps"]:
        assert {r["goal"] for r in version["gaps"]} == car_goals
        assert version["n_real"] == 8 and version["per_side"] == 4
        for r in version["gaps"]:
            assert r["ratio"] == math.inf or math.isfinite(r["ratio"]), r
            assert 0 < r["p"] <= 1, r
        # The floor and the matched W1 are envi verify's (fair_reference, same seed); each p-value
        # is the fair floor's permutation test on that goal.
        rows = version["gaps"]
        mr, ms = np.array([r["real"] for r in rows]).T, np.array([r["sim"] for r in rows]).T
        scale = np.array([r["scale"] for r in rows])
        floor, matched, tests = fair_reference(mr, ms, scale, None, None, SEED, permutations=VERSION_PERMUTATIONS)
        np.testing.assert_allclose([r["floor"] for r in rows], floor.w1)
        np.testing.assert_allclose([r["w1"] for r in rows], matched.w1)
        assert version["goals_test"]["p_value"] == tests["goals_w1"]["p_value"]
        for j, r in enumerate(rows):
            assert r["p"] == fair_floor(mr[:, j], ms[:, j], w1_normalised(scale[j]), 10, 99, 0.05, SEED).p_value
    assert [c["signal"] for c in d["residual_map"]] == ["color", "distance"]
    assert [c["unit"] for c in d["residual_map"]] == ["%", "cm"]
    for c in d["residual_map"]:
        assert c["rmse"] > 0 and [m["action_signal"] for m in c["by_action"]] == ["steering", "speed"]
    assert {h["signal"] for h in d["horizon"]} == {"color", "distance"}
    assert all(set(r["rms"]) == {"color", "distance"} for r in d["runs"])
    effects = {f["effect"] for f in d["findings"]}
    assert {"noise on color", "noise on distance", "backlash on steering", "backlash on speed"} <= effects
    assert d["shrink"] is None
    md = (out / "diagnosis.md").read_text()
    for goal in car_goals:
        assert f"| {goal} |" in md
    # The verdict leads with the goal ranked first: beyond the floor by its test, then by ratio.
    version, lead = min(((g, r) for g in d["gaps"] for r in g["gaps"]), key=lambda x: gap_rank(x[1]))
    assert "distance [cm]: cells with significant bias" in md
    assert f"is in {lead['goal']} of {version['controller']} (" in verdict


def test_diagnose_takes_no_lane_only_centre_or_band(tmp_path, capsys):
    """The lane-keeping preset takes its centre from the system description; the command line has
    no lane-only option left to contradict it on another system."""
    with pytest.raises(SystemExit) as exit_:
        main(["diagnose", "--help"])
    assert exit_.value.code == 0
    usage = capsys.readouterr().out
    assert "--model" in usage and "--centre" not in usage and "--band" not in usage
    for option in ("--centre=40", "--band=10"):
        with pytest.raises(SystemExit) as exit_:
            main(["diagnose", "--model", str(tmp_path / "car.pt"), "--real", str(tmp_path), option])
        assert exit_.value.code == 2
        assert f"unrecognized arguments: {option}" in capsys.readouterr().err
