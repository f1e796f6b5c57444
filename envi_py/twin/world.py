"""The twin's physics, vectorised over runs: a robot following a black/white edge.

Hidden state per run: lateral offset ``y`` of the rear axle from the edge (mm, positive over
white), heading ``psi`` relative to the lane (rad, positive toward white), the actual steering
angle ``delta`` (deg) and the distance travelled ``s`` (mm). A positive controller angle turns the
robot toward black, as Algorithm 1 expects (steer +x when brighter than the threshold).

The colour sensor sits ``ahead`` mm in front of the axle; its reading blends black and white with
a smooth step of width ``spot`` as it crosses the edge. Every effect of :mod:`.effects` acts at the
place it does on the real robot: sensor effects on the reading, steering effects between command
and wheel angle, speed/grip/track effects in the dynamics.
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np

from .effects import colour_reading, resolve, steering_command
from .profile import TwinProfile, default_profile

SUBSTEPS = 2  # Euler sub-steps per control period; 2 keeps the 6 mm/period motion accurate enough


class Batch:
    """N independent twin runs advanced together; the engine of :func:`generate` and :class:`TwinWorld`."""

    def __init__(
        self,
        profile: TwinProfile,
        effects: dict[str, dict[str, float]],
        n: int,
        rng: np.random.Generator,
        horizon_s: float,
        max_distance_mm: float,
    ) -> None:
        self.p, self.fx, self.n, self.rng = profile, effects, n, rng
        self.horizon_s = max(horizon_s, 1e-9)
        rv = effects.get("run_variation", {})
        self.v_run = profile.speed * np.clip(1 + rv.get("speed_sd", 0.0) * rng.standard_normal(n), 0.2, None)
        self.grip_run = np.clip(1 + rv.get("grip_sd", 0.0) * rng.standard_normal(n), 0.2, None)
        self.white_run = profile.white + rv.get("white_sd", 0.0) * rng.standard_normal(n)
        self.patches = self._make_patches(max_distance_mm)
        cv = effects.get("curvature")
        self.curve_phase = rng.uniform(0, 2 * math.pi, n) if cv else None
        self.y = rng.uniform(-profile.spot / 2, profile.spot / 2, n)
        self.psi = 0.1 * rng.standard_normal(n)
        self.delta = np.zeros(n)
        self.lagged = np.zeros(n)
        self.play = np.zeros(n)  # backlash output
        self.s = np.zeros(n)
        self.t = 0.0
        self.queue = [np.zeros(n) for _ in range(int(effects.get("delay", {}).get("ticks", 0)))]
        self.sensed = self._surface()

    def _make_patches(self, max_distance_mm: float) -> np.ndarray | None:
        """Patch start positions (N, K) along the distance travelled, a Poisson process per run."""
        pt = self.fx.get("patches")
        if not pt or pt["per_m"] <= 0:
            return None
        spacing = 1000.0 / pt["per_m"]
        k = int(math.ceil(max_distance_mm / spacing * 1.5)) + 5
        return np.cumsum(self.rng.exponential(spacing, (self.n, k)), axis=1) - spacing / 2

    def _surface(self) -> np.ndarray:
        """Reflectance under the sensor spot: a smooth step across the edge, bent by the sensor's
        non-linearity (the real readings linger longer on the white side than a linear blend would)."""
        ys = self.y + self.p.ahead * np.sin(self.psi)
        u = np.clip(ys / self.p.spot + 0.5, 0.0, 1.0)
        blend = u * u * (3 - 2 * u)
        if self.p.gamma != 1.0:
            blend = blend**self.p.gamma
        return self.p.black + (self.white_run - self.p.black) * blend

    def start_logging(self, elapsed_s: float) -> None:
        """The first logged row: battery sag counts from here (the warmup's ``elapsed_s`` is not needed)."""
        self.t = 0.0

    def read(self) -> np.ndarray:
        """The colour readings now, shape (N,), after the sensor effects (unrounded unless quantised)."""
        return colour_reading(self, self.sensed, None)

    def _target(self, command: np.ndarray) -> np.ndarray:
        """Command after delay, dead zone, backlash and end stops: where the steering is asked to go."""
        return steering_command(self, command)

    def apply(self, angle_deg: np.ndarray, dt_s: np.ndarray | float) -> None:
        """Steer with the controller's angle (N,) for ``dt_s`` seconds, then update the sensor."""
        fx, p = self.fx, self.p
        target = self._target(np.asarray(angle_deg, dtype=np.float64).reshape(self.n))
        h = np.broadcast_to(np.asarray(dt_s, dtype=np.float64), (self.n,)) / SUBSTEPS
        for _ in range(SUBSTEPS):
            goal = target
            if "lag" in fx:
                self.lagged = self.lagged + (target - self.lagged) * (1 - np.exp(-h * 1000 / fx["lag"]["tau_ms"]))
                goal = self.lagged
            if "rate_limit" in fx:
                r = fx["rate_limit"]["deg_per_s"] * h
                self.delta = self.delta + np.clip(goal - self.delta, -r, r)
            else:
                self.delta = goal
            v = self.v_run
            if "battery" in fx:
                v = v * (1 - fx["battery"]["sag"] * min(self.t / self.horizon_s, 1.0))
            grip = self.grip_run
            if self.patches is not None:
                pt = fx["patches"]
                on = ((self.patches <= self.s[:, None]) & (self.s[:, None] < self.patches + pt["length_mm"])).any(1)
                grip = np.where(on, grip * pt["grip"], grip)
            yaw = -v / p.wheelbase * np.tan(np.radians(self.delta)) * grip
            if self.curve_phase is not None:
                cv = fx["curvature"]
                kappa = cv["mean_per_m"] + cv["amp_per_m"] * np.sin(
                    2 * math.pi * self.s / (cv["wavelength_m"] * 1000) + self.curve_phase
                )
                yaw = yaw - v * kappa / 1000
            self.psi = np.clip(self.psi + yaw * h, -1.3, 1.3)
            self.y = self.y + v * np.sin(self.psi) * h
            self.s = self.s + v * np.cos(self.psi) * h
            self.t += float(h.mean())
        surface = self._surface()
        if "lowpass" in fx:
            a = 1 - np.exp(-h * SUBSTEPS * 1000 / fx["lowpass"]["tau_ms"])
            self.sensed = self.sensed + (surface - self.sensed) * a
        else:
            self.sensed = surface


class TwinWorld:
    """One twin run, step by step: the world of a simulated brick running a real controller.

    ``read_color()`` is the sensor now; ``apply(angle, dt)`` steers for ``dt`` seconds. Sampling
    jitter is the brick's own business here (it decides ``dt``), so the ``jitter`` effect is unused.
    """

    def __init__(
        self,
        profile: TwinProfile | None = None,
        effects: dict[str, Any] | None = None,
        seed: int = 0,
        horizon_s: float = 4.0,
    ) -> None:
        self.profile = profile or default_profile()
        self.effects = resolve(self.profile.effects, effects)
        self.horizon_s = horizon_s
        self.seed = seed
        self.reset()

    def reset(self, seed: int | None = None) -> None:
        """Start a new run (a new seed gives a new start, speed, patches...)."""
        if seed is not None:
            self.seed = seed
        rng = np.random.default_rng(self.seed)
        dist = self.profile.speed * 1.5 * max(self.horizon_s, 60.0)
        self.batch = Batch(self.profile, self.effects, 1, rng, self.horizon_s, dist)

    def read_color(self) -> float:
        return float(self.batch.read()[0])

    def apply(self, angle_deg: float, dt_s: float) -> None:
        self.batch.apply(np.array([float(angle_deg)]), float(dt_s))

    @property
    def state(self) -> dict[str, float]:
        """Hidden state, for tests and plots."""
        b = self.batch
        return {
            "y_mm": float(b.y[0]),
            "psi_rad": float(b.psi[0]),
            "delta_deg": float(b.delta[0]),
            "s_mm": float(b.s[0]),
        }
