"""``envi-collect``: record field (or hardware-in-the-loop) logs from a brick over any pyserial URL.

Each run re-handshakes, measures the link with pings, runs for ``--duration`` and is written
atomically, never over an existing file, with the process umask (source ``fot``, or ``hil`` with
``--inject``). A run cut short by a disconnect or Ctrl-C is still written, marked incomplete in its
sidecar; after a disconnect the port is reopened (a rebooted brick or re-plugged cable) for the
next run. Every run is in the folder's ledger (``collect-ledger.jsonl``) before the brick starts
it, so a collector restarted after being killed stops the run the dead one left going, reports it
lost (or recovers its log if it was written), and carries on at the next free index. A second
collector on an ``--out`` in use is refused at once (``collect.lock`` there). The exit code is 2
when a run was lost or incomplete or rows were lost, unless ``--accept-partial``.
"""

from __future__ import annotations

import argparse
import datetime as _dt
import os
import re
import secrets
import sys
import time
from pathlib import Path
from typing import Any, Sequence

import numpy as np
import serial
from tqdm import tqdm

from envi_py import __version__
from envi_py.cli_parser import EnviParser
from envi_py.controllers import ControllerSpec
from envi_py.interrupt import exit_code, signals_interrupt
from envi_py.logs import LANE_KEEPING_SCHEMA, Log, LogMeta, read_log

from ..brick import protocol as P
from .inject import EnvironmentModel, load_model
from .ledger import LEDGER_NAME, Ledger
from .link import Link, LinkLost
from .lock import FolderBusy, hold
from .session import BrickError, BrickInfo, Run, RunResult, handshake, ping
from .settle import settle
from .stats import gaps, period_stats, summary
from .store import (
    LogExists,
    process_umask,
    remove_stale_staging,
    save_new,
    taken,
    used_indices,
)
from .tally import Tally


def parse_duration(text: str) -> float:
    """``4s``, ``4000ms``, ``1.5min`` or a bare number of seconds -> seconds."""
    m = re.fullmatch(r"\s*([0-9.]+)\s*(ms|s|min)?\s*", text)
    if not m:
        raise argparse.ArgumentTypeError(f"duration {text!r}: expected e.g. 4s, 4000ms or 1min")
    value = float(m.group(1))
    return value * {"ms": 0.001, "s": 1.0, "min": 60.0, None: 1.0}[m.group(2)]


def open_link(url: str, wait: float) -> Link:
    """Open the port, retrying for ``wait`` seconds (a brick that reboots takes a moment)."""
    end = time.monotonic() + wait
    while True:
        try:
            return Link(url)
        except (serial.SerialException, OSError) as exc:
            if "exclusively lock" in str(exc):  # pyserial's only sign of it: waiting will not help
                raise BrickError(f"{url}: another program has the port open (another envi-collect?)") from None
            if time.monotonic() >= end:
                raise BrickError(f"{url}: cannot open ({exc})") from exc
            time.sleep(0.2)


def connect(link: Link | None, url: str, wait: float, pings: int) -> tuple[Link, BrickInfo, dict[str, Any]]:
    """(Re)open the link if needed, handshake and ping; a link lost on the way is opened again."""
    for attempt in range(3):
        try:
            if link is None:
                link = open_link(url, wait)
            return link, handshake(link), ping(link, pings)
        except LinkLost:
            link.close()
            link = None
    raise BrickError(f"{url}: the link keeps dropping during the handshake")


def initial_window(model: EnvironmentModel, init_rows: np.ndarray | None, info: BrickInfo) -> np.ndarray:
    """sigma_0: ``init_rows`` (the first ``history`` rows of ``--init-log``), or the robot resting on white."""
    if init_rows is not None:
        return init_rows
    x = float(info.params.get("x", 0.0))
    return np.tile([[75.0, x]], (model.history, 1))


