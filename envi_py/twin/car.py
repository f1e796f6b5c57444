"""The car twin: a small robot car keeping a lane edge while following a lead vehicle.

The project's second system (``envi_py/systems/car.toml``): two states, two actions, two PID loops.

Physics (:mod:`.car_world`), at the brick's 25 Hz (40 ms period), 4 Euler sub-steps per period:

- Drive: LEGO 56 mm tyres, so 1 deg/s of the wheels is 0.489 mm/s: the controller's 300 deg/s
  offset is 14.7 cm/s (the lane-keeping robot's 148 mm/s) and its 720 deg/s top 35 cm/s. The wheel
  speed follows the command through a first-order lag of 150 ms (motor plus the car's mass).
- Steering: front wheels follow the command through a 60 ms first-order servo, end stops at
  +-45 deg; kinematic bicycle with a 140 mm wheelbase; a positive angle turns toward black.
- Lane: a black/white edge with curvature ``mean + 1.0/m * sin(2 pi s / 1.5 m + phase)``, the mean
  per run ~ N(0, 0.3/m) (radii down to about 0.6 m, a table-top track), so that a gentle steering
  gain lags visibly behind the bends and the steering integral has work to do.
- Colour sensor 60 mm ahead of the rear axle (the lead that damps the steering loop), its reading
  a smooth step from black 5 to white ~75 (per-run sd 2.5) over a 20 mm spot, noise sd 1.5,
  rounded to 1 % and clipped to 0..100, as the lane-keeping twin.
- Lead vehicle on the same lane: per-run cruise speed 4-10 cm/s (slower than the ego's 14.7 cm/s
  at the set gap, so the ego must hold back: how far back is what kp_speed sets) and acceleration
  limit 15-30 cm/s^2
  (braking 40 cm/s^2); new speed targets arrive as a Poisson process at 0.5/s, each a stop
  (20 %), a slow-down to 30-60 % of cruise (30 %) or a cruise speed +-25 %.
- Gap: bumper to bumper along the lane, starting at 25-70 cm, or (20 % of runs) at 220-300 cm,
  beyond the echo so the ego starts by chasing at full speed and is often still chasing when
  logging starts. Touching bumpers hold the ego at
  the lead's speed (counted in the sidecar as ``contact_ticks``; none for the shipped versions).
- Ultrasonic sensor: gap plus noise sd 0.7 cm, rounded to 1 cm, clipped to 0..255; 255 (no echo)
  beyond a per-run range of 110-160 cm (a small target's echo is lost well before the sensor's
  nominal 2.5 m) and, with probability 0.002 per reading, a spurious 255 drop-out (one tick at
  full speed command, as on the real sensor). About 30 % of runs read 255 at least once.

Why these numbers: they are a LEGO-sized car at the lane-keeping robot's speed, and they make both
loops stable for every shipped version while the versions differ measurably.

- Steering (sensor lead 60 mm, servo 60 ms, 40 ms sampling), from an 8 mm offset on a straight
  edge without noise: kp_steer 0.8 undershoots to colour 26 and is back at 40 only after 1.6 s,
  2.0 undershoots to 30 and settles within about 1 s, and even 5.0 only rings (29, 42, 38) before
  settling. On the bends, the mean over 100 runs of the per-run mean |colour - 40| falls from 3.8
  (kp_steer 0.8) to 2.3 (2.0).
- Following: the stand-still gap is ``30 - offset / kp_speed`` (the description's offset 300), so
  kp_speed must be at least 15 for the car to stop 10 cm or more behind a stopped lead, and the
  gap it settles at behind a lead at v cm/s is ``30 + (v / 0.0489 - 300) / kp_speed``. The
  versions use kp_speed 18 to 50, looser to tighter following: over 100 runs each (seed 1) the
  median of the per-run median echo is 20 cm at 18 and 26 cm at 50, the median closest approach
  17 and 24 cm. (A kp_speed of 8 would stop 7.5 cm *past* a stopped lead: only touching bumpers
  would stop it; the description's default is 25.)

Controller memory: the world runs ``profile.warmup`` ticks (3 s) under the controller, then the
controller is reset and logging starts. So row 0 of every log is the first call of a fresh
controller: replaying a log's states from row 0 through a freshly built controller reproduces its
actions and PID-term columns exactly, which is also what the project's simulator assumes when it
warms a controller up on a log's first rows. The price is the integral the warm-up had built: it
starts again from 0 (the ``steer_i`` and ``speed_i`` columns show it rebuild), so over 200 runs
of kp_steer 0.8 the mean |colour - 40| is 4.8 on rows 10-29 against 3.7 on rows 30-99 (2.6 and
2.2 for kp_steer 2.0): a brick program restarted at the first logged row behaves the same way.
"""

