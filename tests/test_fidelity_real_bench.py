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

from envi_py.metrics import MetricConfig
from envi_py.model import Checkpoint

BENCH = Path(__file__).resolve().parents[1] / "benchmarks" / "fidelity_real.py"


def load_bench(monkeypatch):
    spec = importlib.util.spec_from_file_location("fidelity_real", BENCH)
    bench = importlib.util.module_from_spec(spec)
    monkeypatch.setitem(sys.modules, "fidelity_real", bench)  # its dataclasses look their module up there
    spec.loader.exec_module(bench)
    return bench


def test_the_headline_interval_resamples_the_trained_models(monkeypatch):
    bench = load_bench(monkeypatch)

    def cells(per_model):
        return [{"per_x": {x: {"kld": v} for x in bench.ALL_X}} for v in per_model]

    same = bench.mean_kld_interval(cells([1.3] * 6))
    assert np.allclose(same, 1.3)  # no spread between models, none in the headline
    lo, hi = bench.mean_kld_interval(cells([1.0, 1.5, 2.0, 16.0, 0.8, 1.2]))
    headline = float(np.exp(np.mean(np.log([1.0, 1.5, 2.0, 16.0, 0.8, 1.2]))))
    assert lo < headline < hi and hi > 2 * lo  # one model at 16 makes a headline from 6 models uncertain
    assert all(math.isnan(v) for v in bench.mean_kld_interval(cells([1.0, 2.0])))  # too few to resample
    assert all(math.isnan(v) for v in bench.mean_kld_interval(cells([1.0, 2.0, math.inf])))


def test_the_smoke_run_scores_every_version_over_several_simulations(real_dir, tmp_path, monkeypatch):
    bench = load_bench(monkeypatch)
    out, kept = tmp_path / "f.json", tmp_path / "models"
    argv = ["--quick", "--sim-seeds", "3", "--data", str(real_dir), "--save-dir", str(kept)]
    assert bench.main([*argv, "--out", str(out)]) == 0
    report = json.loads(out.read_text())
    rows = {r["algorithm"]: r for r in report["summary"]}
    bc = rows["bc-gaussian"]
    ((shape,),) = bc["noise_shapes"]  # one fold, one model
    assert shape in {f"t{nu}" for nu in range(3, 31)}, shape  # lane keeping's description fits Student-t tails
    assert set(rows) == {"random", "bc-gaussian", "bc-gaussian:normal-draws"}
    assert all(math.isnan(v) for v in bc["kld_mean_ci95"])  # one model: no interval, rather than a fake one
    for cell in report["cells"]:
        for x, per in cell["per_x"].items():
            seeds = per["kld_per_sim_seed"]
            assert len(seeds) == 3 and per["runs"] == [10, 10], (cell["algorithm"], x)
            assert math.isclose(per["kld"], float(np.exp(np.mean(np.log(seeds)))), rel_tol=1e-9)
    paired = [c for c in report["cells"] if c["algorithm"].startswith("bc-gaussian")]
    assert paired[0]["train_seconds"] == paired[1]["train_seconds"]  # one training, scored both ways
    assert paired[0]["per_x"]["10"]["kld_per_sim_seed"] != paired[1]["per_x"]["10"]["kld_per_sim_seed"]
    assert report["real_vs_real"]["10"]["shifts"] == 40
    # --save-dir keeps the very model that was scored: reloaded, it scores the same on the same blocks
    assert sorted(p.name for p in kept.iterdir()) == ["bc-gaussian_n3_fold0_seed0.pt", "random_n3_fold0_seed0.pt"]
    args = bench.parse_args(argv)
    by_x = bench.logs_by_version(real_dir, args.history)
    parts = {x: bench.blocks(by_x[x], 0, 1, 3, args.val, args.test, x in bench.TRAIN_X) for x in bench.ALL_X}
    again = bench.score(Checkpoint.load(kept / "bc-gaussian_n3_fold0_seed0.pt"), parts, 0, args, MetricConfig(skip=10))
    assert again[10]["kld_per_sim_seed"] == paired[0]["per_x"]["10"]["kld_per_sim_seed"]


def test_a_seed_ensemble_is_the_folds_models_as_envi_ships_them(real_dir, tmp_path, monkeypatch):
    bench = load_bench(monkeypatch)
    calls = []
    real_simulate = bench.simulate_versions

    def recording(ckpt, logs, **kw):
        calls.append((ckpt, len(logs)))
        return real_simulate(ckpt, logs, **kw)

    monkeypatch.setattr(bench, "simulate_versions", recording)
    out = tmp_path / "e.json"
    argv = ["--algorithms", "bc-gaussian", "--n", "3", "--folds", "1", "--seeds", "2", "--epochs", "2"]
    assert bench.main([*argv, "--ensemble", "--sim-seeds", "1", "--data", str(real_dir), "--out", str(out)]) == 0
    report = json.loads(out.read_text())
    (ens,) = [c for c in report["cells"] if c["algorithm"] == "bc-gaussian:seed-ensemble"]
    assert ens["members"] == 2 and all(per["runs"] == [10, 10] for per in ens["per_x"].values())
    singles = [c for c in report["cells"] if c["algorithm"] == "bc-gaussian"]
    assert ens["train_seconds"] == sum(c["train_seconds"] for c in singles)
    # 2 members and their normal-draw twins: whole test blocks (5 versions x 4); then the ensemble of
    # the two members (one checkpoint, the engine shares each block's runs out between them)
    whole, ensemble = calls[:20], calls[20:]
    assert all(n == 10 for _, n in whole) and [n for _, n in ensemble] == [10] * 5
    trained = {id(ck.model) for ck, _ in whole}
    assert all(ck.size == 2 and len({id(m) for m in ck.members} & trained) == 2 for ck, _ in ensemble)
