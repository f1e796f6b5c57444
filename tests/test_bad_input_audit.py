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
        # once accepted: envi check printed two rows under one name
        ('name = "keeps the lane"', 'name = "no collision"', "requirement 'no collision' is given twice"),
        ('params = ["kp_steer", "kp_speed"]', 'params = ["kp_steer", "kp_steer"]', "'kp_steer' is given twice"),
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


# ----------------------------------------------------------------------------- logs and models


@pytest.fixture(scope="module")
def car_logs(tmp_path_factory: pytest.TempPathFactory) -> Path:
    d = tmp_path_factory.mktemp("car")
    code, err = run_cli(
        ["twin", "generate", "--system", "car", "--version", "0", "1", "--runs", "2", "--steps", "30", "--out", str(d)]
    )
    assert code == 0, err
    return d


@pytest.mark.parametrize(
    "cmd, extra",
    [
        ("simulate", ["--init-logs"]),
        ("check", ["--max-runs", "20", "--batch", "10", "--real"]),
        ("diagnose", ["--no-retrain", "--runs", "2", "--real"]),
    ],
)
def test_a_model_of_another_system_names_the_log_and_the_model(
    cmd: str, extra: list[str], car_logs: Path, lane_model: Path, tmp_path: Path
):
    """Once a message naming neither file ('controller pid reads state channel 1') or, for the
    diagnosis, an IndexError traceback."""
    code, err = run_cli([cmd, "--model", str(lane_model), "--out", str(tmp_path / "o"), *extra, str(car_logs)])
    line = assert_one_line(code, err, cmd, car_logs)
    assert str(lane_model) in line and "another system" in line


def test_a_controller_unknown_to_the_registry_in_a_sidecar_is_one_line_naming_the_log(
    lane_logs: Path, lane_model: Path, tmp_path: Path
):
    """Once two lines: a note that the native engine cannot run it, then the error naming no file."""
    d = tmp_path / "logs"
    shutil.copytree(lane_logs, d)
    side = sorted(d.glob("*.meta.json"))[0]
    side.write_text(side.read_text().replace('"lane-keeping"', '"nosuch"', 1))
    code, err = run_cli(["simulate", "--model", str(lane_model), "--init-logs", str(d), "--out", str(tmp_path / "o")])
    assert "unknown controller 'nosuch'" in assert_one_line(
        code, err, "simulate", side.with_suffix("").with_suffix(".csv")
    )


@pytest.mark.parametrize(
    "argv, why",
    [
        (["--param", "x=nan"], "non-finite"),  # once simulated NaN logs, exit 0
        (["--param", "x=inf"], "non-finite"),
    ],
)
def test_simulate_refuses_a_non_finite_gain(
    lane_logs: Path, lane_model: Path, tmp_path: Path, argv: list[str], why: str
):
    out = tmp_path / "o"
    base = ["simulate", "--model", str(lane_model), "--init-logs", str(lane_logs), "--out", str(out)]
    code, err = run_cli([*base, "--controller", "lane-keeping", *argv])
    assert why in assert_one_line(code, err, "simulate", "--param")
    assert not out.exists()


def test_simulate_refuses_zero_steps(lane_logs: Path, lane_model: Path, tmp_path: Path):
    """``--steps 0`` once exited 0 having written logs of the initial window alone."""
    out = tmp_path / "o"
    argv = ["simulate", "--model", str(lane_model), "--init-logs", str(lane_logs), "--steps", "0", "--out", str(out)]
    assert "--steps must lie in 1..1000000" in assert_one_line(*run_cli(argv), "simulate", "--steps")
    assert not out.exists()


def test_an_output_that_is_a_file_is_named_plainly(lane_logs: Path, lane_model: Path, tmp_path: Path):
    """Once '[Errno 17] File exists: ...' (simulate: after the simulation's work)."""
    f = tmp_path / "afile"
    f.write_text("keep me\n")
    for cmd, argv in (
        ("simulate", ["--model", str(lane_model), "--init-logs", str(lane_logs)]),
        ("split", ["--logs", str(lane_logs)]),
        # verify once found it after all its work, behind numpy warnings; check after its simulations
        ("verify", ["--real", str(tmp_path / "none"), "--sim", str(tmp_path / "none")]),
        ("check", ["--model", str(tmp_path / "none.pt"), "--real", str(lane_logs), "--require", "x: P >= 0.5"]),
    ):
        code, err = run_cli([cmd, *argv, "--out", str(f)])
        assert "exists and is not a folder" in assert_one_line(code, err, cmd, f)
    assert f.read_text() == "keep me\n"


