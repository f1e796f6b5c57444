"""The wire protocol of PROTOCOL.md: message layouts, the frame encoder and the frame decoder.

Brick and host import this one module, so the two ends cannot drift apart. A frame is
``0x00 COBS(header payload crc) 0x00``; the header is ``<BBHI`` (protocol version, message type,
sequence number, sender time in ms). Each direction numbers its frames; the decoder counts every
frame it did not get from the gaps in those numbers and drops duplicates, so losses are measured
rather than guessed. Version 2 tags every frame of a run (STARTED, TELEMETRY, INJECT, STOP,
RUN_END) with the host's 32-bit run id and has the HANDSHAKE say which run the brick is in, so a
host that (re)connects can tell a run it never started from its own and never mixes the two.
"""

from .compat import struct
from . import cobs
from .crc import crc16

VERSION = 2

HELLO = 1
HANDSHAKE = 2
START = 3
STARTED = 4
TELEMETRY = 5
INJECT = 6
PING = 7
PONG = 8
STOP = 9
RUN_END = 10

MODE_FIELD = 0
MODE_LOCKSTEP = 1
MODE_FREE = 2
MODE_NAMES = ("field", "lockstep", "free")

FLAG_OVERRUN = 1  # the tick's work ended after the next tick was due
FLAG_INJECTED = 2  # the colour came from the host, not the sensor
FLAG_TIMEOUT = 4  # lock-step: no colour for this tick arrived in time; nothing was actuated
FLAG_STALE = 8  # free-running: the injected colour was meant for an earlier tick

END_DONE = 0
END_STOPPED = 1

RUN_NONE = 0  # HANDSHAKE run state: no run since the brick started
RUN_RUNNING = 1  # a run is in progress (the host that started it may be gone)
RUN_ENDED = 2  # the latest run has ended; STOP with its id repeats its RUN_END

HEADER = "<BBHI"
HEADER_SIZE = 8
MAX_FRAME = 255  # decoded bytes; longer chunks are garbage

# type: (name, fixed layout, number of trailing length-prefixed strings)
LAYOUTS = {
    HELLO: ("hello", "<", 0),
    # protocol version, loop period ms, run state (RUN_*), that run's id; strings: program hash,
    # runtime, controller, params
    HANDSHAKE: ("handshake", "<BHBI", 4),
    # run id, mode, ticks, period ms (0: brick default), lock-step timeout ms (0: two periods)
    START: ("start", "<IBIHH", 0),
    # run id, mode, period ms
    STARTED: ("started", "<IBH", 0),
    # run id, tick, ms since tick 0 was due, colour x100, angle x100, loop work us, flags, injected age ms
    TELEMETRY: ("telemetry", "<IIIhhHBH", 0),
    # run id, tick, colour x100
    INJECT: ("inject", "<IIh", 0),
    # nonce (echoed)
    PING: ("ping", "<I", 0),
    PONG: ("pong", "<I", 0),
    # run id
    STOP: ("stop", "<I", 0),
    # run id, reason, ticks done, rows sent (TELEMETRY frames without FLAG_TIMEOUT), overruns,
    # skipped ticks, timeouts, frames lost / bad / duplicated on the way in, injected colours that
    # came too late
    RUN_END: ("run_end", "<IBIIIIIIIII", 0),
}


def _extra(mtype):
    """The per-type CRC seed byte, derived from the layout so a changed layout changes it."""
    name, fmt, nstr = LAYOUTS[mtype]
    c = crc16(("%s %s %d" % (name, fmt, nstr)).encode())
    return (c ^ (c >> 8)) & 0xFF


CRC_EXTRA = dict((t, _extra(t)) for t in LAYOUTS)


def pack_payload(mtype, fields):
    name, fmt, nstr = LAYOUTS[mtype]
    nfix = len(fields) - nstr
    out = struct.pack(fmt, *fields[:nfix])
    for s in fields[nfix:]:
        b = s.encode() if isinstance(s, str) else bytes(s)
        if len(b) > 60:
            raise ValueError("string field longer than 60 bytes")
        out += bytes((len(b),)) + b
    return out


def unpack_payload(mtype, payload):
    """Fields of a payload as a tuple; ValueError when the length does not fit the layout."""
    name, fmt, nstr = LAYOUTS[mtype]
    size = struct.calcsize(fmt)
    if len(payload) < size or (nstr == 0 and len(payload) != size):
        raise ValueError("bad payload length")
    fields = list(struct.unpack(fmt, payload[:size]))
    i = size
    for _ in range(nstr):
        if i >= len(payload):
            raise ValueError("missing string field")
        n = payload[i]
        if i + 1 + n > len(payload):
            raise ValueError("string field runs past the payload")
        fields.append(bytes(payload[i + 1 : i + 1 + n]).decode())
        i += 1 + n
    if i != len(payload):
        raise ValueError("trailing bytes after the payload")
    return tuple(fields)


