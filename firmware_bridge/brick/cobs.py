"""Consistent Overhead Byte Stuffing: a frame never contains 0x00, so 0x00 delimits frames.

A receiver that lost sync (garbage, a cut cable, a flipped bit) is back in step at the next zero
byte, which is why the framing is self-synchronising.
"""


def encode(data):
    """Bytes without zeros; ``decode(encode(d)) == d``."""
    out = bytearray(b"\x00")
    code_pos = 0
    code = 1
    for b in data:
        if b == 0:
            out[code_pos] = code
            code_pos = len(out)
            out.append(0)
            code = 1
        else:
            out.append(b)
            code += 1
            if code == 0xFF:
                out[code_pos] = code
                code_pos = len(out)
                out.append(0)
                code = 1
    out[code_pos] = code
    return bytes(out)


def decode(data):
    """Inverse of :func:`encode`; raises ValueError on a block that runs past the end or a zero."""
    out = bytearray()
    i = 0
    n = len(data)
    while i < n:
        code = data[i]
        if code == 0:
            raise ValueError("zero byte inside a COBS frame")
        i += 1
        end = i + code - 1
        if end > n:
            raise ValueError("COBS block runs past the end of the frame")
        out.extend(data[i:end])
        i = end
        if code < 0xFF and i < n:
            out.append(0)
    return bytes(out)