def test_an_output_that_is_an_input_is_refused_and_the_input_kept(lane_logs: Path, lane_model: Path, tmp_path: Path):
    """``envi train -o log.csv`` and ``envi-export m.pt -o m.pt`` once replaced the input they read,
    exit 0 (found by a bad-input sweep): now one line naming the output, nothing written."""
    from envi_py.export_cli import main as export_main

    logs = tmp_path / "logs"
    shutil.copytree(lane_logs, logs)
    first = sorted(logs.glob("*.csv"))[0]
    before = first.read_bytes()
    argv = ["train", "--logs", str(logs), "--epochs", "1", "--members", "1", "--history", "5", "-o", str(first)]
    line = assert_one_line(*run_cli(argv), "train", first)
    assert "is an input of this command" in line and first.read_bytes() == before
    model = tmp_path / "m.pt"
    shutil.copy(lane_model, model)
    err = io.StringIO()
    with contextlib.redirect_stderr(err), contextlib.redirect_stdout(io.StringIO()):
        code = export_main([str(model), "-o", str(tmp_path / "." / "m.pt")])
    assert code == 2 and "is an input of this command" in err.getvalue() and len(err.getvalue().splitlines()) == 1
    assert model.read_bytes() == lane_model.read_bytes()


def test_a_model_saved_among_its_logs_is_refused_before_training(lane_logs: Path, tmp_path: Path):
    """``envi train -o logs/m.pt`` once wrote ``logs/m.curves.csv`` beside the logs, and every later
    read of that folder stopped at it: now refused before any training, the folder untouched."""
    logs = tmp_path / "logs"
    shutil.copytree(lane_logs, logs)
    before = sorted(p.name for p in logs.iterdir())
    argv = ["train", "--logs", str(logs), "--epochs", "1", "--members", "1", "--history", "5", "-o", str(logs / "m.pt")]
    line = assert_one_line(*run_cli(argv), "train", logs / "m.curves.csv")
    assert "among the logs it reads" in line
    assert sorted(p.name for p in logs.iterdir()) == before
    code, _ = run_cli([*argv[:-1], str(logs / "sub" / "m.pt")])  # a subfolder is not read as logs: allowed
    assert code == 0 and load_logs(logs)


def test_where_naming_an_unknown_parameter_says_so(lane_logs: Path, tmp_path: Path):
    """Once 'no logs found matching {'y': [3.0]}', as if the value were wrong."""
    code, err = run_cli(["split", "--logs", str(lane_logs), "--where", "y=3", "--out", str(tmp_path / "o")])
    line = assert_one_line(code, err, "split", lane_logs)
    assert "no log has the parameter 'y'" in line and "their parameters: x" in line


def test_where_selects_the_cars_version_parameters_with_its_description(car_logs: Path, tmp_path: Path):
    """The car's kp_steer sits in loops.0.params.kp: ``--where kp_steer=..`` once matched nothing."""
    kept = load_logs(car_logs, load_system("car"), where={"kp_steer": [0.8]})
    assert kept and len(kept) < len(load_logs(car_logs))
    assert {lg.param["loops"][0]["params"]["kp"] for lg in kept} == {0.8}


def test_mixed_control_periods_are_refused_naming_both_logs(lane_logs: Path, tmp_path: Path):
    """One sidecar saying 50 ms among 40 ms ones was once read into one dataset silently."""
    d = tmp_path / "logs"
    shutil.copytree(lane_logs, d)
    side = sorted(d.glob("*.meta.json"))[-1]
    side.write_text(side.read_text().replace('"period_ms": 40.0', '"period_ms": 50.0'))
    code, err = run_cli(["split", "--logs", str(d), "--out", str(tmp_path / "o")])
    assert "mixed control periods" in assert_one_line(code, err, "split", side.with_suffix("").with_suffix(".csv"))


# ----------------------------------------------------------------------------- envi twin generate


@pytest.mark.parametrize(
    "argv, why",
    [
        (["--param", "x=nan"], "non-finite"),  # once 100 rows of NaN, exit 0
        (["--system", "car", "--param", "kp_steer=inf", "kp_speed=20"], "non-finite"),
        (["--system", "car", "--world", "dropout_prob=nan"], "non-finite"),
        (["--runs", "100000000000"], "at most"),  # once a MemoryError traceback
        (["--runs", "0"], "at least 1"),
    ],
)
def test_twin_generate_refuses_bad_values_before_any_work(tmp_path: Path, argv: list[str], why: str):
    out = tmp_path / "o"
    code, err = run_cli(["twin", "generate", *argv, "--out", str(out)])
    lines = [ln for ln in err.splitlines() if ln.strip()]
    assert code == 2 and len(lines) == 1 and why in lines[0], err
    assert not out.exists()


