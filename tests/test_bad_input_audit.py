"""The bad-input audit's regressions: each input here once gave a traceback, a wrong exit code, a
message naming no file, or a silently wrong result (list: /work/bench/audit.md). Each must now be
one line on stderr naming the file and the problem, exit code 2, or (for the check) the right result."""

from __future__ import annotations

import contextlib
import io
import shutil
from pathlib import Path

import pytest

from envi_py.check import check
from envi_py.cli import main
from envi_py.controllers import ControllerSpec
from envi_py.logs import load_logs
from envi_py.system import RequirementSpec, SystemDescription, load_system, shipped
from envi_py.train import train
from envi_py.twin import generate, write_logs


def run_cli(argv: list[str]) -> tuple[int, str]:
    """``envi <argv>`` in process: the exit code and stderr."""
    err = io.StringIO()
    with contextlib.redirect_stderr(err), contextlib.redirect_stdout(io.StringIO()):
        try:
            code = main(argv)
        except SystemExit as exc:
            code = exc.code if isinstance(exc.code, int) else 2
    return code, err.getvalue()


def assert_one_line(code: int, err: str, cmd: str, *names: object) -> str:
    """Exit code 2 and one stderr line from ``envi <cmd>`` naming one of ``names``."""
    lines = [ln for ln in err.splitlines() if ln.strip()]
    assert code == 2, (code, err)
    assert len(lines) == 1 and lines[0].startswith(f"envi {cmd}: error: "), err
    assert any(str(n) in lines[0] for n in names), f"{lines[0]!r} names none of {names}"
    return lines[0]


@pytest.fixture(scope="module")
def lane_logs(tmp_path_factory: pytest.TempPathFactory) -> Path:
    d = tmp_path_factory.mktemp("lane")
    write_logs(generate(ControllerSpec("lane-keeping", {"x": 30}), 4, 40, seed=1), d)
    return d


# ----------------------------------------------------------------------------- system descriptions

CAR = shipped()["car"].read_text()


@pytest.mark.parametrize(
    "old, new, why",
    [
        ("period_ms = 40", "periodms = 40", "unknown key 'periodms' (did you mean 'period_ms'?"),
        ("[system]", "[sytem]", "unknown key 'sytem' (did you mean 'system'?"),
        ('role = "logged"', 'role = "logged"\nscale = 2', "[[signals]]: unknown key 'scale'"),
        ("probability = 0.95", "probabilty = 0.95", "did you mean 'probability'?"),
        ('metric = "max_abs_dev"', 'metric = "nosuch"', "unknown goal metric 'nosuch'"),
        ("setpoint = 40\n", "setpoint = 40\nband = 3\n", "has no parameter 'band'"),
        ("min(distance) >= 10", "min(dist) >= 10", "unknown signal 'dist'"),
        ("min(distance) >= 10", "minimum(distance) >= 10", "unknown metric 'minimum'"),
        ("min(distance) >= 10", "min(distance >= >= 10", "is not an expression"),
        ('expr = "min(distance) >= 10"', 'kind = "stl"\nexpr = "always[0:10]((color >= 5) and"', "STL syntax"),
        ('expr = "min(distance) >= 10"', 'kind = "stl"\nexpr = "always[0:10](colour >= 5)"', "'colour'"),
        ('kp_steer = "loops.0.params.kp"', 'kp_steer = "loops.9.params.kp"', "does not lead into"),
    ],
)
def test_a_wrong_description_is_refused_when_read_naming_the_file(tmp_path: Path, old: str, new: str, why: str):
    """Typos and requirements that cannot parse were once accepted silently (a typo'd key dropped,
    a bad requirement found only by ``envi check`` after the training)."""
    assert old in CAR
    f = tmp_path / "car.toml"
    f.write_text(CAR.replace(old, new, 1))
    with pytest.raises(ValueError) as exc:
        load_system(f)
    assert str(f) in str(exc.value) and why in str(exc.value) and "\n" not in str(exc.value)
    code, err = run_cli(["split", "--logs", str(tmp_path), "--system", str(f), "--out", str(tmp_path / "s")])
    assert why in assert_one_line(code, err, "split", f)


@pytest.mark.parametrize("name", sorted(shipped()))
def test_the_shipped_descriptions_pass_the_read_time_checks(tmp_path: Path, name: str):
    """A copy (not read as shipped) goes through every check a user's file does."""
    copy = tmp_path / f"{name}.toml"
    shutil.copy(shipped()[name], copy)
    assert load_system(copy).schema == load_system(name).schema


def test_a_description_without_system_table_is_named_after_its_file(tmp_path: Path):
    """[system] is optional (the name is the file's, the period the logs'): documented, not an error."""
    f = tmp_path / "mine.toml"
    f.write_text("[[signals]]\nname = 'a'\nrole = 'state'\n[[signals]]\nname = 'b'\nrole = 'action'\n")
    desc = SystemDescription.load(f)
    assert desc.name == "mine" and desc.period_ms is None


# ----------------------------------------------------------------------------- envi check


@pytest.fixture(scope="module")
def lane_model(lane_logs: Path, tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A two-epoch model of the lane-keeping twin, saved as a checkpoint."""
    ckpt = train("bc", load_logs(lane_logs), [], epochs=2, hidden=(8, 8), history=5, seed=0)
    return ckpt.save(tmp_path_factory.mktemp("model") / "lane.pt")


def test_check_starts_from_further_logs_that_repeat_the_real_ones(lane_logs: Path, lane_model: Path):
    """The real logs again among the further starts (the CLI passes the training logs, often the
    same files): once ``ValueError: The truth value of an array ... is ambiguous`` from ``lg in logs``."""
    from envi_py.model import Checkpoint

    ckpt = Checkpoint.load(lane_model)
    real = load_logs(lane_logs)
    again = load_logs(lane_logs)  # equal content, other objects
    req = [RequirementSpec("near", "max_abs_dev(color, 40) <= 35", "metric", 0.9)]
    kw = dict(max_runs=20, batch=10, sims_per_start=2, engine="torch")
    rows = check(ckpt, real, req, extra_starts=again + real, **kw)
    assert len(rows) == 1 and rows[0].n_real == len(real)
    assert "no further starts" in " ".join(rows[0].notes)  # repeats are not further starts


def test_check_reads_the_requirements_of_the_system_it_is_given(lane_logs: Path, lane_model: Path, tmp_path: Path):
    """``--system`` once changed only how logs are read; its requirements were silently replaced by
    the checkpoint's copy."""
    f = tmp_path / "lane.toml"
    f.write_text(
        shipped()["lane-keeping"].read_text() + '\n[[requirements]]\nname = "added"\nexpr = "min(color) >= 0"\n'
    )
    out = tmp_path / "out"
    argv = ["check", "--model", str(lane_model), "--real", str(lane_logs), "--max-runs", "20", "--batch", "10"]
    code, err = run_cli([*argv, "--sims-per-start", "2", "--engine", "torch", "--system", str(f), "--out", str(out)])
    assert code == 0, err
    assert "added" in (out / "check.md").read_text()