def controller_mismatches(info: BrickInfo, color: np.ndarray, angle: np.ndarray) -> int | None:
    """Rows whose angle differs from envi's own controller applied to the colour (None: unknown one)."""
    try:
        ctrl = ControllerSpec(info.controller, info.params).build()
    except ValueError:
        return None
    if color.size == 0:
        return 0
    ctrl.reset(1)
    want = np.concatenate([ctrl(c.reshape(1, 1)) for c in color]).ravel()
    return int(np.sum(np.abs(want - angle) > 1e-6))


def _counter_delta(r: RunResult) -> dict[str, int]:
    return {k: r.link_after[k] - r.link_before.get(k, 0) for k in r.link_after}


def provenance(
    r: RunResult,
    info: BrickInfo,
    url: str,
    clock: dict[str, Any],
    mismatches: int | None,
    model: EnvironmentModel | None,
) -> dict[str, Any]:
    rx = _counter_delta(r)
    end = r.end
    brick = None
    if end is not None:
        names = (
            "run_id",
            "reason",
            "ticks",
            "rows",
            "overruns",
            "skipped_ticks",
            "timeouts",
            "lost_in",
            "bad_in",
            "duplicates_in",
            "late_injects",
        )
        brick = dict(zip(names, end))
    prov: dict[str, Any] = {
        "collector": f"envi-collect {__version__}",
        "collected_at": _dt.datetime.now(_dt.timezone.utc).isoformat(timespec="seconds"),
        "link": url,
        "mode": P.MODE_NAMES[r.mode],
        "brick_run_id": r.run_id,
        "complete": r.complete,
        "end_reason": r.end_reason,
        "brick": {
            "program_hash": info.program_hash,
            "runtime": info.runtime,
            "protocol": info.protocol,
            "period_ms": info.period_ms,
        },
        "ticks_requested": r.n_ticks,
        "rows": len(r.ticks),
        "rows_sent": r.rows_sent,
        "rows_lost": None if r.rows_sent is None else r.rows_sent - len(r.ticks),
        "foreign_frames_at_host": r.foreign_frames,
        "timing": {
            "brick_period_ms": period_stats(r.ticks, r.time_ms),
            "host_arrival_period_ms": period_stats(r.ticks, [t * 1000 for t in r.arrival]),
            "loop_work_us": summary(r.work_us),
        },
        "lost_frames": {"brick_to_host": rx["lost"], "host_to_brick": None if brick is None else brick["lost_in"]},
        "crc_errors": {"at_host": rx["crc_errors"], "at_brick": None if brick is None else brick["bad_in"]},
        "malformed_at_host": rx["malformed"],
        "duplicates_at_host": rx["duplicates"],
        "discarded_bytes_at_host": rx["discarded_bytes"],
        "overruns": r.overrun_flags if brick is None else brick["overruns"],
        "skipped_ticks": None if brick is None else brick["skipped_ticks"],
        "gaps": gaps(r.ticks, r.n_ticks if r.complete else (max(r.ticks) + 1 if r.ticks else 0)),
        "clock": {
            "ping_rtt_ms": summary(clock["rtt_ms"]),
            "offset_ms": clock["offset_ms"],
            "pings_lost": clock["lost"],
        },
        "controller_mismatches": mismatches,
        "brick_report": brick,
    }
    if model is not None:
        rtt = np.asarray(r.hil_rtt_ms)
        prov["hil"] = {
            "model": model.description,
            "history": model.history,
            "timeouts": len(r.timeouts),
            "timeout_ticks": r.timeouts,
            "stale": r.stale,
            "inject_to_action_ms": summary(rtt),
            "inject_held_at_brick_ms": summary(r.age_ms),
            "rtt_ms_per_row": [round(float(v), 3) for v in rtt],
        }
    return prov


def row_breaks(ticks: Sequence[int]) -> tuple[int, ...]:
    """The rows whose tick does not follow the previous row's: rows are missing between the two (a
    frame lost on the link, a tick the brick skipped, or a lock-step tick never sent), so training
    keeps its windows off the gap (:attr:`envi_py.logs.LogMeta.breaks`)."""
    return tuple(i for i in range(1, len(ticks)) if ticks[i] != ticks[i - 1] + 1)


