"""Absolute deadlines for a fixed-rate loop.

Tick k is due at ``t0 + k * period``. Sleeping one period after each tick would add the work time
and every late wake-up to all later ticks (drift); with absolute deadlines a late tick only delays
itself. When a tick ends after the next one was due that is an overrun; when it ends a whole period
or more late the missed ticks are skipped (and counted) so that the phase is kept, except in
lock-step where every tick is needed.
"""

from .compat import ticks_add, ticks_diff


class Ticker:
    def __init__(self, period_ms, t0, diff=ticks_diff, add=ticks_add):
        self.period = period_ms
        self.t0 = t0
        self.deadline = t0
        self.tick = 0
        self.overruns = 0
        self.skipped = 0
        self._diff = diff
        self._add = add

    def wait_ms(self, now):
        """Milliseconds until the current tick is due (0 when due or late)."""
        return max(0, self._diff(self.deadline, now))

    def since_t0(self, now):
        """Milliseconds since tick 0 was due: the time stamp of a reading."""
        return self._diff(now, self.t0)

    def advance(self, now, skip=True):
        """The current tick's work ended at ``now``: move on; True when that was an overrun.

        ``skip=False`` never skips a tick (lock-step: tick k is the host's k-th colour, not a time
        slot); late ticks then run back to back until the loop is on its deadlines again.
        """
        self.tick += 1
        self.deadline = self._add(self.deadline, self.period)
        late = self._diff(now, self.deadline)
        if late <= 0:
            return False
        self.overruns += 1
        missed = late // self.period if skip else 0
        if missed:
            self.tick += missed
            self.skipped += missed
            self.deadline = self._add(self.deadline, missed * self.period)
        return True