class Encoder:
    """Turns messages into frames, numbering them 0, 1, 2, ... (mod 2**16)."""

    def __init__(self):
        self.seq = 0

    def encode(self, mtype, fields, time_ms):
        body = struct.pack(HEADER, VERSION, mtype, self.seq, time_ms & 0xFFFFFFFF) + pack_payload(mtype, fields)
        crc = crc16(bytes((CRC_EXTRA[mtype],)), crc16(body))
        self.seq = (self.seq + 1) & 0xFFFF
        return b"\x00" + cobs.encode(body + struct.pack("<H", crc)) + b"\x00"


class Message:
    """A decoded frame: ``type``, sequence number, sender time (ms) and payload ``fields``."""

    def __init__(self, mtype, seq, time_ms, fields):
        self.type = mtype
        self.seq = seq
        self.time = time_ms
        self.fields = fields

    def __repr__(self):
        return "Message(%s, seq=%d, time=%d, %r)" % (LAYOUTS[self.type][0], self.seq, self.time, self.fields)


class Decoder:
    """Bytes in any chunking -> messages, with every loss counted.

    ``lost`` counts frames missing from the sequence (dropped, corrupted or truncated alike),
    ``crc_errors`` frames whose checksum failed, ``malformed`` chunks that are not frames at all
    (garbage, bad COBS, unknown type or version, wrong length), ``duplicates`` repeated or
    out-of-order frames, ``discarded`` the bytes thrown away; ``other_version`` is the version byte
    of the latest frame that was dropped for speaking another protocol version. A HELLO or HANDSHAKE restarts the
    sequence (the other end has just (re)started), so a reboot is not counted as a loss.
    """

    def __init__(self):
        self.buf = bytearray()
        self.last_seq = None
        self.frames = 0
        self.lost = 0
        self.crc_errors = 0
        self.malformed = 0
        self.duplicates = 0
        self.discarded = 0
        self.other_version = None  # the version of the latest frame of another protocol version

    def counters(self):
        return {
            "frames": self.frames,
            "lost": self.lost,
            "crc_errors": self.crc_errors,
            "malformed": self.malformed,
            "duplicates": self.duplicates,
            "discarded_bytes": self.discarded,
        }

    def feed(self, data):
        """All complete messages in ``data`` (plus what was buffered before), in order."""
        data = bytes(data)
        out = []
        start = 0
        n = len(data)
        while start < n:
            z = data.find(b"\x00", start)
            if z < 0:
                self.buf.extend(data[start:])
                if len(self.buf) > 2 * MAX_FRAME + 2:
                    self.malformed += 1
                    self.discarded += len(self.buf)
                    self.buf = bytearray()
                break
            self.buf.extend(data[start:z])
            start = z + 1
            if self.buf:
                msg = self._frame(bytes(self.buf))
                self.buf = bytearray()
                if msg is not None:
                    out.append(msg)
        return out

    def _frame(self, chunk):
        try:
            raw = cobs.decode(chunk)
        except ValueError:
            return self._bad(chunk, False)
        if len(raw) < HEADER_SIZE + 2 or len(raw) > MAX_FRAME:
            return self._bad(chunk, False)
        version, mtype, seq, time_ms = struct.unpack(HEADER, raw[:HEADER_SIZE])
        if version != VERSION or mtype not in LAYOUTS:
            if version != VERSION:
                self.other_version = version  # lets a host say "the brick speaks protocol N"
            return self._bad(chunk, False)
        body = raw[:-2]
        got = struct.unpack("<H", raw[-2:])[0]
        if crc16(bytes((CRC_EXTRA[mtype],)), crc16(body)) != got:
            return self._bad(chunk, True)
        try:
            fields = unpack_payload(mtype, body[HEADER_SIZE:])
        except ValueError:
            return self._bad(chunk, False)
        if self.last_seq is not None and mtype not in (HELLO, HANDSHAKE):
            gap = (seq - self.last_seq) & 0xFFFF
            if gap == 0 or gap >= 0x8000:
                self.duplicates += 1
                return None
            self.lost += gap - 1
        self.last_seq = seq
        self.frames += 1
        return Message(mtype, seq, time_ms, fields)

    def _bad(self, chunk, crc):
        if crc:
            self.crc_errors += 1
        else:
            self.malformed += 1
        self.discarded += len(chunk)
        return None
