"""``pip wheel .`` builds a self-contained wheel without a system Eigen, and it runs from a fresh venv.

The wheel is built as a user's ``pip install .`` builds it: in pip's isolated build environment, with
scikit-build-core, pybind11 and cmeel-eigen fetched from the package index. The system Eigen
(/usr/include/eigen3 on a machine with libeigen3-dev) is hidden from CMake and Eigen is taken from
cmeel only, so a pass shows the build needs no system package. The wheel is installed into a new
venv that shares only the runtime dependencies (torch, numpy, ...) of this interpreter, and run from
an empty directory: the source tree cannot stand in for anything the wheel lacks.

A clean build of the C++ runtime takes minutes; ``ENVI_SKIP_WHEEL=1`` skips the build (CI runs it).
"""

from __future__ import annotations

import importlib.util
import json
import os
import re
import subprocess
import sys
import zipfile
from pathlib import Path

import numpy as np
import pytest

from .conftest import make_log
from .test_export import paper_ckpt

ROOT = Path(__file__).resolve().parents[1]
SKIP_WHEEL = os.environ.get("ENVI_SKIP_WHEEL") == "1"
#: where a system Eigen's headers and CMake config live (Debian/Ubuntu package, or built from source)
SYSTEM_EIGEN = ["/usr/include/eigen3", "/usr/share/eigen3/cmake", "/usr/lib/cmake/eigen3", "/usr/local/include/eigen3"]
SYSTEM_EIGEN += ["/usr/local/share/eigen3/cmake"]
#: what the installed package imports at run time; the fresh venv sees these through a .pth file
RUNTIME_DEPS = ["numpy", "scipy", "torch", "onnx", "onnxruntime", "serial", "tqdm", "matplotlib", "rtamt"]

needs_wheel = pytest.mark.skipif(SKIP_WHEEL, reason="ENVI_SKIP_WHEEL=1: the wheel build (minutes) is skipped")

#: run by the fresh venv's Python: the native engine on the exported model against the PyTorch one
CHECK = r"""
import json, sys
import numpy as np
import envi_py
from envi_py import native
from envi_py.controllers import ControllerSpec
from envi_py.model import Checkpoint
from envi_py.simulate import rollout

ckpt, init, model = Checkpoint.load(sys.argv[1]), np.load(sys.argv[2]), sys.argv[3]
spec = ControllerSpec("lane-keeping", {"x": 30})
got = native.rollout(model, spec, init, 40, runs=2, threads=2)
want = rollout(ckpt, spec, init, 40, runs=2)
variant = native.variant()
module = sys.modules["envi_py." + variant.split()[0]] if native.available() else None
print(json.dumps({
    "envi_py": envi_py.__file__,
    "module": module.__file__ if module else None,
    "variant": variant,
    "shape": list(got.shape),
    "max_abs_diff": float(np.abs(got - want).max()),
}))
"""


def cmeel_eigen_pins() -> tuple[str, str]:
    """The cmeel-eigen requirement in pyproject.toml's [build-system] and in constraints.txt."""
    try:
        import tomllib
    except ModuleNotFoundError:  # pragma: no cover - Python 3.10
        import tomli as tomllib
    requires = tomllib.loads((ROOT / "pyproject.toml").read_text())["build-system"]["requires"]
    build = [r for r in requires if r.startswith("cmeel-eigen")]
    lines = (ROOT / "constraints.txt").read_text().splitlines()
    constraint = [ln.strip() for ln in lines if ln.strip().startswith("cmeel-eigen")]
    assert len(build) == 1 and len(constraint) == 1, (build, constraint)
    return build[0], constraint[0]


def test_the_build_and_the_ctest_build_pin_the_same_eigen():
    build, constraint = cmeel_eigen_pins()
    assert re.fullmatch(r"cmeel-eigen==[0-9.]+", build), build
    assert build == constraint


def clean_env() -> dict[str, str]:
    """This environment less what could make Python import from elsewhere (PYTHONPATH, ...) or point
    CMake at another Eigen (CMAKE_PREFIX_PATH)."""
    return {k: v for k, v in os.environ.items() if not k.startswith(("PYTHON", "VIRTUAL_ENV", "CMAKE_PREFIX"))}


@pytest.fixture(scope="module")
def wheel(tmp_path_factory) -> tuple[Path, str]:
    """The wheel built from this tree with Eigen from cmeel only, and pip's log of the build."""
    out = tmp_path_factory.mktemp("wheel")
    cmd = [
        sys.executable, "-m", "pip", "wheel", str(ROOT), "--no-deps", "-v", "-w", str(out / "dist"),
        f"--config-settings=build-dir={out / 'build'}",  # a clean build, not the tree's build/
        "--config-settings=build.verbose=true",  # compiler command lines in the log
        "--config-settings=cmake.define.ENVI_EIGEN_FROM=cmeel",
        f"--config-settings=cmake.define.CMAKE_IGNORE_PATH={';'.join(SYSTEM_EIGEN)}",
    ]  # fmt: skip
    env = clean_env()
    env.setdefault("CMAKE_BUILD_PARALLEL_LEVEL", str(os.cpu_count() or 1))
    done = subprocess.run(cmd, cwd=out, env=env, capture_output=True, text=True, timeout=3600)
    log = done.stdout + done.stderr
    (out / "build.log").write_text(log)
    assert done.returncode == 0, f"pip wheel failed (log: {out / 'build.log'}):\n{log[-4000:]}"
    wheels = sorted((out / "dist").glob("envi-*.whl"))
    assert len(wheels) == 1, wheels
    return wheels[0], log


