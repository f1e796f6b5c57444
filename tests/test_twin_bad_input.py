"""Bad input to ``envi twin generate | effects | calibrate``: one stderr line ``envi twin SUB: error: ...``
naming the option or file and the problem, exit code 2, no traceback, no hang, and the output folder's
earlier content intact. Each case here once wrote NaN logs, ran with a meaningless option, gave a bare
Python message, or waited for ever on a named pipe."""

from __future__ import annotations

import hashlib
import json
import os
import subprocess
import sys
from pathlib import Path

import pytest

from envi_py.controllers import ControllerSpec
from envi_py.twin import EFFECTS, generate, parse_effects, resolve, write_logs
from envi_py.twin.diffdrive import DIFFDRIVE_EFFECTS, NOVEL, resolve_diffdrive

TINY = ["--runs", "1", "--steps", "5"]
PATTERN = "twin_{x}_{run}.csv"


def twin(*argv: object) -> subprocess.CompletedProcess:
    """``envi twin ARGV`` in a fresh interpreter; a hang fails the test instead of stalling it."""
    cmd = [sys.executable, "-m", "envi_py.cli", "twin", *map(str, argv)]
    return subprocess.run(cmd, capture_output=True, text=True, timeout=60, check=False)


def refused(proc: subprocess.CompletedProcess, sub: str, *names: object) -> str:
    """Exit code 2 and one stderr line ``envi twin SUB: error: ...`` holding every one of ``names``."""
    lines = [ln for ln in proc.stderr.splitlines() if ln.strip()]
    assert proc.returncode == 2, (proc.returncode, proc.stderr)
    assert len(lines) == 1 and lines[0].startswith(f"envi twin {sub}: error: "), proc.stderr
    assert all(str(n) in lines[0] for n in names), f"{lines[0]!r} names not all of {names}"
    return lines[0]


def snapshot(folder: Path) -> dict[str, str]:
    """Every file in ``folder`` and a hash of its bytes."""
    return {p.name: hashlib.sha256(p.read_bytes()).hexdigest() for p in sorted(folder.iterdir())}


@pytest.fixture
def earlier(tmp_path: Path) -> Path:
    """An output folder holding the logs of an earlier run and a file of the user's."""
    out = tmp_path / "out"
    write_logs(generate(ControllerSpec("lane-keeping", {"x": 30}), 2, 10, seed=1), out)
    (out / "notes.txt").write_text("keep me\n")
    return out


