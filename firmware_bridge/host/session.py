"""One conversation with a brick: handshake, clock pings, and one run in any mode.

Everything measured on the way is returned in :class:`RunResult` for the sidecar; nothing is
written here. A run ends when the brick reports RUN_END, the link is lost, the brick stays silent
for ``silence`` seconds, or the caller is interrupted; rows received until then are kept. Only
frames that carry this run's id are its rows: frames of any other run (one a dead collector left
running on the brick) are counted and dropped, never appended.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from ..brick import protocol as P
from .inject import EnvironmentModel, reset
from .link import Link, LinkLost


class BrickError(Exception):
    """The brick did not answer as the protocol says (no handshake, wrong version)."""


@dataclass
class BrickInfo:
    protocol: int
    period_ms: int
    program_hash: str
    runtime: str
    controller: str
    params: dict[str, float | str]
    run_state: int = P.RUN_NONE  # the brick's latest run when it answered: none, running or ended
    run_id: int = 0  # that run's id (meaningless with RUN_NONE)

    def controller_json(self) -> dict[str, Any]:
        return {"name": self.controller, "params": dict(self.params)}


def _params(text: str) -> dict[str, float | str]:
    out: dict[str, float | str] = {}
    for item in filter(None, text.split(";")):
        k, _, v = item.partition("=")
        try:
            out[k] = float(v)
        except ValueError:
            out[k] = v
    return out


def handshake(link: Link, timeout: float = 2.0, tries: int = 3) -> BrickInfo:
    """HELLO until a HANDSHAKE comes back; messages from an earlier conversation are skipped."""
    for _ in range(tries):
        link.send(P.HELLO, ())
        end = time.perf_counter() + timeout
        while (left := end - time.perf_counter()) > 0:
            got = link.recv(left)
            if got is None:
                break
            msg = got[1]
            if msg.type == P.HANDSHAKE:
                version, period, state, run_id, phash, runtime, name, params = msg.fields
                return BrickInfo(version, period, phash, runtime, name, _params(params), state, run_id)
    other = link.decoder.other_version
    if other is not None:  # its frames were dropped as malformed: say why rather than "no answer"
        raise BrickError(
            f"{link.url}: the brick speaks protocol {other}, this host {P.VERSION}; "
            "update the brick program or the host"
        )
    raise BrickError(f"{link.url}: no handshake from the brick after {tries} tries")


def stop_run(
    link: Link,
    run_id: int,
    tries: int = 3,
    wait: float = 0.3,
    on_message: Callable[[float, P.Message], None] | None = None,
) -> tuple[int, ...] | None:
    """STOP ``run_id`` until its RUN_END comes back (the brick repeats it for an ended run); None if not.

    Other messages on the way (the run's last frames) go to ``on_message``, else are skipped.
    ``LinkLost`` propagates: the caller decides.
    """
    for _ in range(tries):
        link.send(P.STOP, (run_id,))
        end = time.perf_counter() + wait
        while (left := end - time.perf_counter()) > 0:
            got = link.recv(left)
            if got is None:
                break
            if got[1].type == P.RUN_END and got[1].fields[0] == run_id:
                return got[1].fields
            if on_message is not None:
                on_message(*got)
    return None


def ping(link: Link, count: int = 10, timeout: float = 0.5) -> dict[str, Any]:
    """Round-trip times (ms) and the brick clock's offset from the host's (ms, at the fastest ping)."""
    rtts: list[float] = []
    best: tuple[float, float] | None = None
    for nonce in range(count):
        sent = link.send(P.PING, (nonce,))
        end = sent + timeout
        while (left := end - time.perf_counter()) > 0:
            got = link.recv(left)
            if got is None:
                break
            t, msg = got
            if msg.type == P.PONG and msg.fields[0] == nonce:
                rtt = (t - sent) * 1000
                rtts.append(rtt)
                mid_host_ms = link.host_ms((sent + t) / 2)
                if best is None or rtt < best[0]:
                    best = (rtt, msg.time - mid_host_ms)
                break
    return {"rtt_ms": rtts, "offset_ms": None if best is None else round(best[1], 3), "lost": count - len(rtts)}


@dataclass
class RunResult:
    run_id: int
    mode: int
    n_ticks: int
    period_ms: int
    ticks: list[int] = field(default_factory=list)
    time_ms: list[int] = field(default_factory=list)
    color: list[float] = field(default_factory=list)
    angle: list[float] = field(default_factory=list)
    work_us: list[int] = field(default_factory=list)
    age_ms: list[int] = field(default_factory=list)
    arrival: list[float] = field(default_factory=list)
    hil_rtt_ms: list[float] = field(default_factory=list)  # INJECT(k) sent -> TELEMETRY(k) received
    overrun_flags: int = 0
    timeouts: list[int] = field(default_factory=list)
    stale: int = 0
    foreign_frames: int = 0  # frames of another run (another collector's), dropped
    end: tuple[int, ...] | None = None
    end_reason: str = "done"
    link_before: dict[str, int] = field(default_factory=dict)
    link_after: dict[str, int] = field(default_factory=dict)

    @property
    def complete(self) -> bool:
        return self.end is not None and self.end[1] == P.END_DONE and self.end_reason == "done"

    @property
    def rows_sent(self) -> int | None:
        """Rows the brick sent in this run (its RUN_END says so); None when that never arrived."""
        return None if self.end is None else self.end[3]


class Run:
    """Drives one run; ``model`` is None for a field run, else it supplies the injected colours."""

    def __init__(
        self,
        link: Link,
        info: BrickInfo,
        run_id: int,
        mode: int,
        n_ticks: int,
        model: EnvironmentModel | None = None,
        init_window: np.ndarray | None = None,
        silence: float = 1.0,
        on_row: Callable[[int], None] | None = None,
    ) -> None:
        self.link = link
        self.info = info
        self.model = model
        self.window = None if init_window is None else np.array(init_window, dtype=np.float64)
        self.silence = silence
        self.on_row = on_row
        self.result = RunResult(run_id, mode, n_ticks, info.period_ms)
        self._sent: dict[int, float] = {}

    def _inject(self, tick: int) -> None:
        """Predict the colour for ``tick`` from the window and send it (x100, as the wire has it)."""
        assert self.model is not None and self.window is not None
        color = min(100.0, max(0.0, self.model(self.window)))
        self._sent[tick] = self.link.send(P.INJECT, (self.result.run_id, tick, round(color * 100)))

    def execute(self) -> RunResult:
        r = self.result
        r.link_before = self.link.decoder.counters()
        try:
            self.link.send(P.START, (r.run_id, r.mode, r.n_ticks, 0, 0))
            self._loop()
        except LinkLost:
            r.end_reason = "disconnect"
        except KeyboardInterrupt:
            r.end_reason = "interrupted"
            self._stop()
            raise
        finally:
            r.link_after = self.link.decoder.counters()
        return r

    def _stop(self) -> None:
        """Ask the brick to stop (a STOP also makes it repeat a RUN_END the host missed)."""

        def keep_rows(t: float, msg: P.Message) -> None:  # frames sent before the brick saw the STOP
            if msg.type == P.TELEMETRY and msg.fields[0] == self.result.run_id:
                self._telemetry(t, msg.fields[1:])

        try:
            end = stop_run(self.link, self.result.run_id, on_message=keep_rows)
        except LinkLost:
            return
        if end is not None:
            self.result.end = end

    def _loop(self) -> None:
        r = self.result
        started = False
        if self.model is not None:
            reset(self.model)
        starts = 1
        while True:
            got = self.link.recv(self.silence)
            if got is None:
                if not started and starts < 3:  # the START or its answer was lost: ask again
                    self.link.send(P.START, (r.run_id, r.mode, r.n_ticks, 0, 0))
                    starts += 1
                    continue
                if started:
                    self._stop()  # maybe only the RUN_END got lost
                r.end_reason = "silent" if r.end is None else r.end_reason
                return
            t, msg = got
            if msg.type in (P.STARTED, P.TELEMETRY, P.RUN_END) and msg.fields[0] != r.run_id:
                r.foreign_frames += 1  # another run's (one a dead collector left running): never ours
            elif msg.type == P.STARTED and not started:
                started = True
                r.period_ms = msg.fields[2]
                if self.model is not None:
                    self._inject(0)
            elif msg.type == P.TELEMETRY:
                started = True  # the STARTED frame itself may have been lost
                self._telemetry(t, msg.fields[1:])
            elif msg.type == P.RUN_END:
                r.end = msg.fields
                return

    def _telemetry(self, t: float, fields: tuple[int, ...]) -> None:
        r = self.result
        tick, stamp, color_c, angle_c, work, flags, age = fields
        if flags & P.FLAG_OVERRUN:
            r.overrun_flags += 1
        if flags & P.FLAG_TIMEOUT:
            r.timeouts.append(tick)
        else:
            color, angle = color_c / 100.0, angle_c / 100.0
            r.ticks.append(tick)
            r.time_ms.append(stamp)
            r.color.append(color)
            r.angle.append(angle)
            r.work_us.append(work)
            r.age_ms.append(age)
            r.arrival.append(t)
            if flags & P.FLAG_STALE:
                r.stale += 1
            if tick in self._sent:
                r.hil_rtt_ms.append((t - self._sent[tick]) * 1000)
            if self.window is not None:
                self.window = np.concatenate([self.window[1:], [[color, angle]]])
            if self.on_row is not None:
                self.on_row(tick)
        if self.model is not None and tick + 1 < r.n_ticks:
            self._sent = {k: v for k, v in self._sent.items() if k > tick}
            self._inject(tick + 1)