from __future__ import annotations

import math
import os
from dataclasses import replace
from functools import cache
from pathlib import Path
from typing import Any

import numpy as np

from envi_py.controllers import ControllerSpec, in_range
from envi_py.logs import Log, LogMeta, write_log
from envi_py.system import SystemDescription, load_system

from .car_world import CarBatch, CarProfile

#: (kp_steer, kp_speed) of the five shipped versions: three to train on, then two unseen ones inside
#: the triangle the trained ones span (in each gain's range too).
CAR_GAINS: tuple[tuple[float, float], ...] = ((0.8, 18.0), (2.0, 18.0), (1.4, 50.0), (1.2, 25.0), (1.6, 33.0))
CAR_TRAINED: tuple[int, ...] = (0, 1, 2)
CAR_UNSEEN: tuple[int, ...] = (3, 4)


@cache
def car_system() -> SystemDescription:
    """The shipped car description, read once: its controller, actions' ranges and goals."""
    return load_system("car")


def car_versions() -> list[ControllerSpec]:
    """The five shipped controller versions, in :data:`CAR_GAINS` order (trained, then unseen)."""
    system = car_system()
    return [_spec(system.controller_for({"kp_steer": ks, "kp_speed": kv})) for ks, kv in CAR_GAINS]


def _spec(spec: ControllerSpec | None) -> ControllerSpec:
    if spec is None:
        raise ValueError("the car system description declares no controller")
    return spec


def with_options(profile: CarProfile, options: dict[str, Any]) -> CarProfile:
    """``profile`` with some fields replaced, each checked: a number where the profile has a
    number, a (low, high) pair where it has a range; counts and probabilities in their domains."""
    current = profile.to_json()
    changes: dict[str, Any] = {}
    for key, value in options.items():
        if key not in current:
            raise ValueError(f"car twin: unknown world parameter {key!r}; known: {', '.join(current)}")
        if isinstance(current[key], list):
            if (
                not isinstance(value, (list, tuple))
                or len(value) != 2
                or not all(_finite(v) for v in value)
                or not value[0] <= value[1]
            ):
                raise ValueError(f"car twin: {key} must be a (low, high) pair of numbers, not {value!r:.40}")
            changes[key] = (float(value[0]), float(value[1]))
        elif not _finite(value) or value < 0:
            raise ValueError(f"car twin: {key} must be a non-negative number, not {value!r:.40}")
        elif isinstance(current[key], int):
            if value != int(value):
                raise ValueError(f"car twin: {key} must be a whole number, not {value!r}")
            changes[key] = int(value)
        else:
            changes[key] = float(value)
    out = replace(profile, **changes)
    for key in ("dropout_prob", "far_start_prob", "lead_stop_prob", "lead_slow_prob"):
        if getattr(out, key) > 1:
            raise ValueError(f"car twin: {key} is a probability, not {getattr(out, key)}")
    for key in (
        "period_ms",
        "substeps",
        "wheel_mm",
        "wheelbase_mm",
        "spot_mm",
        "steer_tau_s",
        "motor_tau_s",
        "wavelength_m",
    ):
        if getattr(out, key) <= 0:
            raise ValueError(f"car twin: {key} must be positive")
    return out


def _finite(v: Any) -> bool:
    return isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(v)


def simulate_car(
    controller: ControllerSpec, runs: int, steps: int, profile: CarProfile, rng: np.random.Generator
) -> tuple[np.ndarray, np.ndarray, np.ndarray, CarBatch]:
    """Raw arrays of ``runs`` car runs: states (R, T, 2), actions (R, T, 2), PID terms (R, T, 6),
    and the world (for its hidden state). See the module docstring for the controller reset."""
    world = CarBatch(profile, runs, rng)
    ctrl = controller.build(n_state=2, n_action=2, period_ms=profile.period_ms)
    loops = getattr(getattr(ctrl, "inner", None), "loops", None)
    if loops is None or len(loops) != 2 or not all(hasattr(lp, "terms") for lp in loops):
        raise ValueError(
            f"car twin: controller {controller.label()!r} is not a 'combine' of two PID loops; "
            "the logged P, I and D columns need them"
        )
    ctrl.reset(runs)
    channels = car_system().schema.actions  # a command no actuator can do is an error, as in simulation
    states, actions = np.empty((runs, steps, 2)), np.empty((runs, steps, 2))
    terms = np.empty((runs, steps, 6))
    for i in range(profile.warmup + steps):
        if i == profile.warmup:
            ctrl.reset(runs)
        s = world.read()
        a = in_range(np.asarray(ctrl(s), dtype=np.float64), channels, controller)
        if i >= profile.warmup:
            t = i - profile.warmup
            states[:, t], actions[:, t] = s, a
            terms[:, t] = np.concatenate([np.asarray(lp.terms, dtype=np.float64) for lp in loops], axis=1)
        world.apply(a)
    return states, actions, terms, world