def to_log(
    r: RunResult, info: BrickInfo, url: str, clock: dict[str, Any], run_name: str, model: EnvironmentModel | None
) -> Log | None:
    if not r.ticks:
        return None
    color = np.asarray(r.color, dtype=np.float64)
    angle = np.asarray(r.angle, dtype=np.float64)
    meta = LogMeta(
        schema=LANE_KEEPING_SCHEMA,
        controller=info.controller_json(),
        period_ms=float(r.period_ms),
        run_id=run_name,
        source="fot" if model is None else "hil",
        provenance=provenance(r, info, url, clock, controller_mismatches(info, color, angle), model),
        breaks=row_breaks(r.ticks),
    )
    return Log(None, np.asarray(r.time_ms, dtype=np.float64), color[:, None], angle[:, None], meta)


def build_parser() -> argparse.ArgumentParser:
    p = EnviParser(prog="envi-collect", description=__doc__)
    p.add_argument(
        "--port",
        required=True,
        help="pyserial URL: /dev/ttyACM0, socket://ev3dev.local:7777, or the path printed by 'envi brick-sim'",
    )
    p.add_argument("--runs", type=int, default=1, help="number of runs (default 1)")
    p.add_argument("--duration", type=parse_duration, default=4.0, help="length of a run, e.g. 4s (default)")
    p.add_argument("--out", type=Path, required=True, help="folder for the logs")
    p.add_argument("--prefix", help="file name prefix (default 'log', or 'hil' with --inject): PREFIX_X_RUN.csv")
    p.add_argument(
        "--first-run",
        type=int,
        help="number of the first run in file names (default: the next "
        "one free in --out); a number already used is refused, never overwritten",
    )
    p.add_argument(
        "--inject",
        help="hardware in the loop: an envi checkpoint (.pt) or 'module:function' mapping a window to the next colour",
    )
    p.add_argument(
        "--init-log",
        type=Path,
        help="with --inject: sigma_0 from the first rows of this log (default: the robot resting on white)",
    )
    p.add_argument(
        "--free-running",
        action="store_true",
        help="with --inject: the brick does not wait for each colour but uses the newest one and reports its age",
    )
    p.add_argument("--reconnect", type=float, default=10.0, help="seconds to keep reopening a lost port")
    p.add_argument("--pings", type=int, default=10, help="pings per run for round trip and clock offset")
    p.add_argument(
        "--accept-partial",
        action="store_true",
        help="exit 0 even when runs were lost or incomplete or rows were lost (what was recorded is kept either way)",
    )
    p.add_argument("--quiet", action="store_true", help="no progress bar")
    return p


def run_name(prefix: str, info: BrickInfo, index: int) -> str:
    """``PREFIX_X_INDEX`` as the real logs are named (``PREFIX_INDEX`` for a controller without x)."""
    x = info.params.get("x")
    return f"{prefix}_{x:g}_{index}" if isinstance(x, float) else f"{prefix}_{index}"


def first_index(args: argparse.Namespace, prefix: str, ledger: Ledger) -> int:
    """Where numbering starts: the next free index, or ``--first-run`` if none of its indices is used."""
    used = used_indices(args.out, prefix, ledger.names())
    free = max(used) + 1 if used else 0
    if args.first_run is None:
        return free
    for i in range(args.first_run, args.first_run + args.runs):
        if i in used:
            name = used[i]
            path = taken(args.out, name)
            what = (
                f"{path}: exists"
                if path is not None
                else f"{args.out / name}.csv: run {i} was started by an earlier collector (see {LEDGER_NAME})"
            )
            raise LogExists(f"{what}; not replacing it (leave out --first-run to continue at {free})")
    return args.first_run


def new_run_id(ledger: Ledger, info: BrickInfo) -> int:
    """A 32-bit run id used by no run in the ledger nor by the brick's latest run (0 is never used)."""
    taken_ids = ledger.run_ids() | {0, info.run_id}
    while (rid := secrets.randbits(32)) in taken_ids:
        pass
    return rid


