"""``envi-collect``: record field (or hardware-in-the-loop) logs from a brick over any pyserial URL.

Each run re-handshakes, measures the link with pings, runs for ``--duration`` and is written
atomically with ``envi_py.logs.write_log`` (source ``fot``, or ``hil`` with ``--inject``). A run cut
short by a disconnect or Ctrl-C is still written, marked incomplete in its sidecar; after a
disconnect the port is reopened (a rebooted brick or re-plugged cable) for the next run.
"""

from __future__ import annotations

import argparse
import datetime as _dt
import re
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np
import serial
from tqdm import tqdm

from envi_py import __version__
from envi_py.controllers import ControllerSpec
from envi_py.logs import LANE_KEEPING_SCHEMA, Log, LogMeta, read_log, write_log

from ..brick import protocol as P
from .inject import EnvironmentModel, load_model
from .link import Link, LinkLost
from .session import BrickError, BrickInfo, Run, RunResult, handshake, ping
from .stats import gaps, period_stats, summary


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


def initial_window(model: EnvironmentModel, init_log: Path | None, info: BrickInfo) -> np.ndarray:
    """sigma_0: the first ``history`` rows of ``init_log``, or the robot resting on white."""
    if init_log is not None:
        log = read_log(init_log, min_length=model.history)
        return log.values[:model.history]
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


def provenance(r: RunResult, info: BrickInfo, url: str, clock: dict[str, Any], mismatches: int | None,
               model: EnvironmentModel | None) -> dict[str, Any]:
    rx = _counter_delta(r)
    end = r.end
    brick = None
    if end is not None:
        names = ("run_id", "reason", "ticks", "overruns", "skipped_ticks", "timeouts", "lost_in", "bad_in",
                 "duplicates_in", "late_injects")
        brick = dict(zip(names, end))
    prov: dict[str, Any] = {
        "collector": f"envi-collect {__version__}",
        "collected_at": _dt.datetime.now(_dt.timezone.utc).isoformat(timespec="seconds"),
        "link": url,
        "mode": P.MODE_NAMES[r.mode],
        "complete": r.complete,
        "end_reason": r.end_reason,
        "brick": {"program_hash": info.program_hash, "runtime": info.runtime, "protocol": info.protocol,
                  "period_ms": info.period_ms},
        "ticks_requested": r.n_ticks,
        "rows": len(r.ticks),
        "timing": {"brick_period_ms": period_stats(r.ticks, r.time_ms),
                   "host_arrival_period_ms": period_stats(r.ticks, [t * 1000 for t in r.arrival]),
                   "loop_work_us": summary(r.work_us)},
        "lost_frames": {"brick_to_host": rx["lost"], "host_to_brick": None if brick is None else brick["lost_in"]},
        "crc_errors": {"at_host": rx["crc_errors"], "at_brick": None if brick is None else brick["bad_in"]},
        "malformed_at_host": rx["malformed"],
        "duplicates_at_host": rx["duplicates"],
        "discarded_bytes_at_host": rx["discarded_bytes"],
        "overruns": r.overrun_flags if brick is None else brick["overruns"],
        "skipped_ticks": None if brick is None else brick["skipped_ticks"],
        "gaps": gaps(r.ticks, r.n_ticks if r.complete else (max(r.ticks) + 1 if r.ticks else 0)),
        "clock": {"ping_rtt_ms": summary(clock["rtt_ms"]), "offset_ms": clock["offset_ms"],
                  "pings_lost": clock["lost"]},
        "controller_mismatches": mismatches,
        "brick_report": brick,
    }
    if model is not None:
        rtt = np.asarray(r.hil_rtt_ms)
        prov["hil"] = {"model": model.description, "history": model.history,
                       "timeouts": len(r.timeouts), "timeout_ticks": r.timeouts, "stale": r.stale,
                       "inject_to_action_ms": summary(rtt),
                       "inject_held_at_brick_ms": summary(r.age_ms),
                       "rtt_ms_per_row": [round(float(v), 3) for v in rtt]}
    return prov


