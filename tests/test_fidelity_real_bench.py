"""benchmarks/fidelity_real.py in its smoke configuration: the protocol the README's real-log figures
come from (blocks kept apart, several simulations per comparison, a Student-t model paired with its
normal-draw twin) still runs and says what each figure rests on."""

from __future__ import annotations

import importlib.util
import json
import math
import sys
from pathlib import Path

import numpy as np

BENCH = Path(__file__).resolve().parents[1] / "benchmarks" / "fidelity_real.py"


def test_the_smoke_run_scores_every_version_over_several_simulations(real_dir, tmp_path, monkeypatch):
    spec = importlib.util.spec_from_file_location("fidelity_real", BENCH)
    bench = importlib.util.module_from_spec(spec)
    monkeypatch.setitem(sys.modules, "fidelity_real", bench)  # its dataclasses look their module up there
    spec.loader.exec_module(bench)
    out = tmp_path / "f.json"
    assert bench.main(["--quick", "--sim-seeds", "3", "--data", str(real_dir), "--out", str(out)]) == 0
    report = json.loads(out.read_text())
    rows = {r["algorithm"]: r for r in report["summary"]}
    bc = rows["bc-gaussian"]
    (dof,) = bc["noise_dof"]
    assert dof and 3 <= dof[0] <= 30  # lane keeping's description fits Student-t tails
    assert set(rows) == {"random", "bc-gaussian", "bc-gaussian:normal-draws"}
    for cell in report["cells"]:
        for x, per in cell["per_x"].items():
            seeds = per["kld_per_sim_seed"]
            assert len(seeds) == 3 and per["runs"] == [10, 10], (cell["algorithm"], x)
            assert math.isclose(per["kld"], float(np.exp(np.mean(np.log(seeds)))), rel_tol=1e-9)
    paired = [c for c in report["cells"] if c["algorithm"].startswith("bc-gaussian")]
    assert paired[0]["train_seconds"] == paired[1]["train_seconds"]  # one training, scored both ways
    assert paired[0]["per_x"]["10"]["kld_per_sim_seed"] != paired[1]["per_x"]["10"]["kld_per_sim_seed"]
    assert report["real_vs_real"]["10"]["shifts"] == 40
