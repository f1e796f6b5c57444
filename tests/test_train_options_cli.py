"""`envi train` options for closed-loop stability: --residual, --multistep, --input-noise."""

from __future__ import annotations

import pytest

from envi_py.cli import main
from envi_py.model import Checkpoint
from envi_py.twin.car import generate_car_versions, write_car_logs


@pytest.fixture(scope="module")
def car_dir(tmp_path_factory):
    out = tmp_path_factory.mktemp("car")
    write_car_logs(generate_car_versions(2, seed=1, versions=[0, 2]), out)
    return out


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
    ],
)
def test_bad_values_are_one_line_and_exit_code_2(car_dir, tmp_path, capsys, extra, message):
    argv = ["train", "--logs", str(car_dir), "--system", "car", "--epochs", "1", "-o", str(tmp_path / "m.pt")]
    assert main([*argv, *extra]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and message in err[0]
