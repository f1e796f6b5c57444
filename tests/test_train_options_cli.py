"""`envi train` options for closed-loop stability: --residual, --multistep, --input-noise, and the
defaults a system description's ``[training]`` table gives them."""

from __future__ import annotations

import re

import pytest

from envi_py.cli import main
from envi_py.logs import load_logs
from envi_py.model import Checkpoint
from envi_py.system import SHIPPED_DIR, TrainingDefaults, load_system
from envi_py.twin.car import generate_car_versions, write_car_logs


def test_the_options_reach_the_checkpoint(car_dir, tmp_path):
    out = tmp_path / "m.pt"
    argv = ["train", "--logs", str(car_dir), "--system", "car", "--epochs", "1", "--hidden", "8", "--quiet"]
    assert main([*argv, "--residual", "--multistep", "2", "--input-noise", "0.5", "-o", str(out)]) == 0
    ck = Checkpoint.load(out)
    assert ck.config.residual and ck.config.plain
    assert ck.record.hyper["multistep"] == 2 and ck.record.hyper["input_noise"] == 0.5


@pytest.mark.parametrize(
    "extra, message",
    [
        (["--input-noise", "nan"], "--input-noise is a multiple of the typical step"),
        (["--multistep", "-1"], "--multistep is a number of steps"),
        (["--algorithm", "gail", "--multistep", "3"], "behaviour-cloning losses, not gail's"),
        (["--algorithm", "gail", "--head", "deterministic"], "gail trains a Gaussian policy"),
        (["--algorithm", "gail", "--residual", "--head", "deterministic"], "gail trains a Gaussian policy"),
    ],
)
def test_bad_values_are_one_line_and_exit_code_2(car_dir, tmp_path, capsys, extra, message):
    argv = ["train", "--logs", str(car_dir), "--system", "car", "--epochs", "1", "-o", str(tmp_path / "m.pt")]
    assert main([*argv, *extra]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and message in err[0]


def test_the_system_description_sets_the_defaults_and_the_command_line_wins(car_dir, tmp_path):
    """The car's [training] (residual head, input noise 0.5) applies to a plain `envi train` on its logs,
    also without --system (twin logs carry sidecars); --no-residual / --input-noise override it; lane
    keeping's description sets neither (its Student-t step noise: tests/test_step_noise.py); a
    deterministic BC head is still allowed."""
    base = ["train", "--logs", str(car_dir), "--epochs", "1", "--hidden", "8", "--quiet"]
    for extra, residual, noise in (
        ([], True, 0.5),
        (["--system", "car"], True, 0.5),
        (["--no-residual", "--input-noise", "0"], False, 0.0),
        (["--head", "deterministic"], True, 0.5),
    ):
        out = tmp_path / f"m{len(extra)}.pt"
        assert main([*base, *extra, "-o", str(out)]) == 0, extra
        ck = Checkpoint.load(out)
        assert ck.config.residual is residual and ck.record.hyper["input_noise"] == noise, extra
    car = TrainingDefaults(residual=True, input_noise=0.5, select_runs=10, lr_schedule="cosine")
    assert load_system("car").training == car
    lane = TrainingDefaults(step_noise="student-t", members=3, hidden=(128, 128))
    assert load_system("lane-keeping").training == lane
    assert lane.for_algorithm("gail") == {"step_noise": "student-t"}  # members and widths: measured for BC
    assert TrainingDefaults(True, 0.5).for_algorithm("gail") == {"residual": True}  # input noise is BC's loss
    assert TrainingDefaults(True, 0.5).for_algorithm("random") == {}


@pytest.mark.parametrize(
    "line, bad, message",
    [
        ("residual = true", "residual = 1", "residual must be true or false"),
        ("input_noise = 0.5", "input_noise = -0.5", "input_noise must be a multiple of the typical step in 0..100"),
        ("input_noise = 0.5", "input_noise = nan", "input_noise must be a multiple of the typical step in 0..100"),
        ("residual = true", "residuals = true", "unknown key 'residuals' (did you mean 'residual'?"),
        ("input_noise = 0.5", 'input_noise = 0.5\nstep_noise = "laplace"', "step_noise must be one of gaussian"),
        ("input_noise = 0.5", 'input_noise = 0.5\ncontext = "yes"', "context must be true or false"),
        ("input_noise = 0.5", "input_noise = 0.5\nhidden = 128", "hidden must be a list of widths"),
        ("input_noise = 0.5", "input_noise = 0.5\nhidden = [128, 0]", "hidden must be a list of widths"),
        ("input_noise = 0.5", "input_noise = 0.5\nhidden = [true]", "hidden must be a list of widths"),
        ("input_noise = 0.5", "input_noise = 0.5\nhidden = []", "hidden must be a list of widths"),
        ("select_runs = 10", "select_runs = 0", "select_runs must be a whole number in 1..1000"),
        ("select_runs = 10", "select_runs = 2.5", "select_runs must be a whole number in 1..1000"),
        ("select_runs = 10", "select_runs = true", "select_runs must be a whole number in 1..1000"),
    ],
)
def test_a_bad_training_table_is_refused_naming_the_file(tmp_path, line, bad, message):
    text = (SHIPPED_DIR / "car.toml").read_text().replace(line, bad)
    path = tmp_path / "car.toml"
    path.write_text(text)
    with pytest.raises(ValueError, match=re.escape(message)) as err:
        load_system(path)
    assert str(path) in str(err.value)


def test_a_description_asks_for_a_run_context_and_the_command_line_wins(car_dir, tmp_path):
    """``[training] context = true`` gives every learnt model sigma_0's context; --no-context and
    --context override the description either way."""
    text = (SHIPPED_DIR / "car.toml").read_text().replace("input_noise = 0.5", "input_noise = 0.5\ncontext = true")
    desc = tmp_path / "car.toml"
    desc.write_text(text)
    assert load_system(desc).training.for_algorithm("bcxgail") == {"residual": True, "context": True}
    base = ["train", "--logs", str(car_dir), "--epochs", "1", "--hidden", "8", "--quiet"]
    for extra, context in (([], True), (["--no-context"], False), (["--system", "car", "--context"], True)):
        out = tmp_path / f"m{len(extra)}.pt"
        argv = [*base, *(extra if "--system" in extra else ["--system", str(desc), *extra]), "-o", str(out)]
        assert main(argv) == 0, extra
        assert Checkpoint.load(out).config.context is context, extra
    assert load_system("car").training.context is False


def test_the_descriptions_hidden_widths_apply_and_the_command_line_wins(tmp_path):
    """Lane keeping's [training] hidden = [128, 128] shapes a plain BC training on its logs (twin logs:
    their sidecars name the system); --hidden overrides it."""
    from envi_py.controllers import ControllerSpec
    from envi_py.twin import generate, write_logs

    logs = tmp_path / "lane"
    write_logs(generate(ControllerSpec("lane-keeping", {"x": 30}), 2, 30, seed=0), logs)
    base = ["train", "--logs", str(logs), "--epochs", "1", "--members", "1", "--quiet"]
    for extra, widths in (([], (128, 128)), (["--hidden", "8,4"], (8, 4))):
        assert main([*base, *extra, "-o", str(tmp_path / "m.pt")]) == 0
        assert Checkpoint.load(tmp_path / "m.pt").config.hidden == widths


def test_the_descriptions_validation_runs_apply_and_the_command_line_wins(car_dir, tmp_path):
    """The car's [training] select_runs = 10 sets the simulated runs per validation log of a training on
    its logs (API and command line); --select-runs overrides it, and lane keeping keeps the trainer's 5."""
    from envi_py.train import train

    logs = load_logs(car_dir)
    ck = train("bc", logs[:2], logs[2:4], system=load_system("car"), epochs=1, hidden=(8,), eval_every=1)
    assert ck.record.selection["settings"]["runs"] == 10
    val = tmp_path / "val"
    write_car_logs(generate_car_versions(1, seed=2, versions=[0]), val)
    base = ["train", "--logs", str(car_dir), "--val-logs", str(val), "--epochs", "1", "--hidden", "8", "--quiet"]
    for extra, runs in (([], 10), (["--select-runs", "3"], 3)):
        out = tmp_path / f"m{len(extra)}.pt"
        assert main([*base, *extra, "-o", str(out)]) == 0, extra
        assert Checkpoint.load(out).record.selection["settings"]["runs"] == runs, extra
    assert load_system("lane-keeping").training.select_runs is None
