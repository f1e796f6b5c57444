"""The car twin's physics, vectorised over runs: an ego car on a lane edge behind a lead vehicle.

Hidden state per run: the ego's lateral offset ``y`` of the rear axle from the edge (mm, positive
over white), heading ``psi`` relative to the lane (rad), actual front-wheel angle ``delta`` (deg),
actual wheel speed ``wheel`` (deg/s), distance travelled ``s`` (mm); the lead's speed and target
speed (cm/s) and the bumper-to-bumper ``gap`` (cm, along the lane). A positive steering command
turns toward black, as the lane-keeping twin's (a PID on ``color - 40`` steers back to the edge).
The numbers and why they were chosen are in :mod:`envi_py.twin.car`'s docstring.

Every random draw has a fixed shape per tick, whatever the controller does, so one seed gives
every controller version the same lanes, lead profiles and sensor noise (common random numbers).
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass
from typing import Any

import numpy as np

DISTANCE_MAX = 255.0  # what the ultrasonic sensor reads with no echo (and its range's top)


@dataclass(frozen=True)
class CarProfile:
    """Physical parameters of the ego car, the track, the lead vehicle and the two sensors.

    Lengths in mm on the ego/lane side (as the lane-keeping twin), cm on the following side (as
    the ultrasonic sensor reports); ``(low, high)`` pairs are per-run uniform draws."""

    # ego car and lane
    wheel_mm: float = 56.0  # tyre diameter: 1 deg/s of the wheels = 0.489 mm/s
    wheelbase_mm: float = 140.0
    ahead_mm: float = 60.0  # colour sensor ahead of the rear axle
    spot_mm: float = 20.0  # width of the black-to-white blend under the sensor
    black: float = 5.0
    white: float = 75.0
    white_sd: float = 2.5  # per-run white level (paper, light)
    color_noise: float = 1.5  # colour sensor noise, sd in %
    steer_tau_s: float = 0.06  # steering servo, first order
    steer_limit_deg: float = 45.0  # front-wheel end stops
    motor_tau_s: float = 0.15  # drive motor + mass, first order from command to wheel speed
    curvature_amp_per_m: float = 1.0  # lane curvature: mean + amp * sin(2 pi s / wavelength + phase)
    curvature_mean_sd_per_m: float = 0.3
    wavelength_m: float = 1.5
    # lead vehicle (cm/s)
    lead_cruise: tuple[float, float] = (4.0, 10.0)  # per-run cruising speed
    lead_accel: tuple[float, float] = (15.0, 30.0)  # per-run acceleration limit, cm/s^2
    lead_brake: float = 40.0  # braking limit, cm/s^2
    lead_events_per_s: float = 0.5  # rate of new speed targets
    lead_stop_prob: float = 0.2  # a new target is a stop...
    lead_slow_prob: float = 0.3  # ...a slow-down to 30-60 % of cruise, else cruise +-25 %
    # ultrasonic sensor (cm)
    echo_range: tuple[float, float] = (110.0, 160.0)  # per-run: beyond it no echo, the reading is 255
    distance_noise: float = 0.7
    dropout_prob: float = 0.002  # a spurious 255 per reading
    gap_start: tuple[float, float] = (25.0, 70.0)
    far_start_prob: float = 0.2  # a run starts with the lead far ahead...
    far_gap_start: tuple[float, float] = (220.0, 300.0)  # ...here, beyond any echo range
    # timing
    period_ms: float = 40.0
    warmup: int = 75  # unlogged ticks before logging starts (3 s)
    substeps: int = 4  # Euler sub-steps per control period (10 ms)

    @property
    def mm_per_wheel_deg(self) -> float:
        return math.pi * self.wheel_mm / 360.0

    def to_json(self) -> dict[str, Any]:
        return {k: list(v) if isinstance(v, tuple) else v for k, v in asdict(self).items()}


class CarBatch:
    """N independent car runs advanced together; the engine of :func:`envi_py.twin.car.generate_car`."""

    def __init__(self, profile: CarProfile, n: int, rng: np.random.Generator) -> None:
        p = self.p = profile
        self.n, self.rng = n, rng
        self.white_run = p.white + p.white_sd * rng.standard_normal(n)
        self.kappa_mean = p.curvature_mean_sd_per_m * rng.standard_normal(n)
        self.kappa_phase = rng.uniform(0, 2 * math.pi, n)
        self.cruise = rng.uniform(*p.lead_cruise, n)
        self.accel = rng.uniform(*p.lead_accel, n)
        self.range = rng.uniform(*p.echo_range, n)
        far = rng.random(n) < p.far_start_prob
        self.gap = np.where(far, rng.uniform(*p.far_gap_start, n), rng.uniform(*p.gap_start, n))
        self.lead_v = self.cruise * rng.uniform(0.8, 1.2, n)
        self.lead_target = self.lead_v.copy()
        # the ego is already driving along the edge at about the lead's speed
        self.wheel = np.clip(self.lead_v * 10 / p.mm_per_wheel_deg * rng.uniform(0.8, 1.2, n), 0, 720)
        self.y = rng.uniform(-p.spot_mm / 2, p.spot_mm / 2, n)
        self.psi = 0.05 * rng.standard_normal(n)
        self.delta = np.zeros(n)
        self.s = np.zeros(n)
        self.contact_ticks = np.zeros(n, dtype=int)

    # ------------------------------------------------------------------ sensors

    def _color_now(self) -> np.ndarray:
        """Reflectance under the sensor spot: a smooth step across the edge (as the lane twin)."""
        ys = self.y + self.p.ahead_mm * np.sin(self.psi)
        u = np.clip(ys / self.p.spot_mm + 0.5, 0.0, 1.0)
        return self.p.black + (self.white_run - self.p.black) * u * u * (3 - 2 * u)

    def read(self) -> np.ndarray:
        """Both sensors now, (N, 2): colour (%, integer, 0..100) and distance (cm, integer, 0..255)."""
        p, n = self.p, self.n
        color = np.clip(np.round(self._color_now() + p.color_noise * self.rng.standard_normal(n)), 0, 100)
        dist = np.clip(np.round(self.gap + p.distance_noise * self.rng.standard_normal(n)), 0, DISTANCE_MAX)
        lost = (self.gap > self.range) | (self.rng.random(n) < p.dropout_prob)
        return np.stack([color, np.where(lost, DISTANCE_MAX, dist)], axis=1)

    # ------------------------------------------------------------------ dynamics

    def _lead_events(self, dt: float) -> None:
        """New lead speed targets, a Poisson process per run: stop, slow down or cruise."""
        p, n = self.p, self.n
        event = self.rng.random(n) < p.lead_events_per_s * dt
        kind = self.rng.random(n)
        scale = self.rng.random(n)
        target = np.where(
            kind < p.lead_stop_prob,
            0.0,
            np.where(
                kind < p.lead_stop_prob + p.lead_slow_prob,
                self.cruise * (0.3 + 0.3 * scale),
                self.cruise * (0.75 + 0.5 * scale),
            ),
        )
        self.lead_target = np.where(event, target, self.lead_target)

    def apply(self, actions: np.ndarray) -> None:
        """Drive one control period with the commands (N, 2): steering (deg) and wheel speed (deg/s)."""
        p = self.p
        dt = p.period_ms / 1000.0
        self._lead_events(dt)
        steer_cmd = np.clip(actions[:, 0], -p.steer_limit_deg, p.steer_limit_deg)
        wheel_cmd = np.clip(actions[:, 1], 0.0, 720.0)
        h = dt / p.substeps
        a_steer = 1 - math.exp(-h / p.steer_tau_s)
        a_motor = 1 - math.exp(-h / p.motor_tau_s)
        touched = np.zeros(self.n, dtype=bool)
        for _ in range(p.substeps):
            self.delta = self.delta + (steer_cmd - self.delta) * a_steer
            self.wheel = self.wheel + (wheel_cmd - self.wheel) * a_motor
            v = self.wheel * p.mm_per_wheel_deg  # mm/s
            kappa = self.kappa_mean + p.curvature_amp_per_m * np.sin(
                2 * math.pi * self.s / (p.wavelength_m * 1000) + self.kappa_phase
            )
            yaw = -v / p.wheelbase_mm * np.tan(np.radians(self.delta)) - v * kappa / 1000
            self.psi = np.clip(self.psi + yaw * h, -1.3, 1.3)
            self.y = self.y + v * np.sin(self.psi) * h
            along = v * np.cos(self.psi)
            self.s = self.s + along * h
            self.lead_v = self.lead_v + np.clip(self.lead_target - self.lead_v, -p.lead_brake * h, self.accel * h)
            self.gap = self.gap + (self.lead_v - along / 10) * h
            touching = self.gap < 0
            touched |= touching
            self.gap = np.maximum(self.gap, 0.0)  # bumpers touch: the ego is held at the lead's speed
            self.wheel = np.where(touching, self.lead_v * 10 / p.mm_per_wheel_deg, self.wheel)
        self.contact_ticks += touched