@pytest.fixture(scope="module")
def real(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A folder of logs of two versions (x=10, x=30), two runs each: enough to calibrate."""
    d = tmp_path_factory.mktemp("real")
    for x in (10, 30):
        write_logs(generate(ControllerSpec("lane-keeping", {"x": x}), 2, 40, seed=x), d)
    return d


# ----------------------------------------------------------------------------- 1, 2: effect parameters


@pytest.mark.parametrize(
    "effects, names",
    [
        ("noise=nan", ["noise", "sigma", "nan"]),  # once 100% NaN logs
        ("noise=inf", ["noise", "sigma", "inf"]),  # once every reading pinned at the limits
        ("noise=-1", ["noise", "sigma", "-1"]),
        ("delay=-2", ["delay", "ticks", "-2"]),  # once accepted
        ("delay=1.5", ["delay", "ticks", "1.5"]),  # once silently floored to 1 tick
        ("glitch=1.5", ["glitch", "prob", "1.5"]),
        ("jitter.pause_prob=-0.1", ["jitter", "pause_prob", "-0.1"]),
        ("quantise.step=0", ["quantise", "step", "0"]),  # once a division by zero: NaN readings
        ("lag.tau_ms=0", ["lag", "tau_ms", "0"]),  # once a ZeroDivisionError traceback
        ("saturation.low=80,saturation.high=20", ["saturation", "low", "high"]),
        ("battery=2", ["battery", "sag", "2"]),
        ("delay=abc", ["delay", "ticks", "abc"]),  # once "could not convert string to float: 'abc'"
        ("jitter.pause_prob=", ["jitter", "pause_prob"]),
        ("noise.sd=1", ["noise", "sd"]),
    ],
)
def test_generate_refuses_a_bad_effect_parameter_and_keeps_the_earlier_logs(earlier: Path, effects, names):
    before = snapshot(earlier)
    proc = twin("generate", *TINY, "--effects", effects, "--out", earlier, "--force")
    line = refused(proc, "generate", "--effects", *names)
    assert "could not convert" not in line
    assert snapshot(earlier) == before


def test_the_diffdrive_world_checks_its_own_effects_too(earlier: Path):
    before = snapshot(earlier)
    proc = twin("generate", "--family", "diffdrive", *TINY, "--effects", "kick.period_s=0", "--out", earlier, "--force")
    refused(proc, "generate", "kick", "period_s")
    assert snapshot(earlier) == before
    with pytest.raises(ValueError, match="'arc': length_m"):
        resolve_diffdrive({"arc": {"length_m": -1}})
    assert resolve_diffdrive({"kick": 5})["kick"]["deg"] == 5  # its own effects are known to --effects
    assert parse_effects("kick=5", DIFFDRIVE_EFFECTS) == {"kick": 5.0}


def test_a_profile_with_a_bad_effect_is_refused_naming_the_file(earlier: Path, tmp_path: Path):
    prof = tmp_path / "p.json"
    for effects, param in (({"noise": {"sigma": -1}}, "sigma"), ({"delay": float("nan")}, "ticks")):
        prof.write_text(json.dumps({"effects": effects}))  # json writes the NaN as a bare NaN
        before = snapshot(earlier)
        proc = twin("generate", *TINY, "--profile", prof, "--out", earlier, "--force")
        refused(proc, "generate", "--profile", prof, param)
        assert snapshot(earlier) == before
    prof.write_text(json.dumps({"speed": 0}))
    refused(twin("effects", "--profile", prof), "effects", prof, "speed")


def test_every_effect_at_its_defaults_and_the_shipped_profile_still_pass():
    """The ranges refuse nonsense only: every default, the documented example and the shipped profile."""
    assert set(resolve({}, {name: True for name in EFFECTS})) == set(EFFECTS)
    assert set(resolve_diffdrive({name: True for name in NOVEL})) == set(NOVEL)
    assert parse_effects("delay=2,noise=1.5,jitter.pause_prob=0.01,glitch,lowpass=0")["delay"] == 2.0
    proc = twin("effects")
    assert proc.returncode == 0 and proc.stderr == "" and "profile effects" in proc.stdout, proc.stderr


# ----------------------------------------------------------------------------- 3: the error: prefix


@pytest.mark.parametrize(
    "argv, names",
    [
        (["--system", "car", "--family", "diffdrive"], ["--family"]),
        (["--version", "1"], ["--version"]),
        (["--runs", "0"], ["--runs"]),
    ],
)
def test_generate_errors_carry_the_error_prefix(earlier: Path, argv, names):
    before = snapshot(earlier)
    refused(twin("generate", *argv, "--out", earlier, "--force"), "generate", *names)
    assert snapshot(earlier) == before


# ----------------------------------------------------------------------------- 4, 5: calibrate options


@pytest.mark.parametrize(
    "argv, names",
    [
        (["--key", "bogus"], ["--key", "bogus", "known: x"]),  # once ran the whole search
        (["--budget", "-1"], ["--budget", "-1"]),  # once ran (a single search step)
        (["--budget", "0"], ["--budget", "0"]),
        (["--budget", "nan"], ["--budget", "nan"]),
        (["--budget", "inf"], ["--budget", "inf"]),  # would search for ever
    ],
)
def test_calibrate_refuses_a_bad_option_before_the_search(real: Path, tmp_path: Path, argv, names):
    out = tmp_path / "cal"
    out.mkdir()
    (out / "notes.txt").write_text("keep me\n")
    proc = twin("calibrate", "--logs", real, "--pattern", PATTERN, "--quick", "--quiet", *argv, "--out", out)
    refused(proc, "calibrate", *names)
    assert snapshot(out) == {"notes.txt": hashlib.sha256(b"keep me\n").hexdigest()}


def test_calibrate_logs_must_be_a_folder(real: Path, tmp_path: Path):
    """Once "Distribution can't be empty." naming nothing."""
    one = real / "twin_10_0.csv"
    out = tmp_path / "cal"
    proc = twin("calibrate", "--logs", one, "--pattern", PATTERN, "--quick", "--quiet", "--out", out)
    assert "folder" in refused(proc, "calibrate", "--logs", one)
    assert not out.exists()


def test_calibrate_needs_two_runs_of_each_version(tmp_path: Path):
    logs = tmp_path / "logs"
    write_logs(generate(ControllerSpec("lane-keeping", {"x": 10}), 1, 40, seed=0), logs)
    out = tmp_path / "cal"
    proc = twin("calibrate", "--logs", logs, "--pattern", PATTERN, "--quick", "--quiet", "--out", out)
    assert "Distribution" not in refused(proc, "calibrate", "--logs", logs, "x=10")
    assert not out.exists()


# ----------------------------------------------------------------------------- 6: named pipes


@pytest.mark.skipif(not hasattr(os, "mkfifo"), reason="named pipes need POSIX")
@pytest.mark.parametrize(
    "argv, sub, option",
    [
        (["generate", *TINY, "--profile", "{fifo}", "--out", "{out}"], "generate", "--profile"),
        (["effects", "--profile", "{fifo}"], "effects", "--profile"),
        (
            ["calibrate", "--logs", "{real}", "--pattern", PATTERN, "--start", "{fifo}", "--quick", "--out", "{out}"],
            "calibrate",
            "--start",
        ),
    ],
)
def test_a_named_pipe_as_profile_is_refused_at_once(real: Path, tmp_path: Path, argv, sub, option):
    """Once blocked for ever waiting for a writer."""
    fifo = tmp_path / "profile.json"
    os.mkfifo(fifo)
    out = tmp_path / "out"
    given = {"{fifo}": fifo, "{out}": out, "{real}": real}
    proc = twin(*(given.get(a, a) for a in argv))
    assert "not a regular file" in refused(proc, sub, option, fifo)
    assert not out.exists()
