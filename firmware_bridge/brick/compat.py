"""What the brick code needs from the runtime, the same on MicroPython and CPython.

MicroPython has ``ustruct`` and ``utime.ticks_*``; CPython has neither, so the fallbacks give the
same wrapping millisecond/microsecond ticks (period 2**30, as MicroPython's) on top of
``time.monotonic_ns``. Brick code always compares ticks with ``ticks_diff``, never ``-``.
"""

try:
    import ustruct as struct  # noqa: F401 - re-exported for the brick modules
except ImportError:
    import struct  # noqa: F401

try:
    from utime import ticks_ms, ticks_us, ticks_diff, ticks_add, sleep_ms
except ImportError:
    try:
        from time import ticks_ms, ticks_us, ticks_diff, ticks_add, sleep_ms
    except ImportError:
        import time as _time

        _PERIOD = 1 << 30
        _HALF = _PERIOD >> 1

        def ticks_ms():
            return (_time.monotonic_ns() // 1000000) & (_PERIOD - 1)

        def ticks_us():
            return (_time.monotonic_ns() // 1000) & (_PERIOD - 1)

        def ticks_add(ticks, delta):
            return (ticks + delta) & (_PERIOD - 1)

        def ticks_diff(a, b):
            d = (a - b) & (_PERIOD - 1)
            return d - _PERIOD if d >= _HALF else d

        def sleep_ms(ms):
            _time.sleep(ms / 1000.0)
