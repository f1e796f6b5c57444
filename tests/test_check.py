"""envi check: one verdict per version and requirement, for the real system, honest about what it rests on."""

from __future__ import annotations

import json
import re

import numpy as np
import pytest

from envi_py.check import check, parse_requirement
from envi_py.cli import main
from envi_py.controllers import ControllerSpec
from envi_py.system import RequirementSpec
from envi_py.train import train
from envi_py.twin import generate, write_logs


@pytest.fixture(scope="module")
def lane(tmp_path_factory):
    d = tmp_path_factory.mktemp("lane")
    logs = []
    for x in (10, 30, 50):
        logs += write_logs(generate(ControllerSpec("lane-keeping", {"x": x}), 8, 60, seed=x), d)
    from envi_py.logs import load_logs

    logs = load_logs(d)
    fit = [lg for i, lg in enumerate(logs) if i % 8 < 4]
    real = [lg for i, lg in enumerate(logs) if i % 8 >= 4]
    ckpt = train("bc", fit, [], epochs=15, hidden=(32, 32), lr=1e-3, history=10, seed=0)
    return ckpt, real, d


REQS = [
    RequirementSpec("near", "max_abs_dev(color, 40) <= 35", "metric", 0.9),
    RequirementSpec("stl", "always (color >= 5)", "stl", 0.8),
]


def test_every_version_and_requirement_gets_a_verdict_with_its_basis(lane):
    ckpt, real, _ = lane
    rows = check(
        ckpt,
        real,
        REQS,
        unseen=[ControllerSpec("lane-keeping", {"x": 20})],
        max_runs=300,
        batch=100,
        sims_per_start=5,
        engine="torch",
    )
    assert [(r.version, r.requirement) for r in rows] == [
        (v, q) for v in ("x=10", "x=30", "x=50", "x=20") for q in ("near", "stl")
    ]
    for r in rows:
        s, q = r.simulation, r.real_system
        assert s["verdict"] in ("PASS", "FAIL", "UNDECIDED") and 0 <= s["successes"] <= s["runs"] <= 300
        assert s["interval"][0] <= s["successes"] / s["runs"] <= s["interval"][1]
        assert q["verdict"] in ("PASS", "FAIL", "UNDECIDED") and 0 <= q["interval"][0] <= q["interval"][1] <= 1
        if r.version == "x=20":
            assert r.n_real == 0 and q["basis"] == "model only"
        else:
            assert r.n_real == 4 and q["basis"] in ("model+real", "real-only")
            assert q["real_only"]["n"] == 4  # the real-only verdict is always shown beside
            if q["verdict"] == "PASS":
                assert q["interval"][0] >= r.p_required


def test_requirements_from_the_command_line():
    assert parse_requirement("min(distance) >= 10 @ 0.95", 0.9, 0) == RequirementSpec(
        "R1", "min(distance) >= 10", "metric", 0.95
    )
    assert parse_requirement("always (distance >= 10)", 0.8, 1).kind == "stl"
    with pytest.raises(ValueError, match="strictly between"):
        parse_requirement("min(distance) >= 10 @ 1.5", 0.9, 0)


def test_check_cli_writes_the_verdict_table_first(lane, tmp_path, capsys):
    ckpt, real, d = lane
    model = ckpt.save(tmp_path / "m.pt")
    paths = [str(lg.path) for lg in real]
    assert (
        main(
            [
                "check",
                "--model",
                str(model),
                "--real",
                *paths,
                "--require",
                "max_abs_dev(color, 40) <= 35@0.9",
                "--max-runs",
                "200",
                "--batch",
                "100",
                "--sims-per-start",
                "4",
                "--engine",
                "torch",
                "--out",
                str(tmp_path / "c"),
            ]
        )
        == 0
    )
    md = (tmp_path / "c" / "check.md").read_text()
    assert md.splitlines()[2].startswith("| version | requirement |") and "## Provenance" in md
    # the real runs' own verdict beside every combined one (4 real runs per version here)
    assert md.splitlines()[2].rstrip().endswith("| real runs only [interval] |")
    assert len(re.findall(r"\| \d/4 \[[01]\.\d{3}, [01]\.\d{3}\] (?:PASS|FAIL|UNDECIDED) \|", md)) == 3
    assert re.search(r" \d/4 \[[01]\.\d{3}, [01]\.\d{3}\] (?:PASS|FAIL|UNDECIDED)$", capsys.readouterr().out, re.M)
    js = json.loads((tmp_path / "c" / "check.json").read_text())
    assert len(js["rows"]) == 3 and js["alpha"] == 0.05
    assert (
        main(
            [
                "check",
                "--model",
                str(model),
                "--real",
                *paths,
                "--require",
                "max_abs_dev(nope, 40) <= 35",
                "--engine",
                "torch",
            ]
        )
        == 2
    )
    err = capsys.readouterr().err.strip()
    assert err == "envi check: error: requirement 'R1': unknown signal 'nope'; signals: color, angle"
    assert np.isfinite(js["rows"][0]["real_system"]["interval"][0])