@pytest.mark.parametrize("content", ["not json", '{"speed": "fast", "nosuch": 1}'])
def test_twin_generate_names_a_bad_profile_file(tmp_path: Path, content: str):
    """Once json's bare 'Expecting value: line 1 column 1 (char 0)'."""
    prof = tmp_path / "profile.json"
    prof.write_text(content)
    code, err = run_cli(["twin", "generate", "--profile", str(prof), "--runs", "1", "--out", str(tmp_path / "o")])
    lines = [ln for ln in err.splitlines() if ln.strip()]
    assert code == 2 and len(lines) == 1 and str(prof) in lines[0] and "not a twin profile" in lines[0], err


def test_twin_generate_into_a_file_says_it_is_not_a_folder(tmp_path: Path):
    f = tmp_path / "afile"
    f.write_text("keep me\n")
    for system in ("lane-keeping", "car"):
        code, err = run_cli(["twin", "generate", "--system", system, "--runs", "1", "--steps", "5", "--out", str(f)])
        assert code == 2 and f"--out {f}: exists and is not a folder" in err, err
    assert f.read_text() == "keep me\n"


# ----------------------------------------------------------------------------- train, verify, experiment


@pytest.mark.parametrize(
    "argv, why",
    [
        (["--lr", "-1"], "--lr must be"),  # once torch's 'Invalid learning rate: -1.0'
        (["--lr", "inf"], "--lr must be"),  # once a whole training, then 'damaged model' on saving
        (["--lr", "nan"], "--lr must be"),
        (["--patience", "-1"], "--patience must be at least 0"),  # once a SelectionSettings(...) repr
    ],
)
def test_train_names_the_bad_option(lane_logs: Path, tmp_path: Path, argv: list[str], why: str):
    out = tmp_path / "m.pt"
    code, err = run_cli(["train", "--logs", str(lane_logs), "--epochs", "2", "--quiet", "-o", str(out), *argv])
    assert why in assert_one_line(code, err, "train", argv[0])
    assert not out.exists()


def test_train_into_a_folder_is_refused_before_training(lane_logs: Path, tmp_path: Path):
    """Once found only when saving, naming the temporary file '.m.pt.tmp: Is a directory'."""
    folder = tmp_path / "m.pt"
    folder.mkdir()
    code, err = run_cli(["train", "--logs", str(lane_logs), "--epochs", "2", "--quiet", "-o", str(folder)])
    assert "is a folder" in assert_one_line(code, err, "train", folder)
    assert not any(tmp_path.glob(".*.tmp"))


def test_validation_logs_of_another_system_name_both_sets(lane_logs: Path, car_logs: Path, tmp_path: Path):
    """Once numpy's 'operands could not be broadcast together with shapes (100,4) (2,)'."""
    argv = ["train", "--logs", str(lane_logs), "--val-logs", str(car_logs), "--epochs", "2", "--quiet"]
    code, err = run_cli([*argv, "-o", str(tmp_path / "m.pt")])
    line = assert_one_line(code, err, "train", car_logs)
    assert str(lane_logs) in line and "differ from the training logs'" in line


def test_verify_names_simulations_of_another_system_and_a_negative_skip(
    lane_logs: Path, car_logs: Path, tmp_path: Path
):
    """Once 'no simulated runs for controller lane-keeping(x=30); simulated: combine(...)', naming
    no file; a negative --skip once 'skipping -1 rows ... leaves nothing to score'."""
    code, err = run_cli(["verify", "--real", str(lane_logs), "--sim", str(car_logs)])
    assert "another system" in assert_one_line(code, err, "verify", car_logs)
    code, err = run_cli(["verify", "--real", str(lane_logs), "--sim", str(lane_logs), "--skip", "-1"])
    assert_one_line(code, err, "verify", "--skip must be at least 0")


@pytest.mark.parametrize(
    "argv, why",
    [
        (["--reps", "0"], "--reps must be at least 1"),  # once exit 0 after doing nothing
        (["--n", "0"], "--n must be at least 1"),  # once 'x=30: 6 logs cannot hold 0 training ...'
        (["--n-val", "-1"], "--n-val at least 0"),
        (["--n-test", "1"], "--n-test must be at least 2"),  # once blamed on the number of logs
        (["--workers", "-1"], "--workers must be at least 0"),
        (["--epochs", "0"], "--epochs must be at least 1"),
    ],
)
def test_experiment_refuses_bad_sizes_before_any_job(lane_logs: Path, tmp_path: Path, argv: list[str], why: str):
    out = tmp_path / "exp"
    base = ["experiment", "tovk", "--logs", str(lane_logs), "--tovk-version", "x=30", "--algorithms", "random"]
    code, err = run_cli([*base, "--quiet", "--out", str(out), *argv])
    assert_one_line(code, err, "experiment", why)
    assert not out.exists()


