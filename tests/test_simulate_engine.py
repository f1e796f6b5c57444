"""``simulate_logs`` and ``envi simulate`` on either engine: the choice, its errors, and agreement."""

from __future__ import annotations

import numpy as np
import pytest

from envi_py import native
from envi_py.controllers import ControllerSpec
from envi_py.simulate import choose_engine, simulate_logs

from .conftest import make_log
from .test_export import paper_ckpt

LANE = ControllerSpec("lane-keeping", {"x": 30})


def init_logs(n: int = 3) -> list:
    rng = np.random.default_rng(1)
    return [make_log(np.clip(40 + np.cumsum(rng.normal(0, 6, 40)), 0, 100), run=f"r{i}") for i in range(n)]


def test_torch_is_always_possible_and_unknown_engines_are_refused():
    assert choose_engine(paper_ckpt(), LANE, "torch") == "torch"
    with pytest.raises(ValueError, match="unknown engine 'gpu'"):
        choose_engine(paper_ckpt(), LANE, "gpu")


def test_auto_falls_back_to_torch_where_native_cannot_run_and_native_says_why():
    plugin = ControllerSpec("tests.test_simulate_engine:steer", {})
    assert choose_engine(paper_ckpt(), plugin, "auto") == "torch"
    with pytest.raises(ValueError, match="not a registered one" if native.available() else "not built"):
        choose_engine(paper_ckpt(), plugin, "native")
    phase = paper_ckpt(extras=("phase",))
    assert choose_engine(phase, LANE, "auto") == "torch"


@pytest.mark.skipif(not native.available(), reason="native engine not built")
def test_native_and_torch_simulate_the_same_logs():
    ck, logs = paper_ckpt(), init_logs()
    assert choose_engine(ck, LANE, "auto") == "native"
    a = simulate_logs(ck, LANE, logs, runs=2, engine="native")
    b = simulate_logs(ck, LANE, logs, runs=2, engine="torch")
    assert [lg.meta.run_id for lg in a] == [lg.meta.run_id for lg in b]
    assert {lg.meta.provenance["engine"] for lg in a} == {"native"}
    assert {lg.meta.provenance["engine"] for lg in b} == {"torch"}
    for x, y in zip(a, b):
        np.testing.assert_array_equal(x.time, y.time)
        np.testing.assert_allclose(x.values, y.values, atol=1e-4, rtol=0)


def steer(states: np.ndarray) -> np.ndarray:
    """A user's controller given by import path (the native engine cannot run it)."""
    return np.where(states[:, :1] > 40, 20.0, -20.0)


def test_a_model_told_the_interval_is_simulated_with_intervals_like_the_real_ones():
    """Training records the quantiles of the real intervals; simulation draws the ``dt`` channel
    from them (seeded), instead of pretending every period is the nominal one."""
    import torch

    from envi_py.simulate import rollout
    from envi_py.train.common import model_config, new_checkpoint

    rng = np.random.default_rng(0)
    logs = init_logs(4)
    for lg in logs:  # 40 ms plus an exponential extra of mean 10 ms, as a jittery brick
        lg.time = np.concatenate([[0.0], np.cumsum(40 + np.floor(rng.exponential(10, len(lg) - 1)))])
    ck = new_checkpoint("bc", logs, [], model_config(logs, history=10, hidden=(8,), extras=("dt",)), 0, {})
    q = np.asarray(ck.config.intervals)
    assert ck.record.period_ms == pytest.approx(np.median([np.median(np.diff(lg.time)) for lg in logs]))
    assert len(q) == 101 and np.all(np.diff(q) >= 0) and q[-1] > 0.5
    rows = ck.encode_rows(np.repeat(logs[0].values[None, :1], 4000, axis=0), 0, np.random.default_rng(1))
    drawn = rows[:, 0, -1]
    real = np.concatenate([np.diff(lg.time) for lg in logs]) / ck.record.period_ms - 1
    assert abs(drawn.mean() - real.mean()) < 0.03 and abs(drawn.std() - real.std()) < 0.03
    seen = []
    original = ck.model.step
    ck.model.step = lambda x, gen=None: (seen.append(x[:, -1].clone()), original(x, gen))[1]
    a = rollout(ck, LANE, np.stack([lg.values[:10] for lg in logs]), 30, runs=2, seed=5)
    b = rollout(ck, LANE, np.stack([lg.values[:10] for lg in logs]), 30, runs=2, seed=5)
    np.testing.assert_array_equal(a, b)
    assert torch.cat(seen).std() > 0.1  # the interval input varies in simulation, it is not the nominal 0


