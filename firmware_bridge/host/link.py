"""The host's end of the link: a pyserial port, a reader thread and the shared frame codec.

Built on ``serial.threaded``: the reader thread feeds bytes to :class:`FrameProtocol`, which
decodes them with the brick's own :class:`~firmware_bridge.brick.protocol.Decoder` and queues
each message with its arrival time. The caller takes messages from the queue with a timeout, so a
silent brick is noticed; a hang-up (a ``SerialException`` or any ``OSError`` in the reader)
arrives in the same queue as :class:`LinkLost`.
"""

from __future__ import annotations

import queue
import threading
import time
from typing import Any

import serial
import serial.threaded

from ..brick import protocol as P


class LinkLost(Exception):
    """The port went away (cable pulled, brick rebooted) or stopped answering."""


class FrameProtocol(serial.threaded.Protocol):
    def __init__(self) -> None:
        self.decoder = P.Decoder()
        self.inbox: queue.Queue[tuple[float, P.Message | LinkLost]] = queue.Queue()

    def data_received(self, data: bytes) -> None:
        now = time.perf_counter()
        for msg in self.decoder.feed(data):
            self.inbox.put((now, msg))

    def connection_lost(self, exc: BaseException | None) -> None:
        self.inbox.put((time.perf_counter(), LinkLost(f"link lost: {exc}" if exc else "link closed")))


class ReaderThread(serial.threaded.ReaderThread):
    """pyserial 3.5's reader, ending on any ``OSError`` as on a ``SerialException``.

    Its loop catches only ``SerialException``, but ``in_waiting`` on a device that vanished (a
    brick killed or unplugged) can raise a bare ``OSError`` from its ioctl: the thread then died
    with a traceback and no ``connection_lost``, and the run waited out its silence as "silent"
    instead of ending as a disconnect.
    """

    def run(self) -> None:
        try:
            super().run()
        except OSError as exc:  # raised from the loop: the protocol has not been told yet
            self.alive = False
            self.protocol.connection_lost(exc)
            self.protocol = None


class Link:
    """An open link to one brick; ``send`` frames out, ``recv`` messages in (with arrival time)."""

    def __init__(self, url: str, baudrate: int = 115200) -> None:
        self.url = url
        # exclusive: a second program on the port (another collector, a terminal) would split its bytes;
        # pyserial takes an flock on a POSIX device and ignores the flag for socket:// and loop:// URLs
        self.serial = serial.serial_for_url(url, baudrate=baudrate, timeout=0.05, write_timeout=1.0, exclusive=True)
        self.serial.reset_input_buffer()
        self.encoder = P.Encoder()
        self.thread = ReaderThread(self.serial, FrameProtocol)
        self.thread.start()
        _, proto = self.thread.connect()
        self.protocol: FrameProtocol = proto
        self._t0 = time.perf_counter()
        self._lock = threading.Lock()

    @property
    def decoder(self) -> P.Decoder:
        return self.protocol.decoder

    def host_ms(self, t: float | None = None) -> float:
        """Host time in ms since the link opened, of ``t`` (a ``perf_counter`` value) or now."""
        return ((time.perf_counter() if t is None else t) - self._t0) * 1000

    def send(self, mtype: int, fields: tuple[Any, ...]) -> float:
        """Send one message; returns the send time (``time.perf_counter``)."""
        with self._lock:
            frame = self.encoder.encode(mtype, fields, int(self.host_ms()))
        try:
            self.thread.write(frame)
        except (serial.SerialException, OSError) as exc:
            raise LinkLost(f"write failed: {exc}") from exc
        return time.perf_counter()

    def recv(self, timeout: float) -> tuple[float, P.Message] | None:
        """The next message and its arrival time, or None after ``timeout`` seconds of silence."""
        try:
            t, item = self.protocol.inbox.get(timeout=timeout)
        except queue.Empty:
            return None
        if isinstance(item, LinkLost):
            self.protocol.inbox.put((t, item))  # stays lost for every later caller
            raise item
        return t, item

    def close(self) -> None:
        try:
            self.thread.close()
        except (serial.SerialException, OSError):
            pass
