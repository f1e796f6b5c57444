"""A second, structurally different lane-keeping world: a differential-drive robot on a curved track.

The first twin (:mod:`.world`) is a steered vehicle (bicycle model, steering angle = command, straight
edge). Diagnosis rules chosen on it must be checked on a world they were not tuned on, so this one
differs in every part that shapes the logs, while writing the same schema (``time,color,angle`` at
about 24 Hz, integer colour 0..100, the paper's bang-bang controller of x = 10..50):

- *vehicle*: two wheels on DC motors, ``track`` mm apart; the controller's angle is a turn command
  that speeds one wheel up and slows the other (``turn_gain`` of the motor voltage per degree);
  yaw rate and speed follow from the wheel speeds, not from a steering angle;
- *actuators*: each motor is first order (``motor_tau_ms``: armature and inertia) with a static
  dead zone (``motor_deadzone``: voltages below it do not turn the wheel), so a hard turn stalls
  the inner wheel and the turn is not proportional to the command;
- *sensor*: at its own offset ahead of the axle (``ahead`` mm) with a wider, logistic (not smoothstep) blend across the
  edge, and a one-tick conversion latency (the reading is the surface one control period ago);
- *track*: a circle of per-run radius and direction (constant curvature) instead of a straight edge;
- *disturbances*: wheel slip as an Ornstein-Uhlenbeck yaw-rate disturbance.

Every effect of :data:`.effects.EFFECTS` acts here where it would on such a robot (delay, lag, play,
dead zone, limits and rate limit on the turn command; noise, glitches, saturation, quantisation and
low-pass on the reading; battery sag and run-to-run variation on the motors; slippery patches on the
turn; sinusoidal curvature on top of the circle; jitter in the sampling), plus the novel effects of
:data:`NOVEL` that no diagnosis candidate stands for: a periodic heading kick and one sharply curved
section. The numbers are chosen so that clean logs resemble the real ones in colour percentiles and
oscillation period (``tests/test_twin_diffdrive.py`` prints the comparison).
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass
from typing import Any, Mapping

import numpy as np

from envi_py.controllers import ControllerSpec
from envi_py.logs import Log

from .effects import EFFECTS, Effect, Param, colour_reading, effect_params, steering_command
from .generate import drive, lane_logs, sample_periods

SUBSTEPS = 4  # Euler sub-steps per control period: the motors' time constant is a few periods

#: Effects of this world only: outside the diagnosis's candidate list on purpose.
NOVEL: dict[str, Effect] = {
    e.name: e
    for e in (
        Effect(
            "kick",
            "periodic heading kick: every period_s the robot's heading jumps by deg (a bump in the track)",
            {
                "period_s": Param(1.0, "s", "time between kicks", 0.0, above=True),
                "deg": Param(8.0, "deg", "heading jump, alternating in sign"),
            },
            "deg",
        ),
        Effect(
            "arc",
            "one sharply curved section: the edge turns at per_m from start_m for length_m",
            {
                "start_m": Param(0.15, "m", "where the section starts (distance travelled)", 0.0),
                "length_m": Param(0.25, "m", "section length", 0.0),
                "per_m": Param(4.0, "1/m", "curvature inside the section"),
            },
            "per_m",
        ),
    )
}


@dataclass(frozen=True)
class DiffDriveProfile:
    """Physics of the differential-drive robot and its track; lengths in mm, times in ms."""

    wheel_speed: float = 160.0  # straight-line speed at the nominal voltage, mm/s
    track: float = 110.0  # distance between the wheels, mm
    turn_gain: float = 0.015  # voltage difference per degree of turn command (fraction of nominal)
    motor_tau_ms: float = 40.0  # motor + inertia time constant
    motor_deadzone: float = 0.15  # fraction of nominal voltage below which a wheel does not turn
    ahead: float = 50.0  # sensor ahead of the axle, mm
    spot: float = 16.0  # logistic width of the edge under the sensor, mm
    black: float = 6.0
    white: float = 72.0
    radius_m: tuple[float, float] = (1.5, 4.0)  # per-run track radius (direction random)
    slip_sd: float = 0.1  # stationary sd of the yaw-rate disturbance, rad/s
    slip_tau_ms: float = 150.0  # its correlation time
    period_ms: float = 41.0
    warmup: int = 40

    def to_json(self) -> dict[str, Any]:
        return asdict(self)


#: Every effect this world knows: the shared registry's and its own.
DIFFDRIVE_EFFECTS: dict[str, Effect] = {**EFFECTS, **NOVEL}


def resolve_diffdrive(effects: Mapping[str, Any] | None) -> dict[str, dict[str, float]]:
    """Full parameters of the requested effects: the shared registry's and :data:`NOVEL`, each
    checked like :func:`.effects.effect_params` (finite and within its range)."""
    out = {}
    for name, value in (effects or {}).items():
        if name not in DIFFDRIVE_EFFECTS:
            raise ValueError(f"unknown diffdrive effect {name!r}; known: {', '.join(DIFFDRIVE_EFFECTS)}")
        params = effect_params(name, value, DIFFDRIVE_EFFECTS)
        if params is not None:
            out[name] = params
    return dict(sorted(out.items()))


class DiffDriveBatch:
    """N independent runs of the differential-drive world advanced together."""

    def __init__(
        self, profile: DiffDriveProfile, effects: dict[str, dict[str, float]], n: int, rng: np.random.Generator
    ) -> None:
        self.p, self.fx, self.n, self.rng = profile, effects, n, rng
        rv = effects.get("run_variation", {})
        self.gain_run = np.clip(1 + rv.get("speed_sd", 0.0) * rng.standard_normal(n), 0.2, None)
        self.turn_run = np.clip(1 + rv.get("grip_sd", 0.0) * rng.standard_normal(n), 0.2, None)
        self.white_run = profile.white + rv.get("white_sd", 0.0) * rng.standard_normal(n)
        radius = rng.uniform(*profile.radius_m, n) * 1000
        self.kappa0 = rng.choice([-1.0, 1.0], n) / radius  # 1/mm
        self.curve_phase = rng.uniform(0, 2 * math.pi, n)
        self.patch_phase = rng.uniform(0, 1, n)
        self.y = rng.uniform(-profile.spot / 2, profile.spot / 2, n)
        self.psi = 0.1 * rng.standard_normal(n)
        self.omega = np.ones((2, n))  # left, right wheel speeds as fractions of nominal
        self.slip = np.zeros(n)
        self.lagged = np.zeros(n)
        self.rated = np.zeros(n)
        self.play = np.zeros(n)
        self.s = np.zeros(n)
        self.t = 0.0
        self.horizon_s = 1.0
        self.next_kick = effects["kick"]["period_s"] * rng.uniform(0.2, 1.0, n) if "kick" in effects else None
        self.kick_sign = rng.choice([-1.0, 1.0], n)
        self.queue = [np.zeros(n) for _ in range(int(effects.get("delay", {}).get("ticks", 0)))]
        self.latched = self._surface()  # the reading converted last period (one tick of latency)
        self.sensed = self.latched.copy()

    def _surface(self) -> np.ndarray:
        """Reflectance under the sensor: a logistic blend across the edge."""
        ys = self.y + self.p.ahead * np.sin(self.psi)
        blend = 1 / (1 + np.exp(-4 * ys / self.p.spot))
        return self.p.black + (self.white_run - self.p.black) * blend

    def read(self) -> np.ndarray:
        """The colour readings now (N,), after the sensor effects, in whole percent as the brick reports."""
        return colour_reading(self, self.sensed, 1.0)

    def _turn(self, command: np.ndarray) -> np.ndarray:
        """Turn command after delay, dead zone, play and limits."""
        return steering_command(self, command)

    def _curvature(self) -> np.ndarray:
        """Curvature of the edge under the robot (1/mm)."""
        fx, k = self.fx, self.kappa0.copy()
        if "curvature" in fx:
            cv = fx["curvature"]
            wave = np.sin(2 * math.pi * self.s / (cv["wavelength_m"] * 1000) + self.curve_phase)
            k = k + (cv["mean_per_m"] + cv["amp_per_m"] * wave) / 1000
        if "arc" in fx:
            a = fx["arc"]
            inside = (self.s >= a["start_m"] * 1000) & (self.s < (a["start_m"] + a["length_m"]) * 1000)
            k = k + np.where(inside, a["per_m"] / 1000, 0.0)
        return k

    def apply(self, angle_deg: np.ndarray, dt_s: np.ndarray | float) -> None:
        """Turn with the controller's angle (N,) for ``dt_s`` seconds, then latch the sensor."""
        fx, p = self.fx, self.p
        turn = self._turn(np.asarray(angle_deg, dtype=np.float64).reshape(self.n))
        h = np.broadcast_to(np.asarray(dt_s, dtype=np.float64), (self.n,)) / SUBSTEPS
        volt = self.gain_run
        if "battery" in fx:
            volt = volt * (1 - fx["battery"]["sag"] * min(self.t / self.horizon_s, 1.0))
        for _ in range(SUBSTEPS):
            if "lag" in fx:
                self.lagged = self.lagged + (turn - self.lagged) * (1 - np.exp(-h * 1000 / fx["lag"]["tau_ms"]))
                goal = self.lagged
            else:
                goal = turn
            if "rate_limit" in fx:
                r = fx["rate_limit"]["deg_per_s"] * h
                self.rated = self.rated + np.clip(goal - self.rated, -r, r)
                goal = self.rated
            diff = p.turn_gain * goal * self.turn_run
            if self.patches_on():
                diff = diff * np.where(self._on_patch(), fx["patches"]["grip"], 1.0)
            v_cmd = np.stack([volt * (1 + diff), volt * (1 - diff)])  # +angle: left faster, turn toward black
            v_eff = np.sign(v_cmd) * np.maximum(np.abs(v_cmd) - p.motor_deadzone, 0.0) / (1 - p.motor_deadzone)
            self.omega = self.omega + (v_eff - self.omega) * (1 - np.exp(-h * 1000 / p.motor_tau_ms))
            v = p.wheel_speed * self.omega.mean(0)
            yaw = p.wheel_speed * (self.omega[1] - self.omega[0]) / p.track
            a = 1 - np.exp(-h * 1000 / p.slip_tau_ms)
            self.slip = self.slip * (1 - a) + p.slip_sd * np.sqrt(a * (2 - a)) * self.rng.standard_normal(self.n)
            self.psi = np.clip(self.psi + (yaw + self.slip - v * self._curvature()) * h, -1.3, 1.3)
            self.y = self.y + v * np.sin(self.psi) * h
            self.s = self.s + v * np.cos(self.psi) * h
            self.t += float(h.mean())
        if self.next_kick is not None:
            due = self.t >= self.next_kick
            self.psi = np.where(due, self.psi + self.kick_sign * math.radians(self.fx["kick"]["deg"]), self.psi)
            self.kick_sign = np.where(due, -self.kick_sign, self.kick_sign)
            self.next_kick = np.where(due, self.next_kick + self.fx["kick"]["period_s"], self.next_kick)
        surface = self.latched
        self.latched = self._surface()
        if "lowpass" in fx:
            self.sensed = self.sensed + (surface - self.sensed) * (
                1 - np.exp(-h * SUBSTEPS * 1000 / fx["lowpass"]["tau_ms"])
            )
        else:
            self.sensed = surface

    def start_logging(self, elapsed_s: float) -> None:
        """The first logged row: battery sag counts from here and the kick schedule, drawn from the
        start of the warmup, moves back by the ``elapsed_s`` seconds the warmup took."""
        self.t = 0.0
        if self.next_kick is not None:
            self.next_kick = self.next_kick - elapsed_s

    def patches_on(self) -> bool:
        return "patches" in self.fx and self.fx["patches"]["per_m"] > 0

    def _on_patch(self) -> np.ndarray:
        """On a slippery patch: patches spaced evenly at per_m, each length_mm long, per-run phase."""
        pt = self.fx["patches"]
        spacing = 1000.0 / pt["per_m"]
        return ((self.s / spacing + self.patch_phase) % 1.0) * spacing < pt["length_mm"]


