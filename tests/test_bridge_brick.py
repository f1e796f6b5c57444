"""The brick program's timing logic under a fake clock: deadlines, overruns, lock-step timeouts."""

from __future__ import annotations

import heapq
import itertools

import pytest

from firmware_bridge.brick import protocol as P
from firmware_bridge.brick.control import LaneKeeping
from firmware_bridge.brick.program import Brick
from firmware_bridge.brick.ticker import Ticker


def diff(a: int, b: int) -> int:
    return a - b


def add(a: int, b: int) -> int:
    return a + b


class Clock:
    def __init__(self) -> None:
        self.now = 1000

    def ms(self) -> int:
        return self.now

    def us(self) -> int:
        return self.now * 1000


def test_deadlines_do_not_drift() -> None:
    """Late wake-ups and work time delay only their own tick: tick k is always due at t0 + 40k."""
    tk = Ticker(40, 0, diff, add)
    now = 0
    for k in range(100):
        assert tk.tick == k and tk.deadline == 40 * k
        now = max(now, tk.deadline) + (k % 7) * 3  # woke late by up to 18 ms, plus work
        assert not tk.advance(now + 5)
    assert tk.overruns == 0 and tk.skipped == 0


def test_overrun_and_skip_keep_the_phase() -> None:
    tk = Ticker(40, 0, diff, add)
    assert tk.advance(45)  # tick 0 ended 5 ms after tick 1 was due: overrun, tick 1 runs late
    assert (tk.tick, tk.deadline, tk.overruns, tk.skipped) == (1, 40, 1, 0)
    assert tk.wait_ms(45) == 0
    assert tk.advance(170)  # tick 1 ended at 170: ticks 2 and 3 (due 80, 120) are skipped
    assert (tk.tick, tk.deadline, tk.overruns, tk.skipped) == (4, 160, 2, 2)
    assert tk.wait_ms(170) == 0 and tk.since_t0(170) == 170
    assert not tk.advance(199)
    assert tk.deadline == 200 and tk.wait_ms(199) == 1


class Hardware:
    """Colour from a list; steering takes ``slow[k]`` ms on chosen ticks (to force overruns)."""

    def __init__(self, clock: Clock, slow: dict[int, int] | None = None) -> None:
        self.clock, self.slow, self.reads, self.steered = clock, slow or {}, 0, []

    def reset(self, seed: int) -> None:
        self.reads = 0

    def read_color(self) -> float:
        self.reads += 1
        return [10, 75, 40, 39, 41][self.reads % 5]

    def steer(self, angle: float) -> None:
        self.clock.now += self.slow.get(len(self.steered), 0)
        self.steered.append(angle)


class ScriptedHost:
    """A fake link driven by the fake clock: answers each telemetry k with INJECT(k+1) after
    ``delay`` ms, except for ticks in ``withhold`` (to force lock-step timeouts)."""

    def __init__(self, clock: Clock, delay: int = 2, withhold: frozenset[int] = frozenset(), late: int = 0) -> None:
        self.clock, self.delay, self.withhold, self.late = clock, delay, withhold, late
        self.enc, self.dec = P.Encoder(), P.Decoder()
        self.queue: list[tuple[int, int, bytes]] = []
        self.sent: list[P.Message] = []
        self.n = 0
        self.tx_dropped = 0

    def push(self, at: int, mtype: int, fields: tuple) -> None:
        self.n += 1
        heapq.heappush(self.queue, (at, self.n, self.enc.encode(mtype, fields, at)))

    def colour(self, k: int) -> int:
        return [1000, 7500, 4000, 3999, 4001, 5550][k % 6]

    def wait(self, timeout_ms: int) -> bool:
        if self.queue and self.queue[0][0] <= self.clock.now + timeout_ms:
            self.clock.now = max(self.clock.now, self.queue[0][0])
            return True
        self.clock.now += timeout_ms
        return False

    def read(self) -> bytes:
        out = b""
        while self.queue and self.queue[0][0] <= self.clock.now:
            out += heapq.heappop(self.queue)[2]
        return out

    def write(self, data: bytes) -> None:
        for m in self.dec.feed(data):
            self.sent.append(m)
            nxt = m.fields[1] + 1 if m.type == P.TELEMETRY else 0 if m.type == P.STARTED else None
            if nxt is not None and nxt not in self.withhold:
                delay = self.delay + (self.late if nxt in self.withhold else 0)
                self.push(self.clock.now + delay, P.INJECT, (m.fields[0], nxt, self.colour(nxt)))

    def of(self, mtype: int) -> list[tuple]:
        """Fields of every frame of that type the brick sent (TELEMETRY without its run id)."""
        return [m.fields[1:] if mtype == P.TELEMETRY else m.fields for m in self.sent if m.type == mtype]

    def run_ids(self, mtype: int) -> set[int]:
        return {m.fields[0] for m in self.sent if m.type == mtype}