def to_log(r: RunResult, info: BrickInfo, url: str, clock: dict[str, Any], run_name: str,
           model: EnvironmentModel | None) -> Log | None:
    if not r.ticks:
        return None
    color = np.asarray(r.color, dtype=np.float64)
    angle = np.asarray(r.angle, dtype=np.float64)
    meta = LogMeta(schema=LANE_KEEPING_SCHEMA, controller=info.controller_json(), period_ms=float(r.period_ms),
                   run_id=run_name, source="fot" if model is None else "hil",
                   provenance=provenance(r, info, url, clock, controller_mismatches(info, color, angle), model))
    return Log(None, np.asarray(r.time_ms, dtype=np.float64), color[:, None], angle[:, None], meta)


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="envi-collect", description=__doc__)
    p.add_argument("--port", required=True, help="pyserial URL: /dev/ttyACM0, socket://ev3dev.local:7777, "
                   "or the path printed by 'envi brick-sim'")
    p.add_argument("--runs", type=int, default=1, help="number of runs (default 1)")
    p.add_argument("--duration", type=parse_duration, default=4.0, help="length of a run, e.g. 4s (default)")
    p.add_argument("--out", type=Path, required=True, help="folder for the logs")
    p.add_argument("--prefix", help="file name prefix (default 'log', or 'hil' with --inject): PREFIX_X_RUN.csv")
    p.add_argument("--first-run", type=int, default=0, help="number of the first run in file names")
    p.add_argument("--inject", help="hardware in the loop: an envi checkpoint (.pt) or 'module:function' "
                   "mapping a window to the next colour")
    p.add_argument("--init-log", type=Path, help="with --inject: sigma_0 from the first rows of this log "
                   "(default: the robot resting on white)")
    p.add_argument("--free-running", action="store_true", help="with --inject: the brick does not wait for "
                   "each colour but uses the newest one and reports its age")
    p.add_argument("--reconnect", type=float, default=10.0, help="seconds to keep reopening a lost port")
    p.add_argument("--pings", type=int, default=10, help="pings per run for round trip and clock offset")
    p.add_argument("--quiet", action="store_true", help="no progress bar")
    return p


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    model = load_model(args.inject) if args.inject else None
    mode = P.MODE_FIELD if model is None else (P.MODE_FREE if args.free_running else P.MODE_LOCKSTEP)
    prefix = args.prefix or ("log" if model is None else "hil")
    link: Link | None = None
    written = incomplete = 0
    bar = tqdm(unit="row", disable=args.quiet, dynamic_ncols=True)  # total known after the first handshake
    try:
        for i in range(args.first_run, args.first_run + args.runs):
            link, info, clock = connect(link, args.port, args.reconnect, args.pings)
            n_ticks = max(1, int(round(args.duration * 1000 / info.period_ms)))
            if bar.total is None:
                bar.reset(total=n_ticks * args.runs)
            bar.set_description(f"run {i - args.first_run + 1}/{args.runs}")
            init = initial_window(model, args.init_log, info) if model is not None else None
            run = Run(link, info, i & 0xFFFF, mode, n_ticks, model, init,
                      silence=max(1.0, 10 * info.period_ms / 1000), on_row=lambda _tick: bar.update(1))
            try:
                r = run.execute()
            except KeyboardInterrupt:
                r = run.result
                _write(r, info, args, prefix, i, clock, model, bar)
                raise
            ok = _write(r, info, args, prefix, i, clock, model, bar)
            written += ok
            incomplete += not r.complete
            if r.end_reason == "disconnect":
                link.close()
                link = None
            bar.update(n_ticks * (i - args.first_run + 1) - bar.n)  # missing rows still count as done
    except KeyboardInterrupt:
        bar.close()
        print("envi-collect: interrupted; the logs written so far are complete files", file=sys.stderr)
        return 130
    except (BrickError, LinkLost) as exc:
        bar.close()
        print(f"envi-collect: {exc}", file=sys.stderr)
        return 2
    finally:
        if link is not None:
            link.close()
    bar.close()
    print(f"envi-collect: {written} log(s) in {args.out}, {incomplete} incomplete", file=sys.stderr)
    return 0


def _write(r: RunResult, info: BrickInfo, args: argparse.Namespace, prefix: str, i: int,
           clock: dict[str, Any], model: EnvironmentModel | None, bar: tqdm) -> bool:
    x = info.params.get("x")
    name = f"{prefix}_{x:g}_{i}" if isinstance(x, float) else f"{prefix}_{i}"  # as the real logs are named
    log = to_log(r, info, args.port, clock, name, model)
    prov = log.meta.provenance if log is not None else {}
    lost = prov.get("lost_frames", {}).get("brick_to_host")
    bar.set_postfix(rows=len(r.ticks), lost=lost, end=r.end_reason)
    if log is None:
        bar.write(f"run {i}: no rows received ({r.end_reason}); nothing written")
        return False
    write_log(log, args.out / f"{name}.csv")
    if not r.complete:
        bar.write(f"run {i}: incomplete ({prov['end_reason']}), {len(r.ticks)} of {r.n_ticks} rows written")
    return True


if __name__ == "__main__":
    sys.exit(main())