class Session:
    """The runs of one invocation: each is in the ledger before it starts and settled after it ends."""

    def __init__(self, args: argparse.Namespace, model: EnvironmentModel | None, bar: tqdm) -> None:
        self.args = args
        self.model = model
        # read before the ledger is touched: a bad --init-log is refused with nothing reserved
        self.init_rows = (
            read_log(args.init_log, min_length=model.history).values[: model.history]
            if model is not None and args.init_log is not None
            else None
        )
        self.bar = bar
        self.mode = P.MODE_FIELD if model is None else (P.MODE_FREE if args.free_running else P.MODE_LOCKSTEP)
        self.prefix = args.prefix or ("log" if model is None else "hil")
        self.umask = process_umask()
        self.ledger = Ledger(args.out)
        self.tally = Tally()
        self.link: Link | None = None

    def _settle(self, info: BrickInfo) -> None:
        """Stop whatever run the brick is in and settle what earlier collectors left (see settle.py)."""
        assert self.link is not None
        done = settle(self.link, info, self.ledger, self.args.out)
        for e in done.entries:
            self.tally.add(e)
            rows = "an unknown number of" if e["rows_sent"] is None else e["rows_sent"]
            self.bar.write(
                f"{e['run']}: left unsettled by an earlier collector: {e['status']} "
                f"({rows} row(s) sent, {e['rows']} recorded)"
            )
        if done.foreign is not None:
            rid, sent = done.foreign
            self.bar.write(
                f"stopped run {rid}, which another collector (not of {self.args.out}) left running; "
                f"{'its' if sent is None else sent} row(s) are not recorded here"
            )

    def _connect(self) -> tuple[BrickInfo, dict[str, Any]]:
        """Handshake, ping and settle; a link lost while settling is opened again, as in :func:`connect`."""
        for _ in range(3):
            self.link, info, clock = connect(self.link, self.args.port, self.args.reconnect, self.args.pings)
            try:
                self._settle(info)
                return info, clock
            except LinkLost:
                self.link.close()
                self.link = None
        raise BrickError(f"{self.args.port}: the link keeps dropping while settling earlier runs")

    def run_all(self) -> None:
        args = self.args
        first = first_index(args, self.prefix, self.ledger)  # a used --first-run is refused before any contact
        for n in range(args.runs):
            info, clock = self._connect()
            if n == 0:
                remove_stale_staging(args.out)  # after settling, which may finish a dead collector's staging
            n_ticks = round(args.duration * 1000 / info.period_ms)
            if n_ticks < 1:  # before the run is reserved: a run of no rows would only be "lost"
                raise ValueError(f"--duration {args.duration:g} s is shorter than one tick ({info.period_ms} ms)")
            if self.bar.total is None:
                self.bar.reset(total=n_ticks * args.runs)
            self.bar.set_description(f"run {n + 1}/{args.runs}")
            name = run_name(self.prefix, info, first + n)
            init = initial_window(self.model, self.init_rows, info) if self.model is not None else None
            start = self.ledger.start(name, first + n, new_run_id(self.ledger, info), n_ticks, P.MODE_NAMES[self.mode])
            run = Run(
                self.link,
                info,
                start["run_id"],
                self.mode,
                n_ticks,
                self.model,
                init,
                silence=max(1.0, 10 * info.period_ms / 1000),
                on_row=lambda _tick: self.bar.update(1),
            )
            try:
                r = run.execute()
            except KeyboardInterrupt:
                self._record(run.result, start, info, clock)
                raise
            self._record(r, start, info, clock)
            if r.end_reason == "disconnect":
                self.link.close()
                self.link = None
            self.bar.update(n_ticks * (n + 1) - self.bar.n)  # missing rows still count as done

    def _record(self, r: RunResult, start: dict[str, Any], info: BrickInfo, clock: dict[str, Any]) -> None:
        """Write the run's log (if it has rows) under its reserved name, then settle it in the ledger."""
        name = start["run"]
        log = to_log(r, info, self.args.port, clock, name, self.model)
        file = None if log is None else save_new(log, self.args.out, name, self.umask).name
        status = "lost" if log is None else ("complete" if r.complete else "incomplete")
        entry = self.ledger.end(start, status, r.end_reason, r.rows_sent, len(r.ticks), file)
        self.tally.add(entry)
        self.bar.set_postfix(rows=len(r.ticks), lost=entry["rows_lost"], end=r.end_reason)
        lost = "an unknown number" if entry["rows_lost"] is None else entry["rows_lost"]
        if log is None:
            self.bar.write(f"{name}: no rows received ({r.end_reason}); nothing written, {lost} row(s) lost")
        elif status == "incomplete" or entry["rows_lost"] != 0:
            self.bar.write(
                f"{name}: {status} ({r.end_reason}), {len(r.ticks)} of {r.n_ticks} rows written, {lost} row(s) lost"
            )

    def close(self) -> None:
        if self.link is not None:
            self.link.close()


