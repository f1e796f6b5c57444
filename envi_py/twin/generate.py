"""Generate twin logs in the project's log format, with sidecars that say exactly how they were made."""

from __future__ import annotations

import os
from pathlib import Path
from typing import Any, Protocol

import numpy as np

from envi_py.controllers import ControllerSpec, in_range
from envi_py.logs import LANE_KEEPING_SCHEMA, Log, LogMeta, write_log

from .effects import resolve
from .profile import TwinProfile, default_profile
from .world import Batch


def sample_periods(
    effects: dict[str, dict[str, float]], period_ms: float, shape: tuple[int, ...], rng: np.random.Generator
) -> tuple[np.ndarray, np.ndarray]:
    """Logged periods and the periods the robot actually moves (ms). They differ only in a pause:
    the real logs continue smoothly across their 10 s gaps, so the robot stood still."""
    jit = effects.get("jitter")
    if not jit:
        full = np.full(shape, float(period_ms))
        return full, full
    moving = period_ms + np.floor(rng.exponential(max(jit["extra_ms"], 1e-9), shape))
    paused = rng.random(shape) < jit["pause_prob"]
    pause = np.where(paused, np.round(jit["pause_ms"] * rng.uniform(0.75, 1.25, shape)), 0.0)
    return moving + pause, moving


def simulate(
    controller: ControllerSpec,
    runs: int,
    steps: int,
    effects: dict[str, dict[str, float]],
    profile: TwinProfile,
    rng: np.random.Generator,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Raw arrays of ``runs`` twin runs: time (R, T) ms from 0, colour (R, T), angle (R, T)."""
    total = profile.warmup + steps
    logged, moving = sample_periods(effects, profile.period_ms, (runs, total), rng)
    horizon = float(moving[:, profile.warmup :].sum(1).mean()) / 1000
    dist = profile.speed * 1.5 * float(moving.sum(1).max()) / 1000
    batch = Batch(profile, effects, runs, rng, horizon, dist)
    return drive(batch, controller, profile.warmup, logged, moving)


class LoggedWorld(Protocol):
    """What :func:`drive` needs of a batch of twin runs (both world families' batches have it)."""

    def read(self) -> np.ndarray: ...

    def apply(self, angle_deg: np.ndarray, dt_s: np.ndarray) -> None: ...

    def start_logging(self, elapsed_s: float) -> None: ...


def drive(
    batch: LoggedWorld, controller: ControllerSpec, warmup: int, logged: np.ndarray, moving: np.ndarray
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The closed loop of every twin world: ``batch`` driven by ``controller`` for the columns of
    ``moving`` (R, warmup + T) (the periods the robot moves, ms), the first ``warmup`` ticks unlogged.
    One function owns it so the steered and the diffdrive twins log the same way: the controller
    reads the colour each tick, the world is told when logging starts (``start_logging`` with the
    mean seconds moved so far), and time is the cumulative logged period from 0. Returns time (R, T)
    ms, colour (R, T), angle (R, T)."""
    runs, total = moving.shape
    steps = total - warmup
    ctrl = controller.build()
    ctrl.reset(runs)
    color, angle = np.empty((runs, steps)), np.empty((runs, steps))
    for i in range(total):
        if i == warmup:
            batch.start_logging(float(moving[:, :i].sum(1).mean()) / 1000)
        c = batch.read()
        a = np.asarray(ctrl(c[:, None]), dtype=np.float64).reshape(runs, -1)[:, :1]
        a = in_range(a, LANE_KEEPING_SCHEMA.actions, controller)[:, 0]  # as in simulation: no actuator can do more
        if i >= warmup:
            color[:, i - warmup], angle[:, i - warmup] = c, a
        batch.apply(a, moving[:, i] / 1000)
    dt = logged[:, warmup:]
    time = np.concatenate([np.zeros((runs, 1)), np.cumsum(dt[:, :-1], axis=1)], axis=1)
    return time, color, angle


def generate(
    controller: ControllerSpec,
    runs: int,
    steps: int = 100,
    effects: dict[str, Any] | None = None,
    seed: int = 0,
    profile: TwinProfile | None = None,
) -> list[Log]:
    """``runs`` twin logs of ``steps`` rows driven by ``controller``.

    ``effects`` go on top of the profile's own (a value of ``None``/0 switches a profile effect
    off); the sidecar records the profile, every active effect with its parameters, the ones the
    caller injected, and the seed, so the logs are reproducible and their ground truth is known.
    """
    if runs < 1 or steps < 1:
        raise ValueError(f"twin: runs and steps must be positive, got {runs} and {steps}")
    profile = profile or default_profile()
    active = resolve(profile.effects, effects)
    rng = np.random.default_rng(seed)
    time, color, angle = simulate(controller, runs, steps, active, profile, rng)
    prof = profile.to_json()
    prof.pop("fit", None)
    injected = sorted(resolve({}, {k: v for k, v in (effects or {}).items() if v not in (None, False, 0)}))
    provenance = {"effects": active, "injected": injected, "seed": seed}
    return lane_logs(controller, time, color, angle, profile.period_ms, f"twin_{seed}", provenance, prof)


def lane_logs(
    controller: ControllerSpec,
    time: np.ndarray,
    color: np.ndarray,
    angle: np.ndarray,
    period_ms: float,
    run_prefix: str,
    provenance: dict[str, Any],
    profile: dict[str, Any],
) -> list[Log]:
    """One lane-keeping log per run (rows of ``time``, ``color``, ``angle``), as both twin world
    families write them: run ids ``<run_prefix>_<r>``, the sidecar's provenance with the run index
    and the profile, so each log says how it was made."""
    logs = []
    for r in range(time.shape[0]):
        meta = LogMeta(
            schema=LANE_KEEPING_SCHEMA,
            controller=controller.to_json(),
            period_ms=period_ms,
            run_id=f"{run_prefix}_{r}",
            source="twin",
            provenance={**provenance, "run": r, "profile": profile},
        )
        logs.append(Log(None, time[r].copy(), color[r][:, None].copy(), angle[r][:, None].copy(), meta))
    return logs


def write_logs(logs: list[Log], out_dir: str | os.PathLike, prefix: str = "twin") -> list[Path]:
    """Write logs as ``<prefix>_<x>_<run>.csv`` (x when the controller has it) plus sidecars."""
    out = Path(out_dir)
    paths = []
    for i, lg in enumerate(logs):
        x = lg.param.get("x")
        tag = f"{prefix}_{x:g}_{i}" if isinstance(x, (int, float)) else f"{prefix}_{i}"
        lg.path = write_log(lg, out / f"{tag}.csv")
        paths.append(lg.path)
    return paths