def generate_car(
    controller: ControllerSpec,
    runs: int,
    steps: int = 100,
    seed: int = 0,
    profile: CarProfile | None = None,
    **options: Any,
) -> list[Log]:
    """``runs`` car logs of ``steps`` rows driven by ``controller`` (a ``combine`` of two loops).

    ``options`` override :class:`CarProfile` fields (``dropout_prob=0``, ``far_start_prob=0.5``...).
    The sidecar records the controller, the seed, the run, the world's parameters and, when the
    controller is a shipped version, its index in :func:`car_versions`.
    """
    if runs < 1 or steps < 1:
        raise ValueError(f"car twin: runs and steps must be positive, got {runs} and {steps}")
    profile = with_options(profile or CarProfile(), options)
    system = car_system()
    rng = np.random.default_rng(seed)
    states, actions, terms, world = simulate_car(controller, runs, steps, profile, rng)
    time = np.arange(steps) * profile.period_ms
    versions = car_versions()
    version = versions.index(controller) if controller in versions else None
    logs = []
    for r in range(runs):
        meta = LogMeta(
            schema=system.schema,
            controller=controller.to_json(),
            period_ms=profile.period_ms,
            run_id=f"car_{seed}_{r}",
            source="twin",
            provenance={
                "system": "car",
                "seed": seed,
                "run": r,
                "version": version,
                "world": profile.to_json(),
                "contact_ticks": int(world.contact_ticks[r]),
                "controller_reset_at_row": 0,
            },
        )
        logs.append(Log(None, time.copy(), states[r].copy(), actions[r].copy(), meta, terms[r].copy()))
    return logs


def generate_car_versions(
    runs: int, steps: int = 100, seed: int = 0, versions: list[int] | None = None, **options: Any
) -> list[Log]:
    """``runs`` logs of each shipped version (all five by default); version ``i`` uses seed
    ``seed + 1000 * i`` so versions meet different lanes and leads, as field runs would."""
    specs = car_versions()
    chosen = list(range(len(specs))) if versions is None else versions
    bad = [i for i in chosen if not 0 <= i < len(specs)]
    if bad:
        raise ValueError(f"car twin: no version {bad[0]}; versions are 0..{len(specs) - 1}")
    return [lg for i in chosen for lg in generate_car(specs[i], runs, steps, seed + 1000 * i, **options)]


def car_log_name(log: Log) -> str:
    """``car_<kp_steer>_<kp_speed>_<run>.csv``: readable with the pattern
    ``car_{kp_steer}_{kp_speed}_{run}.csv``, and versions never collide."""
    loops = log.param.get("loops") or [{}, {}]
    gains = [lp.get("params", {}).get("kp") for lp in loops[:2]]
    if len(gains) != 2 or not all(isinstance(g, (int, float)) for g in gains):
        raise ValueError(f"{log.name}: not a car log (its controller has no two loops with a 'kp')")
    return f"car_{gains[0]:g}_{gains[1]:g}_{log.meta.provenance.get('run', 0)}.csv"


def write_car_logs(logs: list[Log], out_dir: str | os.PathLike) -> list[Path]:
    """Write car logs with their sidecars as ``car_<kp_steer>_<kp_speed>_<run>.csv``."""
    names = [car_log_name(lg) for lg in logs]
    dup = sorted({n for n in names if names.count(n) > 1})
    if dup:
        raise ValueError(f"car twin: two logs would both be written as {dup[0]} (same version and run)")
    out = Path(out_dir)
    paths = []
    for lg, name in zip(logs, names):
        lg.path = write_log(lg, out / name)
        paths.append(lg.path)
    return paths
