"""A small stand-in world for the simulated brick (the default is the physics twin, ``envi_py.twin``).

A robot drives at constant speed across a black (5) / white (75) edge. The state is its lateral
offset ``y`` (mm, positive over white) and heading ``psi`` (rad, positive towards white); the
steering angle turns the heading like a bicycle model, and the colour is the blend of black and
white under the sensor's spot plus a little noise, rounded as the real sensor reports integers.
Any object with ``reset(seed)``, ``read_color()`` and ``apply(angle_deg, dt_s)`` is a world; this
one has no dependencies and is what ``WorldModel`` uses for HIL without a trained model.
"""

from __future__ import annotations

import math
import random

BLACK, WHITE = 5.0, 75.0


class EdgeWorld:
    def __init__(
        self,
        speed_mm_s: float = 200.0,
        wheelbase_mm: float = 40.0,
        spot_mm: float = 8.0,
        noise: float = 1.0,
        seed: int = 0,
    ) -> None:
        self.speed = speed_mm_s
        self.wheelbase = wheelbase_mm
        self.spot = spot_mm
        self.noise = noise
        self.reset(seed)

    def reset(self, seed: int) -> None:
        """Start each run mostly over white, a few mm from the edge, heading along it."""
        self.rng = random.Random(seed)
        self.y = self.rng.uniform(2.0, 6.0)
        self.psi = self.rng.uniform(-0.05, 0.05)

    def read_color(self) -> float:
        white = min(1.0, max(0.0, (self.y + self.spot) / (2 * self.spot)))
        value = BLACK + (WHITE - BLACK) * white + self.rng.gauss(0.0, self.noise)
        return float(min(100, max(0, round(value))))

    def apply(self, angle_deg: float, dt_s: float) -> None:
        """Steering right (positive angle) turns towards black, as the controller expects."""
        self.psi -= self.speed / self.wheelbase * math.tan(math.radians(angle_deg)) * dt_s
        self.psi = max(-1.2, min(1.2, self.psi))
        self.y += self.speed * math.sin(self.psi) * dt_s
