"""The controller under verification as the brick runs it: lane keeping (paper, Algorithm 1).

Mirrors ``envi_py.controllers.BangBang``: ``angle = sign(color - threshold) * x``. The host
checks every recorded row against the envi controller, so the two cannot silently differ.
"""


class LaneKeeping:
    NAME = "lane-keeping"

    def __init__(self, x=30.0, threshold=40.0):
        self.x = float(x)
        self.threshold = float(threshold)

    def params(self):
        """Parameters as the handshake sends them: ``x=30;threshold=40``."""
        return "x=%g;threshold=%g" % (self.x, self.threshold)

    def __call__(self, color):
        if color > self.threshold:
            return self.x
        if color < self.threshold:
            return -self.x
        return 0.0
