"""Fuzz the native model loader: hundreds of corrupted ONNX files under AddressSanitizer and UBSan.

The harness (cpp/tests/fuzz_loader.cpp) is compiled here with g++ and the sanitizers, fed seeded
mutations of real exports (bit flips, overwritten and inserted bytes, truncations, splices), and
must reject or run each one without a sanitizer report. Seeded, so a failure reproduces.
"""

from __future__ import annotations

import os
import re
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import torch

from envi_py.dataset import Normaliser
from envi_py.export import to_onnx
from envi_py.logs import LANE_KEEPING_SCHEMA
from envi_py.model import Checkpoint, EnvModel, ModelConfig, TrainingRecord

ROOT = Path(__file__).resolve().parents[1]
CPP = ROOT / "cpp"


def eigen_include() -> Path | None:
    """Eigen's headers: the pinned cmeel-eigen wheel that ./dev.sh installs (the engine's own build uses
    it too, cpp/cmake/EnviEigen.cmake), else a system libeigen3-dev; None when neither is there."""
    # `python -m cmeel cmake` lists the prefixes of the installed cmeel wheels (nothing when there are none)
    out = subprocess.run([sys.executable, "-m", "cmeel", "cmake"], capture_output=True, text=True).stdout
    candidates = [Path(p) / "include" / "eigen3" for p in out.strip().split(os.pathsep) if p]
    candidates.append(Path("/usr/include/eigen3"))
    return next((c for c in candidates if (c / "Eigen" / "Core").exists()), None)


EIGEN = eigen_include()
N_FILES = 600


def seeds() -> list[bytes]:
    out = []
    for head, extra in [("deterministic", {}), ("gaussian", {"round_to": (1.0,)}), ("deterministic", {"history": 2})]:
        torch.manual_seed(len(out))
        cfg = ModelConfig(n_state=1, n_action=1, hidden=(8, 8), head=head, **extra)
        norm = Normaliser(np.array([5.0, -30.0]), np.array([80.0, 30.0]))
        ck = Checkpoint(EnvModel(cfg).eval(), norm, LANE_KEEPING_SCHEMA, TrainingRecord("bc", 0))
        out.append(to_onnx(ck).SerializeToString())
    return out


def mutate(data: bytes, rng: np.random.Generator, others: list[bytes]) -> bytes:
    b = bytearray(data)
    kind = rng.integers(6)
    if kind == 0:  # flip a few bits
        for _ in range(rng.integers(1, 9)):
            i = rng.integers(len(b))
            b[i] ^= 1 << rng.integers(8)
    elif kind == 1:  # overwrite bytes (lengths and tags become garbage)
        for _ in range(rng.integers(1, 5)):
            b[rng.integers(len(b))] = int(rng.choice([0x00, 0x7F, 0x80, 0xFF, rng.integers(256)]))
    elif kind == 2:  # truncate
        b = b[: rng.integers(len(b))]
    elif kind == 3:  # insert random bytes
        i = rng.integers(len(b))
        b[i:i] = rng.integers(0, 256, rng.integers(1, 16)).astype(np.uint8).tobytes()
    elif kind == 4:  # splice two files
        o = others[rng.integers(len(others))]
        b = b[: rng.integers(len(b))] + o[rng.integers(len(o)) :]
    else:  # corrupt the metadata text (JSON the loader parses)
        i = bytes(b).find(b"envi.", rng.integers(len(b) // 2))
        if i >= 0:
            for _ in range(rng.integers(1, 4)):
                j = min(len(b) - 1, i + int(rng.integers(0, 120)))
                b[j] = int(rng.choice(list(b'{}[]",:0-9eE\x00\\')))
    return bytes(b)


@pytest.fixture(scope="module")
def harness(tmp_path_factory) -> Path:
    gxx = shutil.which("g++")
    if gxx is None or EIGEN is None:
        pytest.skip("g++ and Eigen (the cmeel-eigen wheel or libeigen3-dev) are needed to build the fuzz harness")
    exe = tmp_path_factory.mktemp("fuzz") / "fuzz_loader"
    sources = [CPP / "tests" / "fuzz_loader.cpp"] + sorted((CPP / "src").glob("*.cpp"))
    sources = [s for s in sources if s.name not in ("pymodule.cpp", "envi_sim.cpp", "csvlog.cpp")]
    cmd = [
        gxx,
        "-std=c++17",
        "-O1",
        "-g",
        "-fsanitize=address,undefined",
        "-fno-sanitize-recover=all",
        "-fno-omit-frame-pointer",
        "-DEIGEN_DONT_PARALLELIZE",
        f"-I{CPP / 'include'}",
        f"-I{EIGEN}",
        *map(str, sources),
        "-o",
        str(exe),
        "-pthread",
    ]
    subprocess.run(cmd, check=True, capture_output=True, text=True)
    return exe


def test_corrupted_models_never_crash_the_loader(harness, tmp_path):
    rng = np.random.default_rng(20261122)
    base = seeds()
    files = []
    for i, seed in enumerate(base):  # the valid seeds must load
        files.append(tmp_path / f"seed{i}.onnx")
        files[-1].write_bytes(seed)
    for i in range(N_FILES):
        data = mutate(base[i % len(base)], rng, base)
        files.append(tmp_path / f"m{i:04d}.onnx")
        files[-1].write_bytes(data)
    env = dict(
        os.environ,
        ASAN_OPTIONS="detect_leaks=1:halt_on_error=1:abort_on_error=0",
        UBSAN_OPTIONS="halt_on_error=1:print_stacktrace=1",
    )
    res = subprocess.run([str(harness), *map(str, files)], capture_output=True, text=True, env=env, timeout=900)
    assert res.returncode == 0, res.stderr[-4000:]
    assert "runtime error" not in res.stderr and "AddressSanitizer" not in res.stderr
    total, loaded, rejected = map(int, re.findall(r"\d+", res.stdout))
    assert total == N_FILES + len(base)
    assert rejected > N_FILES // 2 and loaded >= len(base)  # most mutations are caught, the seeds load
