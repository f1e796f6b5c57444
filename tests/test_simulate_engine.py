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
