"""A command killed half-way (SIGTERM, SIGHUP, Ctrl-C) or failing half-way leaves what it writes as it
was: no hidden staging folder in ``--out``, no truncated ``--metrics`` document, no earlier run lost.

Before stop 40, SIGTERM killed ``envi simulate`` and ``envi_sim`` outright (their hidden staging
folders stayed in ``--out``), and ``envi_sim`` opened ``--metrics`` in place, so a run refused half-way
(a command beyond its actuator's range) replaced an earlier document with a truncated one."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

from envi_py import native
from envi_py.interrupt import Terminated, exit_code, signals_interrupt
from tests.test_native import envi_sim

ROOT = Path(__file__).resolve().parents[1]
EARLIER = '{"earlier": "document"}\n'


def earlier_run(out: Path) -> dict[str, bytes]:
    """An earlier run's files in ``out`` (a log, its sidecar and a file of the user's), as bytes."""
    out.mkdir(parents=True, exist_ok=True)
    (out / "old-sim0.csv").write_text("time,color,angle\n0,40,30\n40,41,30\n")
    (out / "old-sim0.meta.json").write_text('{"schema_version": 1}\n')
    (out / "notes.txt").write_text("mine\n")
    return snapshot(out)


def snapshot(folder: Path) -> dict[str, bytes]:
    """Every entry of ``folder``, hidden ones included, by name."""
    return {p.name: p.read_bytes() if p.is_file() else b"<folder>" for p in sorted(folder.iterdir())}


def kill_once_staging_fills(proc: subprocess.Popen, out: Path, sig: int) -> None:
    """Send ``sig`` once the command has written logs into its hidden staging folder: mid-run."""
    deadline = time.monotonic() + 120
    while time.monotonic() < deadline and proc.poll() is None:
        if any(any(p.iterdir()) for p in out.glob(".staging-*")):
            break
        time.sleep(0.02)
    assert proc.poll() is None, "the run ended before it could be interrupted: give it more runs"
    proc.send_signal(sig)


def test_a_kill_inside_the_block_raises_and_the_host_handlers_come_back():
    before = signal.getsignal(signal.SIGTERM)
    with pytest.raises(Terminated) as caught, signals_interrupt():
        os.kill(os.getpid(), signal.SIGTERM)
        time.sleep(5)  # the handler runs at the next bytecode: this line is never finished
    assert exit_code(caught.value) == 143 and exit_code(KeyboardInterrupt()) == 130
    assert signal.getsignal(signal.SIGTERM) is before


ENGINES = ["torch", pytest.param("native", marks=pytest.mark.skipif(not native.available(), reason="not built"))]


@pytest.mark.parametrize("engine", ENGINES)
@pytest.mark.parametrize("sig", [signal.SIGTERM, signal.SIGHUP], ids=["kill", "hangup"])
def test_envi_simulate_killed_mid_run_leaves_out_as_it_was(mini, tmp_path, engine, sig):
    out = tmp_path / "sim"
    before = earlier_run(out)
    proc = subprocess.Popen(
        [sys.executable, "-m", "envi_py.cli", "simulate", "--model", str(mini["model"])]
        + ["--init-logs", str(mini["logs"]), "--out", str(out), "--force", "--runs", "3000", "--steps", "20"]
        + ["--engine", engine],
        cwd=ROOT,
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
    )
    kill_once_staging_fills(proc, out, sig)
    _, err = proc.communicate(timeout=120)
    assert proc.returncode == 128 + sig, err
    assert err.splitlines() == [f"envi simulate: interrupted ({signal.Signals(sig).name})"], err
    assert snapshot(out) == before  # no hidden staging folder, the earlier logs whole


@pytest.mark.skipif(envi_sim() is None, reason="envi_sim binary not built")
def test_envi_sim_killed_mid_run_leaves_out_and_metrics_as_they_were(mini, tmp_path):
    out, metrics = tmp_path / "sim", tmp_path / "m.json"
    before = earlier_run(out)
    metrics.write_text(EARLIER)
    init = [str(p) for p in sorted(mini["logs"].glob("*.csv"))]
    proc = subprocess.Popen(
        [envi_sim(), "--model", str(mini["onnx"]), "--init", *init, "--runs", "3000", "--steps", "20"]
        + ["--out", str(out), "--force", "--metrics", str(metrics), "--threads", "1"],
        stderr=subprocess.PIPE,
        text=True,
    )
    kill_once_staging_fills(proc, out, signal.SIGTERM)
    _, err = proc.communicate(timeout=120)
    assert proc.returncode == 143, err
    assert err.splitlines() == ["envi_sim: interrupted (SIGTERM); --out and --metrics are left as they were"], err
    assert snapshot(out) == before
    assert sorted(p.name for p in tmp_path.iterdir()) == ["m.json", "sim"]  # no partial document beside it
    assert metrics.read_text() == EARLIER


@pytest.mark.skipif(envi_sim() is None, reason="envi_sim binary not built")
def test_envi_sim_refused_mid_run_keeps_the_earlier_metrics_document(mini, tmp_path):
    """A command beyond the actuator's range is refused at its first step, after the document was
    opened: it once truncated the earlier document to its header."""
    metrics = tmp_path / "m.json"
    metrics.write_text(EARLIER)
    init = str(sorted(mini["logs"].glob("*.csv"))[0])
    done = subprocess.run(
        [envi_sim(), "--model", str(mini["onnx"]), "--init", init, "--metrics", str(metrics)]
        + ["--controller", "lane-keeping", "--param", "x=1e6"],
        capture_output=True,
        text=True,
        check=False,
    )
    assert done.returncode == 2 and len(done.stderr.splitlines()) == 1, done.stderr
    assert metrics.read_text() == EARLIER
    assert [p.name for p in tmp_path.iterdir()] == ["m.json"]
    # nor is a fresh --out left behind, empty (it is created only once every check has passed)
    again = subprocess.run(
        [envi_sim(), "--model", str(mini["onnx"]), "--init", init, "--out", str(tmp_path / "fresh")]
        + ["--controller", "lane-keeping", "--param", "x=1e6"],
        capture_output=True,
        text=True,
        check=False,
    )
    assert again.returncode == 2 and not (tmp_path / "fresh").exists(), again.stderr
    # and a run that completes replaces it whole, with a plain file's mode
    ok = subprocess.run(
        [envi_sim(), "--model", str(mini["onnx"]), "--init", init, "--metrics", str(metrics), "--steps", "5"],
        capture_output=True,
        text=True,
        check=False,
    )
    assert ok.returncode == 0, ok.stderr
    assert len(json.loads(metrics.read_text())["per_run"]) == 1
    umask = os.umask(0)
    os.umask(umask)
    assert metrics.stat().st_mode & 0o777 == 0o666 & ~umask


@pytest.mark.skipif(envi_sim() is None, reason="envi_sim binary not built")
def test_envi_sim_writes_metrics_into_a_fifo_as_it_is(mini, tmp_path):
    """A document renamed into place must never replace a device or FIFO node (``--metrics /dev/null``
    run as root would have replaced the device with a file): such a target is written as it is."""
    fifo = tmp_path / "metrics.fifo"
    os.mkfifo(fifo)
    reader = subprocess.Popen(["cat", str(fifo)], stdout=subprocess.PIPE, text=True)
    init = str(sorted(mini["logs"].glob("*.csv"))[0])
    done = subprocess.run(
        [envi_sim(), "--model", str(mini["onnx"]), "--init", init, "--metrics", str(fifo), "--steps", "5"],
        capture_output=True,
        text=True,
        check=False,
        timeout=120,
    )
    out, _ = reader.communicate(timeout=60)
    assert done.returncode == 0, done.stderr
    assert len(json.loads(out)["per_run"]) == 1
    assert fifo.is_fifo() and sorted(p.name for p in tmp_path.iterdir()) == ["metrics.fifo"]