def make(mode_host: ScriptedHost, clock: Clock, hw: Hardware) -> Brick:
    return Brick(mode_host, hw, LaneKeeping(30), 40, "hash", "test", clock.ms, clock.us, diff)


def test_field_run_is_on_time_and_reports_overruns() -> None:
    clock = Clock()
    host = ScriptedHost(clock, withhold=frozenset(range(1000)))
    hw = Hardware(clock, slow={10: 50, 20: 130})  # tick 10 overruns; tick 20 overruns by 3 periods
    brick = make(host, clock, hw)
    brick.run(3, P.MODE_FIELD, 50, 0, 0)
    tel = host.of(P.TELEMETRY)
    ticks = [t[0] for t in tel]
    assert ticks == [k for k in range(50) if k not in (21, 22)]  # the ticks 20's overrun swallowed
    for tick, stamp, color, angle, work, flags, age in tel:
        assert angle == LaneKeeping(30)(color / 100) * 100
        assert bool(flags & P.FLAG_OVERRUN) == (tick in (10, 20))
        assert stamp == 40 * tick + {11: 10, 23: 10}.get(tick, 0)  # only the tick after an overrun is late
    end = host.of(P.RUN_END)[0]
    assert end[:7] == (3, P.END_DONE, 50, 48, 2, 2, 0)  # 48 rows sent: 50 ticks less the 2 skipped
    assert host.run_ids(P.TELEMETRY) == {3}  # every frame says which run it belongs to


def test_lockstep_uses_the_colour_for_its_tick_and_reports_timeouts() -> None:
    clock = Clock()
    host = ScriptedHost(clock, withhold=frozenset({5, 6, 30}))
    hw = Hardware(clock)
    brick = make(host, clock, hw)
    brick.run(1, P.MODE_LOCKSTEP, 40, 0, 0)
    tel = {t[0]: t for t in host.of(P.TELEMETRY)}
    assert sorted(tel) == list(range(40))  # lock-step never skips a tick, even after a timeout
    for k, (tick, stamp, color, angle, work, flags, age) in tel.items():
        if k in (5, 6, 30):
            assert flags & P.FLAG_TIMEOUT and not flags & P.FLAG_INJECTED and angle == 0
            assert stamp == 40 * k + 80  # waited the full two-period timeout
        else:
            assert flags & ~P.FLAG_OVERRUN == P.FLAG_INJECTED
            assert color == host.colour(k) and angle == LaneKeeping(30)(color / 100) * 100
    assert len(hw.steered) == 37  # a timeout actuates nothing
    assert hw.reads == 0  # injected: the sensor is never read
    end = host.of(P.RUN_END)[0]
    assert end[6] == 3 and end[3] == 37  # 3 timeouts; 37 rows sent (a timeout is no row)


def test_free_running_marks_stale_colours() -> None:
    clock = Clock()
    host = ScriptedHost(clock, withhold=frozenset({10}))
    brick = make(host, clock, Hardware(clock))
    brick.run(2, P.MODE_FREE, 20, 0, 0)
    tel = {t[0]: t for t in host.of(P.TELEMETRY)}
    assert sorted(tel) == list(range(20))
    assert tel[10][5] & P.FLAG_STALE and tel[10][2] == host.colour(9)  # newest colour it had: tick 9's
    assert tel[10][6] >= 38  # and that colour's age says so
    assert not any(tel[k][5] & P.FLAG_STALE for k in tel if k != 10)