# ----------------------------------------------------------------------------- envi-collect


@pytest.mark.parametrize(
    "argv, why",
    [
        (["--runs", "0"], "--runs must be at least 1"),  # once exit 0 having recorded nothing
        (["--runs", "-3"], "--runs must be at least 1"),
        (["--pings", "0"], "--pings must be at least 1"),
        (["--reconnect", "nan"], "--reconnect is a number of seconds"),
        (["--first-run", "-1"], "--first-run must be at least 0"),
        (["--prefix", "a/b"], "--prefix must be a plain file name prefix"),
    ],
)
def test_collect_refuses_bad_options_before_opening_the_port(tmp_path: Path, argv: list[str], why: str):
    from firmware_bridge.host.collect import main as collect

    err = io.StringIO()
    with contextlib.redirect_stderr(err), pytest.raises(SystemExit) as exc:
        collect(["--port", str(tmp_path / "no-such-port"), "--out", str(tmp_path / "logs"), *argv])
    lines = [ln for ln in err.getvalue().splitlines() if ln.strip()]
    assert exc.value.code == 2 and len(lines) == 1 and why in lines[0], err.getvalue()
    assert not (tmp_path / "logs").exists()


# ----------------------------------------------------------------------------- envi diagnose


@pytest.mark.parametrize(
    "argv, why",
    [
        (["--runs", "0"], "--runs and --top must be at least 1"),  # once 'min() arg is an empty sequence'
        (["--top", "-1"], "--runs and --top must be at least 1"),  # once exit 0
    ],
)
def test_diagnose_refuses_bad_sizes_before_any_stage(
    lane_logs: Path, lane_model: Path, tmp_path: Path, argv: list[str], why: str
):
    out = tmp_path / "d"
    code, err = run_cli(["diagnose", "--model", str(lane_model), "--real", str(lane_logs), "--out", str(out), *argv])
    assert_one_line(code, err, "diagnose", why)
    assert not out.exists()


@pytest.mark.parametrize(
    "argv, why",
    [
        (["--runs", "0"], "--runs must be at least 1"),  # once the whole study ran (a 120 s timeout)
        (["--seeds", "0"], "--seeds must be at least 1"),
        (["--shrink-seeds", "-1"], "--shrink-seeds must be at least 0"),
        (["--lr", "nan"], "--lr must be a positive"),
    ],
)
def test_diagnose_validate_refuses_bad_sizes_before_any_trial(tmp_path: Path, argv: list[str], why: str):
    out = tmp_path / "v"
    code, err = run_cli(["diagnose", "validate", "--out", str(out), *argv])
    assert_one_line(code, err, "diagnose", why)
    assert not out.exists()


@pytest.mark.parametrize(
    "argv, why",
    [
        (["--unseen", "y=3"], "has no version parameter 'y' (its parameters: x)"),  # once 'has no version parameter x'
        (["--unseen", "x=nan"], "non-finite"),  # once simulated, then 'signal color holds NaN'
        (["--delta", "5"], "--delta must lie in (0, 0.5)"),  # once accepted
    ],
)
def test_check_names_a_bad_unseen_version_or_delta(
    lane_logs: Path, lane_model: Path, tmp_path: Path, argv: list[str], why: str
):
    base = ["check", "--model", str(lane_model), "--real", str(lane_logs), "--max-runs", "20", "--batch", "10"]
    code, err = run_cli([*base, "--out", str(tmp_path / "o"), *argv])
    assert_one_line(code, err, "check", why)
    assert not (tmp_path / "o").exists()


def test_a_measured_period_a_little_off_the_nominal_is_not_another_period(lane_logs: Path, tmp_path: Path):
    """Simulated logs record their initial log's measured period (41 ms in a 40 ms dataset)."""
    d = tmp_path / "logs"
    shutil.copytree(lane_logs, d)
    side = sorted(d.glob("*.meta.json"))[-1]
    side.write_text(side.read_text().replace('"period_ms": 40.0', '"period_ms": 41.0'))
    assert len(load_logs(d)) == len(load_logs(lane_logs))


def test_verify_names_real_logs_given_as_simulated_ones(real_dir: Path):
    """Real logs (no sidecar) given as --sim: one line naming a file and what --sim takes, not a
    note about unscored runs followed by an error that names nothing."""
    argv = ["verify", "--real", str(real_dir), "--pattern", "log_{x}_{run}.csv", "--sim", str(real_dir)]
    line = assert_one_line(*run_cli(argv), "verify", real_dir)
    assert "no sidecar" in line and "--sim takes what envi simulate wrote" in line
