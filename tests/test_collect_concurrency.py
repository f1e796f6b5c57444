"""Two envi-collect on one --out folder: the second is refused at once and touches nothing.

Without that, the second took the first one's live run for a dead collector's, stopped it on the
brick and settled it lost, and the two numbered their runs over each other.
"""

from __future__ import annotations

import os
import signal
import subprocess
import time
from pathlib import Path

import pytest

from firmware_bridge.host.ledger import Ledger
from firmware_bridge.host.lock import FolderBusy, hold

from .test_bridge_pty import BrickSim
from .test_collect_faults import PERIOD_MS, launch, own_runs


def snapshot(folder: Path) -> dict[str, bytes]:
    return {p.name: p.read_bytes() for p in sorted(folder.iterdir())}


def test_a_second_collector_on_a_busy_folder_is_refused_in_one_line(tmp_path: Path) -> None:
    sim = BrickSim(tmp_path, "--period", str(PERIOD_MS), "--world", "firmware_bridge.host.world:EdgeWorld")
    out = tmp_path / "logs"
    procs: list[subprocess.Popen] = []
    try:
        first = launch(sim.link, out, 1, 60_000, tmp_path / "first.err")  # interrupted below
        procs.append(first)
        deadline = time.monotonic() + 60
        while not own_runs(out, first.pid) and first.poll() is None and time.monotonic() < deadline:
            time.sleep(0.01)
        assert own_runs(out, first.pid), (tmp_path / "first.err").read_text()
        before = snapshot(out)
        second = launch(sim.link, out, 1, 1000, tmp_path / "second.err")
        procs.append(second)
        rc = second.wait(timeout=60)
        err = (tmp_path / "second.err").read_text().splitlines()
        want = f"envi-collect: {out}: another envi-collect (pid {first.pid}) is recording into it; "
        assert rc == 2 and err == [want + "wait for it or give another --out"], err
        assert snapshot(out) == before  # the ledger, the lock file, everything as it was
        assert first.poll() is None  # still recording, its run untouched
        first.send_signal(signal.SIGINT)
        assert first.wait(timeout=60) == 130, (tmp_path / "first.err").read_text()
    finally:
        for p in procs:
            if p.poll() is None:
                p.kill()
                p.wait(timeout=10)
        sim.stop()
    [start, end] = Ledger(out).entries  # the second collector started and settled nothing
    assert start["pid"] == first.pid and (end["run"], end["status"], end["reason"], end["settled_by"]) == (
        "log_30_0",
        "incomplete",
        "interrupted",
        "collector",
    )
    assert end["rows"] > 0 and end["rows_lost"] == 0


def test_a_second_collector_on_a_busy_port_is_refused_at_once(tmp_path: Path) -> None:
    """Two folders, one port: the second would split the brick's bytes with the first (and stop its run
    as a foreign one). The port is opened exclusively, so the second is refused without waiting out
    the reconnection time."""
    sim = BrickSim(tmp_path, "--period", str(PERIOD_MS), "--world", "firmware_bridge.host.world:EdgeWorld")
    procs: list[subprocess.Popen] = []
    try:
        first = launch(sim.link, tmp_path / "a", 1, 60_000, tmp_path / "first.err")
        procs.append(first)
        deadline = time.monotonic() + 60
        while not own_runs(tmp_path / "a", first.pid) and first.poll() is None and time.monotonic() < deadline:
            time.sleep(0.01)
        assert own_runs(tmp_path / "a", first.pid), (tmp_path / "first.err").read_text()
        second = launch(sim.link, tmp_path / "b", 1, 1000, tmp_path / "second.err", "--reconnect", "600")
        procs.append(second)
        rc = second.wait(timeout=60)  # well within the 600 s it would keep reopening a port that is gone
        err = (tmp_path / "second.err").read_text().splitlines()
        assert rc == 2 and err == [
            f"envi-collect: {sim.link}: another program has the port open (another envi-collect?)"
        ]
        assert first.poll() is None
        first.send_signal(signal.SIGINT)
        assert first.wait(timeout=60) == 130
    finally:
        for p in procs:
            if p.poll() is None:
                p.kill()
                p.wait(timeout=10)
        sim.stop()
    [start, end] = Ledger(tmp_path / "a").entries
    assert end["status"] == "incomplete" and end["reason"] == "interrupted" and end["rows_lost"] == 0


@pytest.mark.parametrize("kind", ["symlink", "dangling", "fifo", "directory"])
def test_a_lock_that_is_not_a_regular_file_is_refused_and_left_alone(tmp_path: Path, kind: str) -> None:
    """collect.lock through a symlink would truncate its target (a user's file) to the pid; a FIFO
    would block the open. Each is refused in one line naming it, and nothing is written anywhere."""
    out = tmp_path / "logs"
    out.mkdir()
    target = tmp_path / "precious.txt"
    target.write_text("the user's")
    lock = out / "collect.lock"
    {
        "symlink": lambda: lock.symlink_to(target),
        "dangling": lambda: lock.symlink_to(tmp_path / "nowhere"),
        "fifo": lambda: os.mkfifo(lock),
        "directory": lambda: lock.mkdir(),
    }[kind]()
    with pytest.raises(FolderBusy, match=f"{lock}: "):
        hold(out)
    assert target.read_text() == "the user's" and not (tmp_path / "nowhere").exists()
