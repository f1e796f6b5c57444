"""Run files: options from a TOML file, checked as the command line checks them, and written back."""

from __future__ import annotations

import json

import pytest

from envi_py.cli import main
from envi_py.twin.car import generate_car_versions, write_car_logs


@pytest.fixture()
def logs_dir(tmp_path):
    write_car_logs(generate_car_versions(3, versions=[0, 1]), tmp_path / "logs")
    return tmp_path / "logs"


def write(path, text):
    path.write_text(text)
    return path


def test_a_run_file_gives_the_options_and_the_written_one_repeats_the_run(tmp_path, logs_dir, capsys):
    run = write(
        tmp_path / "run.toml",
        f'[split]\nlogs = ["{logs_dir}"]\nsystem = "car"\ntrain = 2\ntest = 1\nout = "{tmp_path / "a"}"\n',
    )
    assert main(["split", "--config", str(run)]) == 0  # --logs is required, and given by the file
    written = tmp_path / "a" / "run.toml"
    assert "effective configuration" in capsys.readouterr().out and written.exists()
    text = written.read_text()
    assert "[split]" in text and "train = 2" in text and 'mode = "random"' in text  # defaults too
    first = json.loads((tmp_path / "a" / "test.json").read_text())
    # the written file alone repeats the run (into another folder, given on the command line)
    assert main(["split", f"--config={written}", "--out", str(tmp_path / "b")]) == 0
    assert json.loads((tmp_path / "b" / "test.json").read_text())["logs"] == first["logs"]


def test_the_command_line_wins_over_the_file(tmp_path, logs_dir):
    run = write(tmp_path / "run.toml", f'[split]\nlogs = ["{logs_dir}"]\nsystem = "car"\ntrain = 2\ntest = 1\n')
    assert main(["--config", str(run), "split", "--test", "2", "--train", "1", "--out", str(tmp_path / "s")]) == 0
    assert len(json.loads((tmp_path / "s" / "test.json").read_text())["logs"]) == 4  # 2 per version


@pytest.mark.parametrize(
    "table, says",
    [
        ("[split]\ntrian = 2\n", "[split] has no option 'trian'"),
        ('[split]\ntrain = "many"\n', "[split] train: "),
        ('[split]\nmode = "sideways"\n', "is not one of random, blocks"),
        ("[split]\ntotal = 1\n", "must be true or false"),
        ("[split]\ntrain = true\n", "[split] train: True is not a value this option takes"),
        ("[split]\npattern = false\n", "[split] pattern: False is not a value"),
        ("[train]\nepochs = 3\n", "no [split] table"),
        ("[split\n", "a run file is not valid TOML"),
    ],
)
def test_a_bad_run_file_is_one_line_naming_it(tmp_path, logs_dir, capsys, table, says):
    run = write(tmp_path / "run.toml", table)
    assert main(["split", "--logs", str(logs_dir), "--config", str(run)]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and str(run) in err[0] and says in err[0], err


def test_a_missing_run_file_is_one_line(tmp_path, capsys):
    assert main(["split", "--config", str(tmp_path / "none.toml")]) == 2
    assert "no such run file" in capsys.readouterr().err
