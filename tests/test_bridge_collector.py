"""envi-collect's bookkeeping without a brick: the ledger, writes that never replace a log, settling
what a killed collector left, and a run that takes only its own frames."""

from __future__ import annotations

import json
import os
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

from envi_py.logs import read_log, write_log
from firmware_bridge.brick import protocol as P
from firmware_bridge.host import collect
from firmware_bridge.host.ledger import LEDGER_NAME, Ledger
from firmware_bridge.host.lock import LOCK_NAME
from firmware_bridge.host.session import BrickError, BrickInfo, Run, handshake
from firmware_bridge.host.settle import settle
from firmware_bridge.host.store import LogExists, remove_stale_staging, save_new
from firmware_bridge.host.tally import Tally

from .conftest import make_log


class FakeLink:
    """A link whose brick is a script: queued messages come out of ``recv``; a STOP of a run in
    ``ends`` queues that run's RUN_END, as the brick does."""

    url = "fake://brick"

    def __init__(self, inbox: list[tuple[int, tuple]] | None = None, ends: dict[int, tuple] | None = None) -> None:
        self.inbox = [P.Message(t, i, 0, f) for i, (t, f) in enumerate(inbox or [])]
        self.ends = ends or {}
        self.sent: list[tuple[int, tuple]] = []
        self.decoder = P.Decoder()

    def send(self, mtype: int, fields: tuple) -> float:
        self.sent.append((mtype, fields))
        if mtype == P.STOP and fields[0] in self.ends:
            self.inbox.append(P.Message(P.RUN_END, 0, 0, self.ends[fields[0]]))
        return time.perf_counter()

    def recv(self, timeout: float) -> tuple[float, P.Message] | None:
        return (time.perf_counter(), self.inbox.pop(0)) if self.inbox else None


def info(state: int = P.RUN_NONE, run_id: int = 0) -> BrickInfo:
    return BrickInfo(P.VERSION, 40, "hash", "rt", "lane-keeping", {"x": 30.0, "threshold": 40.0}, state, run_id)


def telemetry(run_id: int, tick: int) -> tuple[int, tuple]:
    return P.TELEMETRY, (run_id, tick, 40 * tick, 7500 - tick, 3000, 100, 0, 0)


def run_end(run_id: int, ticks: int, rows: int, reason: int = P.END_DONE) -> tuple:
    return (run_id, reason, ticks, rows, 0, 0, 0, 0, 0, 0, 0)


def test_a_run_takes_only_frames_with_its_id() -> None:
    """The orphan's frames interleave with the run's own (time going backwards): none is recorded."""
    mine, orphan = 0x1234, 0xBEEF
    script = [
        telemetry(orphan, 30),
        (P.STARTED, (mine, P.MODE_FIELD, 40)),
        telemetry(orphan, 31),
        telemetry(mine, 0),
        telemetry(orphan, 32),
        telemetry(mine, 1),
        (P.RUN_END, run_end(orphan, 33, 33)),
        telemetry(mine, 2),
        (P.RUN_END, run_end(mine, 3, 3)),
    ]
    r = Run(FakeLink(script), info(), mine, P.MODE_FIELD, 3).execute()
    assert r.ticks == [0, 1, 2] and r.time_ms == [0, 40, 80] and r.complete
    assert r.foreign_frames == 4 and r.rows_sent == 3


def test_ledger_survives_a_line_torn_by_a_kill(tmp_path: Path) -> None:
    led = Ledger(tmp_path)
    a = led.start("log_30_0", 0, 11, 100, "field")
    led.end(a, "complete", "done", 100, 100, "log_30_0.csv")
    b = led.start("log_30_1", 1, 12, 100, "field")
    with open(tmp_path / LEDGER_NAME, "a") as fh:
        fh.write('{"event": "end", "run": "log_30_1", "run_id": 12, "sta')  # killed mid-write
    again = Ledger(tmp_path)
    assert [e["run"] for e in again.unsettled()] == ["log_30_1"] and again.names() == {"log_30_0", "log_30_1"}
    again.end(b, "lost", "collector died", 40, 0, None, settled_by="next collector")
    lines = (tmp_path / LEDGER_NAME).read_text().splitlines()
    assert json.loads(lines[-1])["rows_lost"] == 40  # the new entry is a line of its own
    assert Ledger(tmp_path).unsettled() == []


def test_ledger_with_foreign_text_is_one_error_naming_the_line(tmp_path: Path) -> None:
    (tmp_path / LEDGER_NAME).write_text('{"event": "start", "run": "a", "run_id": 1}\nhello\n')
    with pytest.raises(ValueError, match=rf"{LEDGER_NAME}: line 2: not a ledger entry"):
        Ledger(tmp_path)


def test_a_log_is_never_replaced_and_follows_the_umask(tmp_path: Path) -> None:
    log = make_log(np.array([10.0, 75.0, 40.0]))
    path = save_new(log, tmp_path, "log_30_0", 0o027)
    assert path.stat().st_mode & 0o777 == 0o640 and (tmp_path / "log_30_0.meta.json").stat().st_mode & 0o777 == 0o640
    before = path.read_bytes(), (tmp_path / "log_30_0.meta.json").read_bytes()
    with pytest.raises(LogExists, match=r"log_30_0\.csv: exists; not replacing it"):
        save_new(make_log(np.array([1.0, 2.0])), tmp_path, "log_30_0", 0o022)
    assert (path.read_bytes(), (tmp_path / "log_30_0.meta.json").read_bytes()) == before
    (tmp_path / "log_30_1.meta.json").write_text("{}")  # a sidecar alone still takes the name
    with pytest.raises(LogExists, match=r"log_30_1\.meta\.json: exists"):
        save_new(log, tmp_path, "log_30_1", 0o022)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["log_30_0.csv", "log_30_0.meta.json", "log_30_1.meta.json"]