def test_runs_commanding_actions_beyond_the_training_range_are_counted_outside(lane):
    """A version beyond the trained ones (x = 80 against 10..50) commands steering the model never saw:
    every one of its runs leaves the training data, although its states may stay in range."""
    ckpt, real, _ = lane
    rows = check(
        ckpt,
        real[:4],
        REQS[:1],
        unseen=[ControllerSpec("lane-keeping", {"x": 20}), ControllerSpec("lane-keeping", {"x": 80})],
        max_runs=100,
        batch=50,
        sims_per_start=2,
        engine="torch",
    )
    by_version = {r.version: r for r in rows}
    far, near = by_version["x=80"], by_version["x=20"]
    assert far.outside_training == far.sim_runs > 0
    assert near.outside_training < near.sim_runs / 2
    # no verdict about the real system rests on extrapolation
    assert far.real_system["verdict"] == "UNDECIDED" and "extrapolation" in far.real_system["reason"]


def test_odd_requests_are_refused_naming_what_is_wrong(lane, tmp_path):
    """A required probability the sequential test cannot hold ('delta must lie in (0, 1), got -9.99e-07'
    named nothing), a version given twice (x=1,x=2 ran as x=2), an exported model given as the
    checkpoint (PyTorch's weights_only advice)."""
    from envi_py.cli import parse_where_one
    from envi_py.model import Checkpoint

    ckpt, real, _ = lane
    tiny = RequirementSpec("rare", "max(color) <= 100", "metric", 1e-300)
    with pytest.raises(ValueError, match="requirement 'rare': probability 1e-300 lies too close to 0 or 1"):
        check(ckpt, real, [tiny], engine="torch")
    from envi_py.check import requirements_of

    with pytest.raises(ValueError, match="^--unseen x=1e\\+308: "):
        check(ckpt, real, REQS[:1], unseen=[ControllerSpec("lane-keeping", {"x": 1e308})], engine="torch")

    with pytest.raises(ValueError, match="^--probability nan: must lie strictly between 0 and 1$"):
        requirements_of(None, ["max(color) <= 100"], float("nan"))
    with pytest.raises(ValueError, match="'x' is given twice"):
        parse_where_one("x=1,x=2")
    onnx = tmp_path / "m.onnx"
    onnx.write_bytes(b"\x08\x07\x12\x04envi")
    with pytest.raises(ValueError, match="an exported ONNX model, not an envi checkpoint"):
        Checkpoint.load(onnx)


def test_runs_from_further_starts_count_in_the_outside_figure(lane):
    """The further starts' simulations feed the real-system estimate, so they are among the runs the
    'outside the training data' figure is over (they were in neither its count nor its total)."""
    ckpt, real, _ = lane
    (row,) = check(
        ckpt, real[:2], REQS[:1], extra_starts=real[2:4], max_runs=50, batch=50, sims_per_start=3, engine="torch"
    )
    assert row.sim_runs == row.simulation["runs"] + (2 + 2) * 3


def test_a_batch_beyond_the_cap_is_refused_and_a_small_cap_is_one_look(lane, tmp_path, capsys):
    """``--max-runs 5 --batch 10`` once ran 5 runs without a word; a cap below the default batch of 10,
    given alone, is one look of the whole cap (as the report's provenance records)."""
    ckpt, real, _ = lane
    model = ckpt.save(tmp_path / "m.pt")
    base = ["check", "--model", str(model), "--real", str(real[0].path), "--require", "max(color) <= 100"]
    base += ["--engine", "torch", "--sims-per-start", "2"]
    assert main([*base, "--max-runs", "5", "--batch", "10"]) == 2
    err = capsys.readouterr().err.strip()
    assert err == "envi check: error: --batch 10 is more than --max-runs 5: give at most the cap", err
    assert main([*base, "--max-runs", "6", "--out", str(tmp_path / "c")]) == 0
    js = json.loads((tmp_path / "c" / "check.json").read_text())
    assert js["provenance"]["batch"] == 6 and js["provenance"]["max_runs"] == 6, js["provenance"]
    assert main([*base, "--max-runs", "30", "--out", str(tmp_path / "d")]) == 0
    js = json.loads((tmp_path / "d" / "check.json").read_text())
    assert js["provenance"]["batch"] == 10 and js["provenance"]["max_runs"] == 30, js["provenance"]
