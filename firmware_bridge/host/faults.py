"""Fault injection on the simulated brick's link, to show that every fault is seen and counted.

``FaultyPort`` wraps the brick's port. Each frame the brick writes may be dropped, have one bit
flipped, be sent twice or be preceded by random garbage; after ``disconnect`` frames the link
goes down once (the simulator then starts over on a fresh pty, like a brick that rebooted).
Chunks the brick reads may be dropped (``rx_drop``). A journal line per written frame
(``kind hex``) lets a test compare what the host recorded with what the brick really sent.
"""

from __future__ import annotations

import random
from dataclasses import dataclass, fields
from typing import IO

from ..brick.port import LinkDown


@dataclass
class FaultSpec:
    garbage: float = 0.0
    flip: float = 0.0
    drop: float = 0.0
    dup: float = 0.0
    rx_drop: float = 0.0
    disconnect: int = 0  # frames written before the link goes down once (0: never)
    seed: int = 0

    @staticmethod
    def parse(text: str) -> "FaultSpec":
        """``"garbage=0.02,flip=0.01,drop=0.01,dup=0.01,rx_drop=0.01,disconnect=300,seed=1"``."""
        spec = FaultSpec()
        types = {f.name: f.type for f in fields(FaultSpec)}
        for item in filter(None, (s.strip() for s in text.split(","))):
            key, sep, value = item.partition("=")
            if not sep or key not in types:
                raise ValueError(f"fault {item!r}: expected one of {', '.join(types)} as name=value")
            setattr(spec, key, int(value) if key in ("disconnect", "seed") else float(value))
        return spec


class FaultyPort:
    """Same interface as :class:`firmware_bridge.brick.port.FdPort`, with faults on the way."""

    def __init__(self, port, spec: FaultSpec, journal: IO[str] | None = None, disconnected: bool = False) -> None:
        self.port = port
        self.spec = spec
        self.rng = random.Random(spec.seed + disconnected)  # after the reboot, other faults
        self.journal = journal
        self.written = 0
        self.disconnected = disconnected

    @property
    def tx_dropped(self) -> int:
        return self.port.tx_dropped

    def wait(self, timeout_ms: int) -> bool:
        return self.port.wait(timeout_ms)

    def read(self) -> bytes:
        data = self.port.read()
        if data and self.rng.random() < self.spec.rx_drop:
            return b""
        return data

    def _note(self, kind: str, frame: bytes) -> None:
        if self.journal is not None:
            self.journal.write(f"{kind} {frame.hex()}\n")
            self.journal.flush()

    def write(self, frame: bytes) -> None:
        self.written += 1
        if self.spec.disconnect and not self.disconnected and self.written > self.spec.disconnect:
            self.disconnected = True
            self._note("disconnect", frame)
            raise LinkDown("injected disconnect")
        r = self.rng.random
        if r() < self.spec.garbage:
            junk = bytes(self.rng.randrange(1, 256) for _ in range(self.rng.randrange(1, 24)))
            self._note("garbage", junk)
            self.port.write(junk)
        if r() < self.spec.drop:
            self._note("drop", frame)
            return
        if r() < self.spec.flip:
            bad = bytearray(frame)
            i = self.rng.randrange(1, len(bad) - 1)  # inside the frame, never a delimiter
            bad[i] ^= 1 << self.rng.randrange(8)
            self._note("flip", frame)
            self.port.write(bytes(bad))
            return
        self._note("sent", frame)
        self.port.write(frame)
        if r() < self.spec.dup:
            self._note("dup", frame)
            self.port.write(frame)
