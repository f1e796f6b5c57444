"""argparse's own errors are one line and exit code 2 in every envi command line (issue 16).

Each case runs the real entry point in a subprocess (what a user sees, stderr and exit code
included): a bad type, a missing required option, an invalid choice, an unknown option, a missing
subcommand, for ``envi`` and its subcommands, ``envi-export`` and ``envi-collect``.
"""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
ENVI = ["-m", "envi_py.cli"]
EXPORT = ["-m", "envi_py.export_cli"]
COLLECT = ["-m", "firmware_bridge.host.collect"]

#: (entry point, arguments, program named in the error, words the reason must contain)
CASES = [
    (ENVI, ["train", "--logs", "x", "--epochs", "1.5", "-o", "m.pt"], "envi train", ["--epochs", "1.5"]),
    (ENVI, ["train", "--logs", "x"], "envi train", ["required", "--output"]),
    (ENVI, ["train", "--logs", "x", "--algorithm", "ppo", "-o", "m.pt"], "envi train", ["invalid choice", "ppo"]),
    (ENVI, ["split", "--logs", "x", "--seed", "-1", "--out", "o"], "envi split", ["--seed", "0..2147483647"]),
    # every command's seed, checked as it is read (diagnose once failed 4.5 s in, naming no option)
    (ENVI, ["twin", "generate", "--seed", "-1", "--out", "o"], "envi twin generate", ["--seed", "-1"]),
    (ENVI, ["diagnose", "--model", "m.pt", "--real", "x", "--seed", "-1"], "envi diagnose", ["--seed", "-1"]),
    (ENVI, ["experiment", "tovk", "--logs", "x", "--seed", "-1", "--out", "o"], "envi experiment", ["--seed"]),
    (ENVI, ["train", "--logs", "x", "--seed", "1" + "0" * 20, "-o", "m.pt"], "envi train", ["--seed", "0..2147483647"]),
    (
        ENVI,
        ["simulate", "--model", "m.pt", "--init-logs", "x", "--engine", "gpu", "--out", "o"],
        "envi simulate",
        ["--engine", "gpu"],
    ),
    (ENVI, ["verify", "--real", "x", "--sim", "y", "--skip", "abc"], "envi verify", ["--skip", "abc"]),
    (ENVI, ["nosuchcommand"], "envi", ["invalid choice", "nosuchcommand"]),
    (ENVI, [], "envi", ["required", "command"]),
    (ENVI, ["--bogus", "demo"], "envi", ["unrecognized", "--bogus"]),
    (ENVI, ["demo", "--epochs", "many"], "envi demo", ["--epochs", "many"]),
    (ENVI, ["twin"], "envi twin", ["required"]),
    (ENVI, ["twin", "generate", "--system", "boat"], "envi twin generate", ["invalid choice", "boat"]),
    (ENVI, ["experiment", "tovk"], "envi experiment", ["required", "--logs"]),
    (ENVI, ["diagnose", "validate", "--seeds", "x"], "envi diagnose validate", ["--seeds", "x"]),
    (ENVI, ["diagnose"], "envi diagnose", ["--model", "--real"]),
    (ENVI, ["brick-sim", "--no-such-flag"], "envi", ["unrecognized", "--no-such-flag"]),
    (EXPORT, [], "envi-export", ["required", "model"]),
    (EXPORT, ["m.pt"], "envi-export", ["required", "--output"]),
    (EXPORT, ["m.pt", "-o", "m.onnx", "--fast"], "envi-export", ["unrecognized", "--fast"]),
    (COLLECT, ["--port", "/dev/null", "--out", "o", "--runs", "two"], "envi-collect", ["--runs", "two"]),
    (COLLECT, ["--out", "o"], "envi-collect", ["required", "--port"]),
]


@pytest.mark.parametrize(
    ("entry", "argv", "prog", "words"), CASES, ids=lambda v: " ".join(v) if isinstance(v, list) else None
)
def test_argparse_errors_are_one_line_with_exit_2(tmp_path, entry, argv, prog, words):
    proc = subprocess.run(
        [sys.executable, *entry, *argv],
        cwd=tmp_path,
        capture_output=True,
        text=True,
        timeout=120,
        env={**os.environ, "PYTHONPATH": str(ROOT), "COLUMNS": "80"},
    )
    lines = [ln for ln in proc.stderr.splitlines() if ln.strip()]
    assert proc.returncode == 2, proc.stderr
    assert len(lines) == 1, proc.stderr
    assert "usage:" not in proc.stderr and "Traceback" not in proc.stderr, proc.stderr
    assert lines[0].startswith(f"{prog}: error: "), lines[0]
    assert lines[0].endswith(f"(see {prog} --help)"), lines[0]
    for word in words:
        assert word in lines[0], (word, lines[0])
    assert proc.stdout == "", proc.stdout


def test_help_is_not_an_error_and_shows_defaults():
    """``--help`` is untouched: the usage block on stdout, exit 0, defaults shown."""
    proc = subprocess.run(
        [sys.executable, *ENVI, "train", "--help"],
        capture_output=True,
        text=True,
        timeout=120,
        env={**os.environ, "PYTHONPATH": str(ROOT), "COLUMNS": "200"},
    )
    assert proc.returncode == 0 and proc.stderr == ""
    assert proc.stdout.startswith("usage: envi train")
    assert "training epochs (default: 300)" in proc.stdout


def test_a_reader_that_stops_early_is_no_error():
    """'envi twin effects | head': the pipe closes before envi is done writing; that is the reader's
    choice, said quietly with a shell's SIGPIPE status (it printed 'error: [Errno 32] Broken pipe' and
    exited 2); not 0, since a command stopped there may not have written what follows its table."""
    import subprocess
    import sys

    p = subprocess.Popen(
        [sys.executable, "-m", "envi_py.cli", "twin", "effects"], stdout=subprocess.PIPE, stderr=subprocess.PIPE
    )
    p.stdout.close()
    assert p.wait(timeout=120) == 141 and p.stderr.read() == b""