def test_mean_mode_is_the_gaussian_models_mean_and_draws_nothing():
    """--mean: a Gaussian model simulated by its mean equals the same weights with a deterministic
    head, whatever the seed, and differs from its sampled runs."""
    gauss, logs = paper_ckpt("gaussian"), init_logs()
    det = paper_ckpt("deterministic")  # same seed: the same trunk and mean head
    det.model.load_state_dict({k: v for k, v in gauss.model.state_dict().items() if not k.startswith("log_std")})
    a = simulate_logs(gauss, LANE, logs, runs=2, seed=1, mean=True)
    b = simulate_logs(gauss, LANE, logs, runs=2, seed=2, mean=True)
    plain = simulate_logs(det, LANE, logs, runs=2)
    sampled = simulate_logs(gauss, LANE, logs, runs=2, seed=1)
    for x, y, z, s in zip(a, b, plain, sampled):
        np.testing.assert_array_equal(x.values, y.values)
        np.testing.assert_array_equal(x.values, z.values)
        assert not np.array_equal(x.values, s.values)
    assert all(lg.meta.provenance["mean"] is True for lg in a)
    assert "mean" not in sampled[0].meta.provenance


@pytest.mark.skipif(not native.available(), reason="native engine not built")
def test_native_mean_mode_agrees_with_torch_and_leaves_the_model_stochastic():
    gauss, logs = paper_ckpt("gaussian"), init_logs()
    assert choose_engine(gauss, LANE, "auto", mean=True) == "native"
    a = simulate_logs(gauss, LANE, logs, engine="native", mean=True)
    b = simulate_logs(gauss, LANE, logs, engine="torch", mean=True)
    for x, y in zip(a, b):
        np.testing.assert_allclose(x.values, y.values, atol=1e-4, rtol=0)
    assert gauss.config.head == "gaussian" and gauss.model.log_std is not None


def test_mean_mode_of_the_random_baseline_is_refused():
    from envi_py.simulate import rollout

    rand = paper_ckpt()
    rand.config.kind = "random"
    init = np.stack([lg.values[:10] for lg in init_logs(1)])
    with pytest.raises(ValueError, match="random baseline has no mean"):
        rollout(rand, LANE, init, 5, mean=True)


def test_envi_simulate_mean_writes_identical_runs_and_says_so(tmp_path, capsys):
    from envi_py.cli import main
    from envi_py.logs import read_log, write_log

    model = tmp_path / "m.pt"
    paper_ckpt("gaussian").save(model)
    for lg in init_logs(2):
        write_log(lg, tmp_path / "init" / f"{lg.meta.run_id}.csv")
    out = tmp_path / "sim"
    args = ["simulate", "--model", str(model), "--init-logs", str(tmp_path / "init"), "--runs", "2", "--mean"]
    assert main([*args, "--out", str(out)]) == 0
    assert "engine" in capsys.readouterr().out
    runs = sorted(out.glob("*.csv"))
    assert len(runs) == 4
    first, second = read_log(runs[0]), read_log(runs[1])  # r0-sim0, r0-sim1: the same mean trajectory
    np.testing.assert_array_equal(first.values, second.values)
    assert first.meta.provenance["mean"] is True