def generate_diffdrive(
    controller: ControllerSpec,
    runs: int,
    steps: int = 100,
    effects: Mapping[str, Any] | None = None,
    seed: int = 0,
    profile: DiffDriveProfile | None = None,
) -> list[Log]:
    """``runs`` logs of ``steps`` rows of the differential-drive world driven by ``controller``; the
    sidecar records the world, the profile, every effect with its parameters and the seed."""
    if runs < 1 or steps < 1:
        raise ValueError(f"diffdrive twin: runs and steps must be positive, got {runs} and {steps}")
    profile = profile or DiffDriveProfile()
    active = resolve_diffdrive(effects)
    rng = np.random.default_rng(seed)
    total = profile.warmup + steps
    logged, moving = sample_periods(active, profile.period_ms, (runs, total), rng)
    batch = DiffDriveBatch(profile, active, runs, rng)
    batch.horizon_s = max(float(moving[:, profile.warmup :].sum(1).mean()) / 1000, 1e-9)
    time, color, angle = drive(batch, controller, profile.warmup, logged, moving)
    provenance = {"world": "diffdrive", "effects": active, "injected": sorted(active), "seed": seed}
    return lane_logs(
        controller, time, color, angle, profile.period_ms, f"diffdrive_{seed}", provenance, profile.to_json()
    )


