"""The brick program: answer the host, and run the control loop at a fixed rate when asked.

One thread, no allocation-heavy features: between ticks the loop services the link (pings are
answered mid-run so the host can measure round trips under load). Modes (see PROTOCOL.md):

* field: read the real sensor each tick;
* lock-step injected: wait for the host's colour for tick k, at most ``timeout`` ms past the
  deadline; a timeout is reported with FLAG_TIMEOUT and nothing is actuated, never filled in;
* free-running injected: use the newest colour the host sent, reporting its age.

Every run carries the id the host gave it in START, and every frame of the run repeats it. The
brick remembers its latest run (running or ended) and says so in each HANDSHAKE, so a host that
connects while a run it did not start is going (its collector died) can stop it and account for
it instead of taking its frames for its own.
"""

from .compat import ticks_ms, ticks_us, ticks_diff
from . import protocol as P
from .ticker import Ticker


class Brick:
    def __init__(
        self,
        port,
        hardware,
        controller,
        period_ms=40,
        program_hash="",
        runtime="",
        clock_ms=ticks_ms,
        clock_us=ticks_us,
        diff=ticks_diff,
    ):
        self.port = port
        self.hw = hardware
        self.ctrl = controller
        self.period = period_ms
        self.program_hash = program_hash
        self.runtime = runtime
        self.enc = P.Encoder()
        self.dec = P.Decoder()
        self._ms = clock_ms
        self._us = clock_us
        self._diff = diff
        self.pending_start = None
        self.current_run = None  # id of the latest run, running or ended
        self.running = False
        self.stop_requested = False
        self.injects = {}  # tick -> (colour x100, receive time ms)
        self.latest = None  # (tick, colour x100, receive time ms), free-running mode
        self.last_end = None
        self.late_injects = 0

    # ------------------------------------------------------------ link
    def send(self, mtype, fields):
        self.port.write(self.enc.encode(mtype, fields, self._ms()))

    def service(self, timeout_ms):
        """Handle whatever arrives within ``timeout_ms`` (returns after the first batch)."""
        if not self.port.wait(timeout_ms):
            return
        for msg in self.dec.feed(self.port.read()):
            self.handle(msg)

    def handle(self, msg):
        t = msg.type
        if t == P.HELLO:
            self.pending_start = None  # a START of the previous host not yet begun is its, not the new one's
            if self.current_run is None:
                state = P.RUN_NONE
            else:
                state = P.RUN_RUNNING if self.running else P.RUN_ENDED
            self.send(
                P.HANDSHAKE,
                (
                    P.VERSION,
                    self.period,
                    state,
                    self.current_run or 0,
                    self.program_hash,
                    self.runtime,
                    self.ctrl.NAME,
                    self.ctrl.params(),
                ),
            )
        elif t == P.PING:
            self.send(P.PONG, msg.fields)
        elif t == P.START:
            if msg.fields[0] != self.current_run:  # a repeated START (lost STARTED) is not a new run
                self.pending_start = msg.fields
        elif t == P.INJECT:
            run_id, tick, color = msg.fields
            if not self.running or run_id != self.current_run:
                return  # a colour for another run is not this run's data
            now = self._ms()
            self.injects[tick] = (color, now)
            if self.latest is None or tick >= self.latest[0]:
                self.latest = (tick, color, now)
        elif t == P.STOP:
            if self.running and msg.fields[0] == self.current_run:
                self.stop_requested = True  # only the run named: an old STOP never ends a newer run
            if self.last_end is not None and self.last_end[0] == msg.fields[0]:
                self.send(P.RUN_END, self.last_end)  # the host missed it: say it again

    # ------------------------------------------------------------ main loop
    def serve_forever(self):
        while True:
            self.serve_once(100)

    def serve_once(self, timeout_ms):
        """Idle: service the link; run when a START arrived."""
        self.service(timeout_ms)
        if self.pending_start is not None:
            start = self.pending_start
            self.pending_start = None
            self.run(*start)

    def run(self, run_id, mode, n_ticks, period_ms, timeout_ms):
        period = period_ms or self.period
        timeout = timeout_ms or 2 * period
        self.current_run = run_id
        self.running = True
        self.stop_requested = False
        self.injects = {}
        self.latest = None
        self.late_injects = 0
        counters0 = (self.dec.lost, self.dec.crc_errors + self.dec.malformed, self.dec.duplicates)
        self.hw.reset(run_id)
        self.send(P.STARTED, (run_id, mode, period))
        tk = Ticker(period, self._ms() + period, self._diff)  # one period for the host to get ready
        timeouts = 0
        rows = 0  # TELEMETRY frames that carry data (not FLAG_TIMEOUT): what the host can record
        last = None  # when the previous tick's colour was had (its time stamp)
        while tk.tick < n_ticks and not self.stop_requested:
            while tk.wait_ms(self._ms()) > 0:
                self.service(tk.wait_ms(self._ms()))
            while last is not None and self._diff(self._ms(), last) <= 0:
                self.service(1)  # late ticks catch up, but two readings never share a ms time stamp
            tick = tk.tick
            begin = self._us()
            flags = 0
            age = 0
            color = None
            if mode == P.MODE_FIELD:
                color = int(round(self.hw.read_color() * 100))
            elif mode == P.MODE_LOCKSTEP:
                got = self._wait_inject(tick, tk.deadline, timeout)
                begin = self._us()  # waiting for the host is not loop work
                if got is not None:
                    color = got[0]
                    age = self._diff(self._ms(), got[1])
                    flags = P.FLAG_INJECTED
            elif self.latest is not None:
                color = self.latest[1]
                age = self._diff(self._ms(), self.latest[2])
                flags = P.FLAG_INJECTED | (P.FLAG_STALE if self.latest[0] < tick else 0)
            last = self._ms()
            stamp = tk.since_t0(last)  # when the colour was had
            if color is None:
                timeouts += 1
                flags |= P.FLAG_TIMEOUT
                angle = 0
                color = 0
            else:
                angle = int(round(self.ctrl(color / 100.0) * 100))
                self.hw.steer(angle / 100.0)
                rows += 1
            work = min(0xFFFF, self._diff(self._us(), begin))
            if tk.advance(self._ms(), mode != P.MODE_LOCKSTEP):
                flags |= P.FLAG_OVERRUN
            self.send(
                P.TELEMETRY, (run_id, tick, stamp & 0xFFFFFFFF, color, angle, work, flags, min(0xFFFF, max(0, age)))
            )
        self.running = False
        skipped = tk.skipped - max(0, tk.tick - n_ticks)  # a skip past the last tick skips no real tick
        self.last_end = (
            run_id,
            P.END_STOPPED if self.stop_requested else P.END_DONE,
            min(tk.tick, n_ticks),
            rows,
            tk.overruns,
            skipped,
            timeouts,
            self.dec.lost - counters0[0],
            self.dec.crc_errors + self.dec.malformed - counters0[1],
            self.dec.duplicates - counters0[2],
            self.late_injects,
        )
        self.send(P.RUN_END, self.last_end)

    def _wait_inject(self, tick, deadline, timeout):
        """The colour for ``tick`` if it arrives before ``deadline + timeout``; stale ones dropped."""
        while True:
            for k in list(self.injects):
                if k < tick:
                    del self.injects[k]
                    self.late_injects += 1
            if tick in self.injects:
                return self.injects.pop(tick)
            left = timeout - self._diff(self._ms(), deadline)
            if left <= 0 or self.stop_requested:
                return None
            self.service(left)
