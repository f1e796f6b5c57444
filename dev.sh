#!/usr/bin/env bash
# One entry point for a fresh Debian/Ubuntu machine:
#   ./dev.sh demo   set up, then run the main job (twin data -> train -> simulate -> verify)
#   ./dev.sh test   set up, then run every test (C++, then ruff on the whole tree, then Python)
#   ./dev.sh setup  only set up
# Set-up is idempotent: system packages via apt-get (g++, cmake, python3-venv, chromium), Python packages into
# ./.venv (Eigen too: the cmeel-eigen wheel, no libeigen3-dev needed).
set -euo pipefail
cd "$(dirname "$0")"
ROOT=$(pwd)
VENV="$ROOT/.venv"
PY="$VENV/bin/python"

sudo_if_needed() { if [ "$(id -u)" -eq 0 ]; then "$@"; else sudo "$@"; fi; }

setup_system() {
  local need=()
  command -v g++ >/dev/null || need+=(g++)
  command -v cmake >/dev/null || need+=(cmake)
  python3 -c 'import venv, ensurepip' 2>/dev/null || need+=(python3-venv)
  command -v chromium >/dev/null || need+=(chromium)  # the headless browser of tests/test_report_html.py
  if [ ${#need[@]} -gt 0 ]; then
    echo "[setup] apt-get install ${need[*]}"
    sudo_if_needed apt-get update -qq
    sudo_if_needed env DEBIAN_FRONTEND=noninteractive apt-get install -y -qq "${need[@]}"
  fi
}

setup_python() {
  [ -x "$PY" ] || python3 -m venv "$VENV"
  # Reinstall only when the build inputs changed: the stamp hashes them.
  local stamp="$VENV/.envi-stamp" want
  want=$(cat pyproject.toml constraints.txt CMakeLists.txt $(find cpp -type f 2>/dev/null | sort) | sha256sum | cut -c1-16)
  if [ "$(cat "$stamp" 2>/dev/null)" != "$want" ]; then
    echo "[setup] installing Python packages into .venv"
    "$PY" -m pip install -q --upgrade pip
    "$PY" -m pip install -q -c constraints.txt torch
    # Eigen's headers for the CTest build below (pip builds fetch their own, see pyproject.toml)
    "$PY" -m pip install -q -c constraints.txt cmeel-eigen
    "$PY" -m pip install -q -c constraints.txt -e ".[test]"
    echo "$want" > "$stamp"
  fi
}

setup() { setup_system; setup_python; }

case "${1:-}" in
  setup) setup ;;
  demo) setup; shift; "$VENV/bin/envi" demo "$@" ;;
  test)
    setup; shift
    if [ -d build/ctest ]; then rm -rf build/ctest; fi
    if [ -f cpp/CMakeLists.txt ]; then
      cmake -S . -B build/ctest -DENVI_BUILD_TESTS=ON -DENVI_ISA_VARIANTS=OFF -DCMAKE_BUILD_TYPE=Release \
        -Dpybind11_DIR="$("$PY" -m pybind11 --cmakedir)" -DPython_EXECUTABLE="$PY" >/dev/null
      cmake --build build/ctest -j"$(nproc)"
      (cd build/ctest && ctest --output-on-failure)
    fi
    "$VENV/bin/ruff" check . && "$VENV/bin/ruff" format --check .  # lint and format: the whole tree
    "$PY" -m pytest "$@" ;;
  *) echo "usage: $0 demo|test|setup [args]"; exit 2 ;;
esac
