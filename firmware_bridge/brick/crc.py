"""CRC-16/MCRF4XX (poly 0x1021 reflected, init 0xFFFF, no final xor), as MAVLink uses it.

MAVLink's trick is kept too: after the frame bytes one extra byte per message type is folded in,
so a host and a brick that disagree about a message's layout reject each other's frames instead
of misreading them.
"""


def crc16(data, crc=0xFFFF):
    """CRC-16/MCRF4XX of ``data`` continuing from ``crc`` (check value of b'123456789': 0x6F91)."""
    for b in data:
        tmp = (b ^ crc) & 0xFF
        tmp = (tmp ^ (tmp << 4)) & 0xFF
        crc = ((crc >> 8) ^ (tmp << 8) ^ (tmp << 3) ^ (tmp >> 4)) & 0xFFFF
    return crc
