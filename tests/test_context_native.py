"""A model with a run context (sigma_0's per-state mean and spread as an input all run long) on both
engines: the export that carries it, the C++ engine (cpp/src/engine.cpp, Model::context) against the
PyTorch rollout, and the loader's check of its metadata."""

from __future__ import annotations

import json
import subprocess

import numpy as np
import pytest
import torch

from envi_py import native
from envi_py.export import export, read_metadata, to_onnx
from envi_py.logs import load_logs, read_log
from envi_py.simulate import initial_windows, rollout
from envi_py.system import lane_keeping

from .test_export import paper_ckpt, with_metadata
from .test_native import LANE, PID, envi_sim, windows

pytestmark = pytest.mark.skipif(not native.available(), reason="native engine not built")


def _context_ckpt(**cfg):
    """The paper's structure with a run context whose input columns weigh as much as the window's."""
    ck = paper_ckpt(context=True, **cfg)
    with torch.no_grad():
        first = ck.model.body[0].weight
        first[:, -ck.config.context_dim :] *= 5  # random init makes them small: the test must see them
    return ck


@pytest.mark.parametrize("spec", [LANE, PID], ids=["lane-keeping", "pid"])
@pytest.mark.parametrize("residual", [False, True], ids=["plain-head", "residual-head"])
def test_a_context_model_runs_alike_on_both_engines(spec, residual):
    ck = _context_ckpt(residual=residual)
    init = windows(6)
    want = rollout(ck, spec, init, 80, runs=2)
    got = native.rollout(ck, spec, init, 80, runs=2, threads=2)
    np.testing.assert_array_equal(got[:, :10], want[:, :10])
    # a residual mean is the last reading plus a change, rounded in float32 at each step: over 80 closed-
    # loop steps that drifts up to a few 1e-4 (test_residual_export allows 1e-3 for the same reason)
    np.testing.assert_allclose(got, want, atol=1e-3 if residual else 1e-4, rtol=0)
    without = _context_ckpt(residual=residual)
    with torch.no_grad():
        without.model.body[0].weight[:, -ck.config.context_dim :] = 0
    assert not np.allclose(want, rollout(without, spec, init, 80, runs=2), atol=1e-2), (
        "the context changed nothing: an engine that ignored it would pass"
    )


def test_the_engine_takes_a_context_model_and_its_draws_stay_put_across_threads():
    ck = _context_ckpt(head="gaussian")
    assert native.unsupported(ck, LANE) is None
    one = native.rollout(ck, LANE, windows(5), 60, runs=7, threads=1, seed=3)
    two = native.rollout(ck, LANE, windows(5), 60, runs=7, threads=2, seed=3)
    np.testing.assert_array_equal(one, two)


def test_the_export_declares_the_context_and_the_loader_checks_it():
    ck = _context_ckpt()
    model = to_onnx(ck)
    assert model.graph.input[0].type.tensor_type.shape.dim[1].dim_value == ck.config.in_features
    meta = {p.key: p.value for p in model.metadata_props}
    assert meta["envi.context"] == "true"
    with pytest.raises(ValueError, match="'envi.context' must be true or false"):
        native.load(with_metadata(ck, "envi.context", "yes"))
    # a file that says it has no context has a first layer too wide for the window: refused by shape
    with pytest.raises(ValueError, match="expects 22 inputs but gets 20"):
        native.load(with_metadata(ck, "envi.context", False))


def test_a_plain_export_says_it_has_no_context(tmp_path):
    path = export(paper_ckpt(), tmp_path / "m.onnx")
    assert read_metadata(path)["envi.context"] is False


@pytest.mark.skipif(envi_sim() is None, reason="envi_sim binary not built")
def test_envi_sim_runs_a_context_model_like_pytorch(tmp_path, real_dir):
    ck = _context_ckpt()
    model = export(ck, tmp_path / "m.onnx")
    files = [real_dir / "log_10_0.csv", real_dir / "log_50_3.csv"]  # sigma_0 of two different runs
    spec = json.dumps(LANE.to_json())
    subprocess.run(
        [envi_sim(), "--model", str(model), "--init", *map(str, files), "--controller", spec, "--steps", "40"]
        + ["--out", str(tmp_path / "sim")],
        check=True,
    )
    real = load_logs(files, lane_keeping().with_pattern("log_{x}_{run}.csv"))
    want = rollout(ck, LANE, initial_windows(real, 10), 40)
    logs = [read_log(tmp_path / "sim" / f"{f.stem}-sim0.csv") for f in files]
    for lg, tr in zip(logs, want, strict=True):
        np.testing.assert_allclose(lg.values, tr, atol=1e-4, rtol=0)  # the binary may use another ISA build
