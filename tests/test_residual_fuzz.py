"""Fuzz the native loader on residual models: the ``residual.*`` nodes, their int64 constants and the
``envi.residual`` metadata, mutated as tests/fuzz_loader_test.py mutates plain models, under
AddressSanitizer and UBSan. A mutation must be rejected with a ModelError or run cleanly."""

from __future__ import annotations

import os
import re
import subprocess

import numpy as np
import torch

from envi_py.dataset import Normaliser
from envi_py.export import to_onnx
from envi_py.model import Checkpoint, EnvModel, ModelConfig, TrainingRecord
from envi_py.system import LogSchema
from envi_py.twin.car import generate_car_versions

from .fuzz_loader_test import harness, mutate  # noqa: F401 - harness is a fixture
from .test_export import paper_ckpt

N_FILES = 400


def residual_seeds() -> list[bytes]:
    """Residual exports: the lane model (a Slice base) deterministic and Gaussian, and a two-state
    model with a saturating second state (the Gather/ArgMax base, an event head)."""
    out = [
        to_onnx(paper_ckpt(head, residual=True, hidden=(8, 8))).SerializeToString()
        for head in ("deterministic", "gaussian")
    ]
    torch.manual_seed(3)
    car = generate_car_versions(1, steps=12, seed=0, versions=[0])[0].meta.schema
    schema = LogSchema(states=car.states, actions=car.actions[:1])  # the harness drives one action (a PID)
    cfg = ModelConfig(
        n_state=2, n_action=1, history=3, hidden=(8,), head="gaussian", residual=True, limit_events=((1, 255.0),)
    )
    norm = Normaliser(np.array([0.0, 0.0, -90.0]), np.array([100.0, 255.0, 90.0]))
    ckpt = Checkpoint(EnvModel(cfg).eval(), norm, schema, TrainingRecord("bc", 0))
    ckpt.fit_limit_levels()
    out.append(to_onnx(ckpt).SerializeToString())
    return out


def test_corrupted_residual_models_never_crash_the_loader(harness, tmp_path):  # noqa: F811
    rng = np.random.default_rng(20261124)
    base = residual_seeds()
    files = []
    for i, seed in enumerate(base):  # the valid seeds must load and run
        files.append(tmp_path / f"seed{i}.onnx")
        files[-1].write_bytes(seed)
    for i in range(N_FILES):
        files.append(tmp_path / f"m{i:04d}.onnx")
        files[-1].write_bytes(mutate(base[i % len(base)], rng, base))
    env = dict(
        os.environ,
        ASAN_OPTIONS="detect_leaks=1:halt_on_error=1:abort_on_error=0",
        UBSAN_OPTIONS="halt_on_error=1:print_stacktrace=1",
    )
    seeds_only = subprocess.run([str(harness), *map(str, files[: len(base)])], capture_output=True, text=True, env=env)
    assert f"loaded {len(base)}, rejected 0" in seeds_only.stdout, seeds_only.stdout + seeds_only.stderr[-2000:]
    res = subprocess.run([str(harness), *map(str, files)], capture_output=True, text=True, env=env, timeout=900)
    assert res.returncode == 0, res.stderr[-4000:]
    assert "runtime error" not in res.stderr and "AddressSanitizer" not in res.stderr
    total, loaded, rejected = map(int, re.findall(r"\d+", res.stdout))
    assert total == N_FILES + len(base)
    assert rejected > N_FILES // 2 and loaded >= len(base)