@needs_wheel
def test_eigen_comes_from_cmeel_not_the_system(wheel):
    _, log = wheel
    said = re.findall(r"envi: Eigen (\S+) from (\w+) \((.*)\)", log)
    assert len(said) == 1, said
    version, origin, include = said[0]
    pinned = cmeel_eigen_pins()[0].split("==")[1]
    assert origin == "cmeel" and version == pinned, said
    assert "cmeel.prefix" in include and "/usr/include/eigen3" not in include, include
    compiles = [ln for ln in log.splitlines() if " -c " in ln and "pymodule.cpp" in ln]
    assert compiles, "no compiler command line in the build log"
    for line in compiles:
        assert "cmeel.prefix/include/eigen3" in line and "/usr/include/eigen3" not in line, line


@needs_wheel
def test_the_common_code_is_compiled_once_and_the_kernels_per_isa(wheel):
    _, log = wheel
    compiled = re.findall(r" -c (\S+\.cpp)", log)
    per_file = {Path(src).name: compiled.count(src) for src in set(compiled)}
    variants = 3 if re.match(r"x86_64|amd64", os.uname().machine.lower()) else 1
    for src in (
        "json.cpp",
        "sha256.cpp",
        "onnx_loader.cpp",
        "controller.cpp",
        "metrics.cpp",
        "envi_sim.cpp",
        "csvlog.cpp",
    ):
        assert per_file.get(src) == 1, (src, per_file)
    for src in ("dense.cpp", "engine.cpp", "peak.cpp", "pymodule.cpp"):
        assert per_file.get(src) == variants, (src, per_file)


@needs_wheel
def test_the_wheel_holds_the_modules_the_binary_and_the_systems(wheel):
    path, _ = wheel
    names = zipfile.ZipFile(path).namelist()
    modules = [n for n in names if re.fullmatch(r"envi_py/_native(_avx2|_avx512)?\..*\.so", n)]
    assert len(modules) == len(set(modules)) >= 1, modules
    assert any(n.endswith(".data/scripts/envi_sim") for n in names), names
    assert any(n.startswith("envi_py/systems/") and n.endswith(".toml") for n in names)
    assert not any(n.startswith(("tests/", "cpp/", "build/")) for n in names)


def runtime_dep_dirs() -> list[str]:
    """The site-packages directories this interpreter imports the runtime dependencies from."""
    dirs: list[str] = []
    for name in RUNTIME_DEPS:
        spec = importlib.util.find_spec(name)
        assert spec is not None and spec.origin, f"{name} is not installed"
        site = str(Path(spec.origin).resolve().parents[1])
        assert Path(site) != ROOT, f"{name} is imported from the source tree"
        if site not in dirs:
            dirs.append(site)
    return dirs


@needs_wheel
def test_the_wheel_runs_the_native_engine_from_a_fresh_venv(wheel, tmp_path):
    path, _ = wheel
    venv = tmp_path / "venv"
    subprocess.run([sys.executable, "-m", "venv", "--without-pip", str(venv)], check=True)
    py = venv / "bin" / "python"
    install = [sys.executable, "-m", "pip", "--python", str(py), "install", "--no-deps", "--no-index", str(path)]
    subprocess.run(install, check=True, capture_output=True, env=clean_env())
    site = Path(
        subprocess.check_output(
            [str(py), "-c", "import sysconfig; print(sysconfig.get_path('purelib'))"], text=True
        ).strip()
    )
    # torch and the rest from this interpreter's site-packages: CI does not download them twice
    (site / "envi_runtime_deps.pth").write_text("\n".join(runtime_dep_dirs()) + "\n")

    work = tmp_path / "elsewhere"  # an empty working directory: nothing importable from the tree
    work.mkdir()
    ckpt = paper_ckpt(seed=1).save(work / "model.pt")
    rng = np.random.default_rng(0)
    init = np.stack([make_log(np.clip(40 + np.cumsum(rng.normal(0, 8, 10)), 0, 100)).values for _ in range(3)])
    np.save(work / "init.npy", init)
    env = clean_env()

    exported = subprocess.run(
        [str(venv / "bin" / "envi-export"), str(ckpt), "-o", "model.onnx"],
        cwd=work,
        env=env,
        capture_output=True,
        text=True,
    )
    assert exported.returncode == 0, exported.stderr
    run = subprocess.run(
        [str(py), "-c", CHECK, str(ckpt), "init.npy", "model.onnx"], cwd=work, env=env, capture_output=True, text=True
    )
    assert run.returncode == 0, run.stderr
    got = json.loads(run.stdout.strip().splitlines()[-1])
    assert Path(got["envi_py"]).resolve().is_relative_to(venv.resolve()), got
    assert got["module"] and Path(got["module"]).resolve().is_relative_to(venv.resolve()), got
    assert got["shape"] == [6, 50, 2], got
    assert got["max_abs_diff"] <= 1e-4, got

    usage = subprocess.run(
        [str(venv / "bin" / "envi_sim"), "--help"], cwd=work, env=env, capture_output=True, text=True
    )
    assert usage.returncode == 0, usage.stderr
    assert "--model" in usage.stdout
