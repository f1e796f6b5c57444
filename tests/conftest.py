"""Shared fixtures: where the real lane-keeping logs live and small helpers to build logs."""

from __future__ import annotations

import os
from pathlib import Path

# One BLAS thread: on a loaded 2-core machine OpenBLAS's threads thrash (a 1536x45 lstsq in the
# diagnosis took 0.47 s instead of 4 ms); set before numpy loads its BLAS.
os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

import numpy as np  # noqa: E402
import pytest  # noqa: E402

from envi_py.logs import Log, LogMeta, load_logs
from envi_py.system import lane_keeping

REAL_DATA = Path(__file__).resolve().parents[1].parent / "shared" / "data" / "lane-keeping-fot"
REAL_PATTERN = "log_{x}_{run}.csv"


@pytest.fixture(scope="session")
def real_dir() -> Path:
    if not REAL_DATA.is_dir():
        pytest.skip(f"real lane-keeping logs not found at {REAL_DATA}")
    return REAL_DATA


@pytest.fixture(scope="session")
def real_logs(real_dir: Path) -> list[Log]:
    return load_logs(real_dir, lane_keeping().with_pattern(REAL_PATTERN), min_length=11)


def make_log(color: np.ndarray, x: float = 30.0, period: float = 40.0, run: str = "r") -> Log:
    """A lane-keeping log whose angles follow the controller exactly."""
    color = np.asarray(color, dtype=float)
    angle = np.sign(color - 40.0) * x
    meta = LogMeta(controller={"name": "lane-keeping", "params": {"x": x}}, period_ms=period, run_id=run)
    return Log(None, np.arange(len(color)) * period, color[:, None], angle[:, None], meta)


@pytest.fixture(scope="module")
def mini(tmp_path_factory: pytest.TempPathFactory) -> dict[str, Path]:
    """4 lane twin logs (x = 30), a small BC model trained on them in seconds, and its ONNX export:
    enough for a command to run end to end where what is checked is its inputs and outputs."""
    from envi_py.controllers import ControllerSpec
    from envi_py.export import export
    from envi_py.train import train
    from envi_py.twin import generate, write_logs

    d = tmp_path_factory.mktemp("mini_lane")
    logs = d / "logs"
    write_logs(generate(ControllerSpec("lane-keeping", {"x": 30}), 4, 40, seed=1), logs)
    ckpt = train("bc", load_logs(logs), [], epochs=2, hidden=(8, 8), history=5, seed=0, members=1)
    ckpt.save(d / "m.pt")
    return {"dir": d, "logs": logs, "model": d / "m.pt", "onnx": export(ckpt, d / "m.onnx")}


@pytest.fixture(scope="module")
def car_dir(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """Car twin logs: 2 runs of 2 versions (for the commands' options, not for fidelity)."""
    from envi_py.twin.car import generate_car_versions, write_car_logs

    out = tmp_path_factory.mktemp("car")
    write_car_logs(generate_car_versions(2, seed=1, versions=[0, 2]), out)
    return out