def resemblance(real: list[Log], runs: int = 20, steps: int = 100, seed: int = 0) -> list[dict[str, Any]]:
    """Per controller version x of the real logs: colour percentiles (5, 25, 50, 75, 95) and the median
    oscillation period (ticks, from crossings of 40) of the real logs and of clean diffdrive logs."""
    from .calibrate import run_stats

    by_x: dict[float, list[np.ndarray]] = {}
    for lg in real:
        x = lg.param.get("x")
        if isinstance(x, (int, float)) and len(lg) >= steps:
            by_x.setdefault(float(x), []).append(lg.states[:steps, 0])
    rows = []
    for x, cols in sorted(by_x.items()):
        twin = generate_diffdrive(ControllerSpec("lane-keeping", {"x": x}), runs, steps, seed=seed)
        for source, c in (("real", np.stack(cols)), ("diffdrive", np.stack([lg.states[:, 0] for lg in twin]))):
            rows.append(
                {
                    "x": x,
                    "source": source,
                    "runs": int(c.shape[0]),
                    "percentiles": np.percentile(c, [5, 25, 50, 75, 95]).tolist(),
                    "period": float(np.median(run_stats(c)[:, 0])),
                }
            )
    return rows


def resemblance_table(rows: list[dict[str, Any]]) -> str:
    """:func:`resemblance` as a markdown table."""
    lines = ["| x | source | runs | colour p5 / p25 / p50 / p75 / p95 | period (ticks) |", "|---:|---|---:|---|---:|"]
    for r in rows:
        pct = " / ".join(f"{v:.0f}" for v in r["percentiles"])
        lines.append(f"| {r['x']:g} | {r['source']} | {r['runs']} | {pct} | {r['period']:.1f} |")
    return "\n".join(lines)
