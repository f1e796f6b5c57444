"""Entry point on the brick: ``brickrun -r -- python3 main.py`` (ev3dev) or Pybricks' main.py.

Opens the host link (USB gadget serial by default), picks the hardware adapter the runtime has,
and serves the host forever. Settings are the module constants below, as a brick has no shell
arguments when started from its menu.
"""

import os

from .control import LaneKeeping
from .hardware import Ev3devHardware, PybricksHardware
from .identity import program_hash, runtime
from .port import FdPort
from .program import Brick

LINK = "/dev/ttyGS0"
PERIOD_MS = 40
X = 30.0


def main():
    try:
        hw = PybricksHardware()
    except ImportError:
        hw = Ev3devHardware()
    folder = __file__.rsplit("/", 1)[0]
    fd = os.open(LINK, os.O_RDWR | os.O_NONBLOCK | os.O_NOCTTY)
    Brick(FdPort(fd), hw, LaneKeeping(X), PERIOD_MS, program_hash(folder), runtime()).serve_forever()


if __name__ == "__main__":
    main()
