"""``envi train --algorithm gail`` finishes without warnings: with one epoch the validation-error panel
of GAIL's curves has no finite point, and ``legend()`` on it once printed matplotlib's 'No artists
with labels found to put in legend' on every successful training."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

from envi_py.controllers import ControllerSpec
from envi_py.twin import generate, write_logs

ROOT = Path(__file__).resolve().parents[1]


def test_gail_training_of_one_epoch_prints_no_warning(tmp_path: Path):
    logs = tmp_path / "logs"
    write_logs(generate(ControllerSpec("lane-keeping", {"x": 30}), 3, 60, seed=4), logs)
    model = tmp_path / "g.pt"
    argv = ["train", "--logs", str(logs), "--algorithm", "gail", "--epochs", "1", "--quiet", "-o", str(model)]
    # Python's default filters, as a user's shell has them (matplotlib's UserWarning shows under them)
    env = {k: v for k, v in os.environ.items() if k != "PYTHONWARNINGS"}
    done = subprocess.run(
        [sys.executable, "-m", "envi_py.cli", *argv], cwd=ROOT, env=env, capture_output=True, text=True, timeout=600
    )
    assert done.returncode == 0, done.stderr
    assert "trained gail" in done.stdout and model.is_file()
    assert "Warning" not in done.stderr and done.stderr.strip() == "", done.stderr
