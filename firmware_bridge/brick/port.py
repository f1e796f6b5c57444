"""The brick's end of the serial link: wait for bytes with a timeout, read what is there, write.

``FdPort`` works on a file descriptor (a pty master in the simulator, ``/dev/ttyGS0`` or a tty on
ev3dev). Writes never block the control loop: if the other side stops reading and the kernel
buffer is full, the frame is dropped and counted (the host sees it as a sequence gap).
"""

import os

try:
    import uselect as select
except ImportError:
    import select


class LinkDown(Exception):
    """The link is gone (the other side hung up); the program goes back to waiting for a host."""


class FdPort:
    def __init__(self, fd):
        self.fd = fd
        self.poller = select.poll()
        self.poller.register(fd, select.POLLIN)
        self.tx_dropped = 0

    def wait(self, timeout_ms):
        """True when bytes can be read within ``timeout_ms``."""
        for _, ev in self.poller.poll(max(0, int(timeout_ms))):
            if ev & (select.POLLERR | select.POLLHUP) and not ev & select.POLLIN:
                raise LinkDown("hang-up")
            return True
        return False

    def read(self):
        try:
            return os.read(self.fd, 512)
        except OSError as exc:
            if exc.args[0] == 11:  # EAGAIN: nothing after all
                return b""
            raise LinkDown(str(exc))

    def write(self, data):
        try:
            os.write(self.fd, data)
        except OSError as exc:
            if exc.args[0] != 11:
                raise LinkDown(str(exc))
            self.tx_dropped += 1