def test_stop_ends_a_run_and_run_end_is_repeated_on_request() -> None:
    clock = Clock()
    host = ScriptedHost(clock, withhold=frozenset(range(1000)))
    brick = make(host, clock, Hardware(clock))
    host.push(clock.now + 400, P.STOP, (9,))
    brick.run(9, P.MODE_FIELD, 100, 0, 0)
    end = host.of(P.RUN_END)
    assert end[0][:2] == (9, P.END_STOPPED) and 8 <= end[0][2] <= 11
    host.push(clock.now + 1, P.STOP, (9,))
    brick.serve_once(10)
    assert host.of(P.RUN_END) == [end[0], end[0]]


@pytest.mark.parametrize("color,angle", [(40.0, 0.0), (40.01, 30.0), (39.99, -30.0), (100, 30.0), (0, -30.0)])
def test_brick_controller_matches_envi(color: float, angle: float) -> None:
    import numpy as np

    from envi_py.controllers import BangBang as EnviLK

    assert LaneKeeping(30)(color) == angle == EnviLK(30)(np.array([[color]]))[0, 0]


def test_catching_up_never_repeats_a_time_stamp() -> None:
    """After a lock-step timeout the late ticks run back to back; with an instant host and no work
    time they would all happen in one millisecond, and a log's time must strictly increase."""
    clock = Clock()
    host = ScriptedHost(clock, delay=0, withhold=frozenset({5}))
    brick = make(host, clock, Hardware(clock))
    brick.run(4, P.MODE_LOCKSTEP, 12, 0, 0)
    tel = host.of(P.TELEMETRY)
    stamps = [t[1] for t in tel]
    assert [t[0] for t in tel] == list(range(12))
    assert all(b > a for a, b in itertools.pairwise(stamps)), stamps
    assert stamps[6] - stamps[5] == 1  # caught up as fast as the stamps allow


def test_handshake_tells_which_run_the_brick_is_in_and_a_stale_stop_ends_nothing() -> None:
    """A collector that connects mid-run learns the run's id from the HANDSHAKE; a STOP naming
    another run (an old one) does not end it, a STOP naming it does."""
    clock = Clock()
    host = ScriptedHost(clock, withhold=frozenset(range(1000)))
    brick = make(host, clock, Hardware(clock))
    host.push(clock.now, P.HELLO, ())
    brick.serve_once(10)
    assert host.of(P.HANDSHAKE)[-1][:3] == (P.VERSION, 40, P.RUN_NONE)
    host.push(clock.now + 200, P.HELLO, ())  # a new collector, mid-run
    host.push(clock.now + 300, P.STOP, (41,))  # a run that is not the one going
    host.push(clock.now + 300, P.INJECT, (41, 0, 5000))  # a colour for that other run: not data
    host.push(clock.now + 600, P.STOP, (0xABCDEF01,))
    brick.run(0xABCDEF01, P.MODE_FIELD, 100, 0, 0)
    assert host.of(P.HANDSHAKE)[-1][2:4] == (P.RUN_RUNNING, 0xABCDEF01)
    end = host.of(P.RUN_END)[0]
    assert end[:2] == (0xABCDEF01, P.END_STOPPED) and 13 <= end[2] <= 16  # stopped at 600 ms, not 300
    assert end[3] == len(host.of(P.TELEMETRY)) == end[2]  # rows sent: every tick's frame
    assert brick.injects == {} and brick.latest is None
    host.push(clock.now + 1, P.HELLO, ())
    brick.serve_once(10)
    assert host.of(P.HANDSHAKE)[-1][2:4] == (P.RUN_ENDED, 0xABCDEF01)


def test_hello_drops_a_start_the_previous_host_left_pending() -> None:
    clock = Clock()
    host = ScriptedHost(clock, withhold=frozenset(range(1000)))
    brick = make(host, clock, Hardware(clock))
    host.push(clock.now, P.START, (5, P.MODE_FIELD, 10, 0, 0))
    host.push(clock.now, P.HELLO, ())  # same batch: the START's sender is gone
    brick.serve_once(10)
    assert brick.current_run is None and host.of(P.STARTED) == []