def dead_pid() -> int:
    proc = subprocess.run(
        [sys.executable, "-c", "import os; print(os.getpid())"], capture_output=True, text=True, check=True
    )
    return int(proc.stdout)


def test_settle_stops_an_orphan_and_reports_it_lost(tmp_path: Path) -> None:
    led = Ledger(tmp_path)
    led.start("log_30_4", 4, 77, 100, "field")
    link = FakeLink([telemetry(77, 40)], ends={77: run_end(77, 41, 41, P.END_STOPPED)})
    done = settle(link, info(P.RUN_RUNNING, 77), led, tmp_path)
    assert (P.STOP, (77,)) in link.sent
    [e] = done.entries
    assert (e["run"], e["status"], e["rows_sent"], e["rows"], e["rows_lost"], e["file"]) == (
        "log_30_4",
        "lost",
        41,
        0,
        41,
        None,
    )
    tally = Tally()
    tally.add(e)
    assert tally.partial and "0 complete, 0 incomplete, 1 lost run(s)" in tally.line("out")
    assert "0 recorded + 41 lost = 41 sent" in tally.line("out")
    assert settle(FakeLink(), info(P.RUN_ENDED, 77), led, tmp_path).entries == []  # settled once only


def test_settle_recovers_a_log_staged_by_a_collector_killed_before_linking_it(tmp_path: Path) -> None:
    led = Ledger(tmp_path)
    led.start("log_30_2", 2, 99, 3, "field")
    log = make_log(np.array([10.0, 75.0, 40.0]))
    log.meta.provenance = {"brick_run_id": 99, "complete": True}
    write_log(log, tmp_path / f".log_30_2.{dead_pid()}.staging.csv")  # both staged, neither linked
    done = settle(FakeLink(ends={99: run_end(99, 3, 3)}), info(P.RUN_ENDED, 99), led, tmp_path)
    [e] = done.entries
    assert (e["status"], e["rows"], e["rows_lost"], e["file"]) == ("complete", 3, 0, "log_30_2.csv")
    assert len(read_log(tmp_path / "log_30_2.csv")) == 3
    assert remove_stale_staging(tmp_path) == [] and not list(tmp_path.glob(".*"))


def test_settle_a_run_the_brick_never_started_and_one_it_cannot_tell(tmp_path: Path) -> None:
    led = Ledger(tmp_path)
    a = led.start("log_30_0", 0, 1, 10, "field")
    led.end(a, "complete", "done", 10, 10, "log_30_0.csv")
    led.start("log_30_1", 1, 2, 10, "field")  # killed before the START went out
    [e] = settle(FakeLink(), info(P.RUN_ENDED, 1), led, tmp_path).entries
    assert (e["status"], e["rows_sent"], e["rows_lost"]) == ("lost", 0, 0)
    led.start("log_30_2", 2, 3, 10, "field")
    [e] = settle(FakeLink(), info(P.RUN_NONE), led, tmp_path).entries  # the brick rebooted
    assert e["status"] == "lost" and e["rows_sent"] is None and e["rows_lost"] is None
    tally = Tally()
    tally.add(e)
    assert tally.partial and "1 run(s) whose sent rows the brick could not report" in tally.line("out")


def test_first_run_already_used_is_refused_in_one_line(tmp_path: Path, capsys: pytest.CaptureFixture) -> None:
    out = tmp_path / "logs"
    save_new(make_log(np.array([10.0, 75.0])), out, "log_30_3", 0o022)
    Ledger(out).start("log_30_5", 5, 8, 10, "field")
    argv = ["--port", str(tmp_path / "no-brick"), "--out", str(out), "--quiet", "--reconnect", "0"]
    assert collect.main([*argv, "--first-run", "2", "--runs", "2"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    want = f"envi-collect: {out}/log_30_3.csv: exists; not replacing it (leave out --first-run to continue at 6)"
    assert err == [want]
    assert collect.main([*argv, "--first-run", "5"]) == 2
    assert "run 5 was started by an earlier collector" in capsys.readouterr().err
    assert collect.main(argv) == 2  # free indices: it goes on to the brick, which is not there
    assert "cannot open" in capsys.readouterr().err
    # nothing touched (the lock file is the collector's, taken before it reads the ledger)
    assert sorted(os.listdir(out)) == [LEDGER_NAME, LOCK_NAME, "log_30_3.csv", "log_30_3.meta.json"]


def test_a_brick_of_another_protocol_version_is_named_as_such() -> None:
    link = FakeLink()
    link.decoder.other_version = 1  # its HANDSHAKE frames were dropped for their version byte
    with pytest.raises(BrickError, match="the brick speaks protocol 1, this host 2"):
        handshake(link, timeout=0.01, tries=1)
