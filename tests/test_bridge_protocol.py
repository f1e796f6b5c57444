"""The wire codec shared by brick and host: round trips, and a decoder that survives a bad line."""

from __future__ import annotations

import random

import pytest

from firmware_bridge.brick import cobs
from firmware_bridge.brick import protocol as P
from firmware_bridge.brick.crc import crc16

SAMPLES = {
    P.HELLO: (),
    P.HANDSHAKE: (
        2,
        40,
        P.RUN_RUNNING,
        0xDEADBEEF,
        "0123456789abcdef",
        "micropython 1.19.1",
        "lane-keeping",
        "x=30;threshold=40",
    ),
    P.START: (0xFFFFFFFF, P.MODE_LOCKSTEP, 100, 40, 80),
    P.STARTED: (7, P.MODE_LOCKSTEP, 40),
    P.TELEMETRY: (0x80000001, 99, 3961, 7500, -3000, 120, P.FLAG_INJECTED | P.FLAG_OVERRUN, 12),
    P.INJECT: (7, 4_000_000_000, 4000),
    P.PING: (0xFFFFFFFF,),
    P.PONG: (12345,),
    P.STOP: (0xFFFFFFFF,),
    P.RUN_END: (7, P.END_DONE, 100, 98, 1, 2, 3, 4, 5, 6, 7),
}


def stream(n: int = 50) -> tuple[bytes, list[bytes]]:
    """n telemetry frames from one encoder: the whole byte stream and each frame."""
    enc = P.Encoder()
    frames = [enc.encode(P.TELEMETRY, (5, k, 40 * k, 100 * (k % 80), 3000, 50, 0, 0), 1000 + 40 * k) for k in range(n)]
    return b"".join(frames), frames


def ticks(msgs: list[P.Message]) -> list[int]:
    return [m.fields[1] for m in msgs]


def test_crc_is_mcrf4xx() -> None:
    assert crc16(b"123456789") == 0x6F91  # the catalogued check value of CRC-16/MCRF4XX
    assert len(set(P.CRC_EXTRA.values())) == len(P.CRC_EXTRA)  # each type seeds differently


@pytest.mark.parametrize("n", [0, 1, 2, 253, 254, 255, 256, 509, 510, 700])
def test_cobs_round_trip_has_no_zero(n: int) -> None:
    rng = random.Random(n)
    for zeros in (0.0, 0.3, 1.0):
        data = bytes(0 if rng.random() < zeros else rng.randrange(1, 256) for _ in range(n))
        enc = cobs.encode(data)
        assert 0 not in enc
        assert cobs.decode(enc) == data


def test_cobs_rejects_block_past_end() -> None:
    with pytest.raises(ValueError):
        cobs.decode(b"\x05ab")


@pytest.mark.parametrize("mtype", sorted(SAMPLES))
def test_every_message_round_trips(mtype: int) -> None:
    enc, dec = P.Encoder(), P.Decoder()
    enc.seq = 0xFFFE  # and across the sequence wrap
    data = enc.encode(mtype, SAMPLES[mtype], 0xFFFFFFFF) + enc.encode(mtype, SAMPLES[mtype], 5)
    msgs = dec.feed(data)
    assert [(m.type, m.seq, m.fields) for m in msgs] == [
        (mtype, 0xFFFE, SAMPLES[mtype]),
        (mtype, 0xFFFF, SAMPLES[mtype]),
    ]
    assert msgs[0].time == 0xFFFFFFFF and msgs[1].time == 5
    assert dec.lost == dec.crc_errors == dec.malformed == 0


def test_byte_by_byte_delivery() -> None:
    data, _ = stream(20)
    dec = P.Decoder()
    got = [m for b in data for m in dec.feed(bytes((b,)))]
    assert ticks(got) == list(range(20)) and dec.lost == 0


def test_garbage_between_frames_is_discarded_not_lost() -> None:
    _, frames = stream(40)
    rng = random.Random(1)
    noisy = b"".join(f + bytes(rng.randrange(1, 256) for _ in range(rng.randrange(1, 30))) for f in frames)
    dec = P.Decoder()
    assert ticks(dec.feed(noisy)) == list(range(40))
    assert dec.lost == 0 and dec.malformed + dec.crc_errors >= 39 and dec.discarded > 0