def checked_args(parser: argparse.ArgumentParser, argv: list[str] | None) -> argparse.Namespace:
    """The options, refused with argparse's one line before the port is opened (``--runs 0`` once
    exited 0 having recorded nothing, ``--prefix a/b`` named files outside --out)."""
    args = parser.parse_args(argv)
    if args.runs < 1:
        parser.error(f"--runs must be at least 1, got {args.runs}")
    if args.pings < 1:
        parser.error(f"--pings must be at least 1, got {args.pings}")
    if args.inject is None and (args.init_log is not None or args.free_running):
        parser.error("--init-log and --free-running apply to hardware in the loop only: give --inject too")
    if not 0 < args.duration <= 86_400:  # a run of 0 s once wrote a one-row log no command could use
        parser.error(f"--duration must be more than 0 s and at most a day, got {args.duration:g} s")
    if not 0 <= args.reconnect <= 86_400:  # NaN fails too
        parser.error(f"--reconnect is a number of seconds in 0..86400, got {args.reconnect}")
    if args.first_run is not None and args.first_run < 0:
        parser.error(f"--first-run must be at least 0, got {args.first_run}")
    if args.prefix is not None and (not args.prefix or Path(args.prefix).name != args.prefix):
        parser.error(f"--prefix must be a plain file name prefix, got {args.prefix!r}")
    if args.out.exists() and not args.out.is_dir():
        parser.error(f"--out {args.out}: exists and is not a folder")
    return args


def main(argv: list[str] | None = None) -> int:
    args = checked_args(build_parser(), argv)
    # total known after the first handshake; shown after 1 s, so a port refused at once leaves one line
    bar = tqdm(unit="row", disable=args.quiet, dynamic_ncols=True, delay=1.0)
    session: Session | None = None
    lock: int | None = None
    code = 0
    interrupted = False
    try:
        with signals_interrupt():  # kill and a closed terminal record the current run as Ctrl-C does
            lock = hold(args.out)  # before the ledger is read or the port opened: both are the holder's
            session = Session(args, load_model(args.inject) if args.inject else None, bar)
            session.run_all()
    except KeyboardInterrupt as exc:
        code = exit_code(exc)
        interrupted = True
    except (FolderBusy, BrickError, LinkLost, ValueError, OSError) as exc:  # LogExists, a bad ledger: ValueErrors
        bar.close()
        print(f"envi-collect: {exc}", file=sys.stderr)
        code = 2
    finally:
        if session is not None:
            session.close()
        if lock is not None:
            os.close(lock)
    bar.close()
    if session is None or (code == 2 and not session.tally.runs):
        return code  # refused before any run: the one error line says it all
    tally = session.tally
    if interrupted:
        print("envi-collect: interrupted; the logs written so far are complete files", file=sys.stderr)
    print(f"envi-collect: {tally.line(str(args.out))}", file=sys.stderr)
    if code == 0 and tally.partial and not args.accept_partial:
        code = 2
    return code


if __name__ == "__main__":
    sys.exit(main())
