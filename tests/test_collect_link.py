"""envi-collect when the serial device vanishes in a way pyserial's reader thread does not expect.

pyserial 3.5's ``serial.threaded.ReaderThread`` catches only ``SerialException``; on a device that
goes away, ``in_waiting`` (an ioctl) can raise a bare ``OSError`` instead (about 1 brick kill in
15). The run must then end as a disconnect, with its rows kept, not as a silent brick after the
reader thread died with a traceback.
"""

from __future__ import annotations

import errno
import threading
from pathlib import Path

import pytest
import serial

from envi_py.logs import read_log
from firmware_bridge.host import collect
from firmware_bridge.host.session import Run

from .test_bridge_pty import BrickSim, check_rows_follow_controller, ledger_ends

VANISH_AT = 20  # rows recorded before the device goes away


@pytest.mark.filterwarnings("error::pytest.PytestUnhandledThreadExceptionWarning")  # a dead reader thread
def test_in_waiting_raising_oserror_mid_run_ends_it_as_a_disconnect(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, capfd: pytest.CaptureFixture
) -> None:
    vanished = threading.Event()
    real_in_waiting = serial.Serial.in_waiting
    real_telemetry = Run._telemetry

    def in_waiting(port: serial.Serial) -> int:
        if vanished.is_set():
            raise OSError(errno.EIO, "Input/output error")  # the ioctl on a device that is gone
        return real_in_waiting.fget(port)

    def telemetry(run: Run, t: float, fields: tuple[int, ...]) -> None:
        real_telemetry(run, t, fields)
        if len(run.result.ticks) >= VANISH_AT:
            vanished.set()

    monkeypatch.setattr(serial.Serial, "in_waiting", property(in_waiting))
    monkeypatch.setattr(Run, "_telemetry", telemetry)
    sim = BrickSim(tmp_path, "--world", "firmware_bridge.host.world:EdgeWorld")
    out = tmp_path / "logs"
    try:
        rc = collect.main(["--port", str(sim.link), "--duration", "4s", "--out", str(out), "--quiet"])
    finally:
        sim.stop()
    said = capfd.readouterr()
    text = said.out + said.err  # the per-run line goes through tqdm.write (stdout)
    assert rc == 2 and "Traceback" not in text and "Exception in thread" not in text, text
    assert "log_30_0: incomplete (disconnect)" in text, text
    log = read_log(out / "log_30_0.csv")
    prov = log.meta.provenance
    assert prov["end_reason"] == "disconnect" and not prov["complete"]
    assert VANISH_AT <= len(log) < 100  # everything that arrived before the link went is kept
    check_rows_follow_controller(log)
    end = ledger_ends(out)["log_30_0"]
    assert (end["status"], end["reason"], end["rows"], end["file"]) == (
        "incomplete",
        "disconnect",
        len(log),
        "log_30_0.csv",
    )


def test_the_collector_marks_a_break_after_each_lost_tick():
    assert collect.row_breaks([0, 1, 2, 3]) == ()
    assert collect.row_breaks([2, 3, 5, 6, 9]) == (2, 4)  # a late first tick is no break: nothing precedes it