def test_long_garbage_without_zero_is_bounded() -> None:
    dec = P.Decoder()
    dec.feed(b"\x55" * 5000)
    assert len(dec.buf) <= 2 * P.MAX_FRAME + 2 and dec.malformed >= 1
    data, _ = stream(3)
    assert ticks(dec.feed(data)) == [0, 1, 2]


def test_every_single_bit_flip_is_caught_and_counted_as_one_loss() -> None:
    _, frames = stream(3)
    victim = frames[1]
    for i in range(1, len(victim) - 1):  # every bit of the frame between the delimiters
        for bit in range(8):
            bad = bytearray(victim)
            bad[i] ^= 1 << bit
            dec = P.Decoder()
            got = dec.feed(frames[0] + bytes(bad) + frames[2])
            assert ticks(got) == [0, 2], (i, bit)
            assert dec.lost == 1 and dec.crc_errors + dec.malformed >= 1


def test_truncated_frames_resynchronise() -> None:
    _, frames = stream(10)
    cut = b"".join(f[: len(f) // 2] if k in (3, 7) else f for k, f in enumerate(frames))
    dec = P.Decoder()
    assert ticks(dec.feed(cut)) == [0, 1, 2, 4, 5, 6, 8, 9]
    assert dec.lost == 2


def test_duplicates_dropped_and_gaps_counted() -> None:
    _, frames = stream(30)
    order = [0, 1, 1, 2, 5, 5, 6, 4, 7, 8, 12, 29]  # dups, a gap of 2, an old frame, gaps of 3 and 16
    dec = P.Decoder()
    got = dec.feed(b"".join(frames[k] for k in order))
    assert ticks(got) == [0, 1, 2, 5, 6, 7, 8, 12, 29]
    assert dec.duplicates == 3
    assert dec.lost == 2 + 3 + 16


def test_lost_counted_across_sequence_wrap() -> None:
    enc, dec = P.Encoder(), P.Decoder()
    enc.seq = 0xFFFD
    frames = [enc.encode(P.PONG, (k,), 0) for k in range(6)]  # seqs FFFD FFFE FFFF 0 1 2
    got = dec.feed(frames[0] + frames[4] + frames[5])
    assert [m.fields[0] for m in got] == [0, 4, 5] and dec.lost == 3


def test_handshake_restarts_the_sequence() -> None:
    dec = P.Decoder()
    a, b = P.Encoder(), P.Encoder()
    a.seq = 500
    dec.feed(a.encode(P.PONG, (1,), 0))
    got = dec.feed(b.encode(P.HANDSHAKE, SAMPLES[P.HANDSHAKE], 0) + b.encode(P.PONG, (2,), 0))
    assert len(got) == 2 and dec.lost == 0 and dec.duplicates == 0


def test_layout_mismatch_is_a_crc_error() -> None:
    """A frame whose CRC was seeded for another type (a peer with another layout) is rejected."""
    body = P.struct.pack(P.HEADER, P.VERSION, P.PING, 0, 0) + P.pack_payload(P.PONG, (1,))
    crc = crc16(bytes((P.CRC_EXTRA[P.PONG],)), crc16(body))
    frame = b"\x00" + cobs.encode(body + P.struct.pack("<H", crc)) + b"\x00"
    dec = P.Decoder()
    assert dec.feed(frame) == [] and dec.crc_errors == 1


def test_wrong_payload_length_is_malformed() -> None:
    body = P.struct.pack(P.HEADER, P.VERSION, P.PING, 0, 0) + b"\x01\x02"
    crc = crc16(bytes((P.CRC_EXTRA[P.PING],)), crc16(body))
    dec = P.Decoder()
    assert dec.feed(b"\x00" + cobs.encode(body + P.struct.pack("<H", crc)) + b"\x00") == []
    assert dec.malformed == 1


def test_a_frame_of_another_protocol_version_is_dropped_and_its_version_kept() -> None:
    """A version 1 brick's frames are not misread as version 2: dropped, and the host can say why."""
    body = P.struct.pack(P.HEADER, 1, P.PONG, 0, 0) + P.pack_payload(P.PONG, (1,))
    crc = crc16(bytes((P.CRC_EXTRA[P.PONG],)), crc16(body))
    dec = P.Decoder()
    assert dec.feed(b"\x00" + cobs.encode(body + P.struct.pack("<H", crc)) + b"\x00") == []
    assert dec.malformed == 1 and dec.other_version == 1 and P.VERSION == 2
