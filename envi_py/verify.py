"""Verification: real runs vs simulated runs of the same controller, goal metric by goal metric.

Runs are grouped by controller version (name and parameters), because a metric distribution only
means something for one version. The goal metrics are the system's (:func:`goals_for`: its preset,
e.g. the paper's eight lane-keeping metrics, and its declared goals; mean, spread and deviation of
every state when it declares none). For each version the report gives, per goal, the real and
simulated means, the Wasserstein-1 distance over the goal's scale and the Kolmogorov-Smirnov
statistic; the paper's accuracy over the goals; for the lane-keeping preset the authors' safety/
comfort KL divergence; and the same figures between real runs (the floor) so a reader sees whether
simulation is already inside real-vs-real variation.
"""

from __future__ import annotations

import json
import math
import warnings
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Sequence

import numpy as np
from scipy import stats

from .goals.evaluate import Runs, goal_scale, goal_table, signals_of
from .goals.presets import LANE_KEEPING_SIGNAL, goals_of, lane_keeping_centre
from .goals.selection import default_goals
from .controllers import ControllerSpec
from .logs import Log, group_by_controller
from .metrics import Distances, gaussian_kld
from .system import GoalSpec, LogSchema, SystemDescription, describe_schema


def goals_for(system: SystemDescription, schema: LogSchema) -> tuple[GoalSpec, ...]:
    """The goals a simulation can be scored on: the system's goals over simulated signals (states
    and actions), or default ones on every state when it declares none."""
    simulated = {c.name for c in schema.channels}
    goals = tuple(g for g in goals_of(system) if g.signal in simulated)
    if goals:
        return goals
    observed = {c.name: (c.low, c.high) for c in schema.states if math.isfinite(c.low) and math.isfinite(c.high)}
    return default_goals(LogSchema(schema.states, schema.actions), observed)


@dataclass(frozen=True)
class Scoring:
    """How runs are scored: the goals, their scales, the rows skipped (sigma_0) and the period."""

    goals: tuple[GoalSpec, ...]
    schema: LogSchema
    skip: int
    period_ms: float
    pair: bool  # the lane-keeping safety/comfort pair and its KLD apply

    @staticmethod
    def of(system: SystemDescription | None, schema: LogSchema, skip: int, period_ms: float) -> "Scoring":
        system = system or describe_schema(schema)
        return Scoring(goals_for(system, schema), LogSchema(schema.states, schema.actions), skip, period_ms,
                       system.preset == "lane-keeping" and LANE_KEEPING_SIGNAL in schema.columns)

    @property
    def names(self) -> list[str]:
        return [g.name for g in self.goals]

    def runs(self, logs: Sequence[Log]) -> Runs:
        """The logs' signals (real logs may carry logged-only columns, simulated ones do not)."""
        return signals_of(logs, logs[0].meta.schema, self.skip, self.period_ms)

    def table(self, runs: Runs) -> np.ndarray:
        """(R, G): every goal metric of every run."""
        values = goal_table(self.goals, runs)
        return np.stack([values[g.name] for g in self.goals], axis=1)

    def scales(self, runs: Runs) -> np.ndarray:
        """Each goal's scale (its possible range over these runs), 1 where none is defined."""
        out = []
        channels = {c.name: c for c in self.schema.channels}
        for g in self.goals:
            ch = channels[g.signal]
            s = goal_scale(g, ch.low, ch.high, runs.scored_length, runs.period_ms)
            out.append(s if s is not None and s > 0 and math.isfinite(s) else 1.0)
        return np.array(out)

    def pair_of(self, runs: Runs, centre: float) -> np.ndarray | None:
        """The authors' (safety, comfort) per run: max |c - centre| and max |third difference of c|."""
        if not self.pair:
            return None
        c = runs.scored(LANE_KEEPING_SIGNAL)
        d3 = np.diff(c, n=3, axis=1)
        comfort = np.abs(d3).max(axis=1) if d3.shape[1] else np.zeros(c.shape[0])
        return np.stack([np.abs(c - centre).max(axis=1), comfort], axis=1)


def table_distances(mr: np.ndarray, ms: np.ndarray, scale: np.ndarray, pr: np.ndarray | None,
                    ps: np.ndarray | None) -> Distances:
    """Distances between two samples of runs given their goal tables (R, G) and pairs."""
    w1 = np.array([stats.wasserstein_distance(mr[:, j], ms[:, j]) for j in range(mr.shape[1])]) / scale
    with warnings.catch_warnings():  # with ties scipy falls back from the exact to the asymptotic p-value
        warnings.simplefilter("ignore", RuntimeWarning)
        ks = [stats.ks_2samp(mr[:, j], ms[:, j]) for j in range(mr.shape[1])]
    acc = float(1.0 - np.mean(np.abs(mr.mean(axis=0) - ms.mean(axis=0)) / scale))
    kld = gaussian_kld(pr, ps) if pr is not None and ps is not None else float("nan")
    return Distances(w1, np.array([k.statistic for k in ks]), np.array([k.pvalue for k in ks]), acc, kld)


def halves_floor(mr: np.ndarray, scale: np.ndarray, pr: np.ndarray | None, splits: int, seed: int) -> Distances:
    """The same distances between two disjoint random halves of the real runs, averaged over
    ``splits`` halvings (KS p-value: the median)."""
    rng = np.random.default_rng(seed)
    n = mr.shape[0]
    parts = []
    for _ in range(splits):
        perm = rng.permutation(n)
        a, b = perm[: n // 2], perm[n // 2:]
        parts.append(table_distances(mr[a], mr[b], scale, None if pr is None else pr[a], None if pr is None else pr[b]))
    return Distances(np.mean([d.w1 for d in parts], axis=0), np.mean([d.ks for d in parts], axis=0),
                     np.median([d.ks_p for d in parts], axis=0), float(np.mean([d.acc for d in parts])),
                     float(np.mean([d.kld for d in parts])))


def _dist_json(d: Distances, names: Sequence[str]) -> dict[str, Any]:
    return {"acc": d.acc, "kld": None if math.isnan(d.kld) else d.kld,
            "w1": dict(zip(names, d.w1.tolist())),
            "ks": dict(zip(names, d.ks.tolist())),
            "ks_p": dict(zip(names, d.ks_p.tolist()))}


@dataclass
class GroupResult:
    """Verification of one controller version."""

    controller: dict[str, Any]
    version: str  # the version parameters (``x=30``), or the controller's label
    goals: list[str]
    n_real: int
    n_sim: int
    real_mean: np.ndarray
    sim_mean: np.ndarray
    sim: Distances
    floor: Distances | None
    real_logs: list[str] = field(default_factory=list)

    def to_json(self) -> dict[str, Any]:
        return {"controller": self.controller, "version": self.version, "goals": self.goals, "n_real": self.n_real, "n_sim": self.n_sim,
                "real_mean": dict(zip(self.goals, self.real_mean.tolist())),
                "sim_mean": dict(zip(self.goals, self.sim_mean.tolist())),
                "sim_vs_real": _dist_json(self.sim, self.goals),
                "floor": None if self.floor is None else _dist_json(self.floor, self.goals),
                "real_logs": self.real_logs}


def verify(real: Sequence[Log], sim: Sequence[Log], system: SystemDescription | None = None, skip: int = 10,
           floor_splits: int = 20, seed: int = 0, period_ms: float | None = None) -> list[GroupResult]:
    """Compare real and simulated logs per controller version. A version with no simulated runs is
    an error. ``skip`` rows (sigma_0, copied from the real log) are not scored."""
    if not real or not sim:
        raise ValueError("verification needs real and simulated logs")
    schema = real[0].meta.schema
    period = period_ms or (system.period_ms if system and system.period_ms else None) or \
        float(np.median(np.diff(real[0].time)))
    scoring = Scoring.of(system, schema, skip, period)
    centre = lane_keeping_centre(system or describe_schema(schema))
    real_g, sim_g = group_by_controller(real), group_by_controller(sim)
    results = []
    for spec, rl in real_g.items():
        if spec not in sim_g:
            raise ValueError(f"no simulated runs for controller {spec.label()}; simulated: "
                             f"{', '.join(s.label() for s in sim_g) or 'none'}")
        sl = sim_g[spec]
        t = min(min(len(lg) for lg in rl), min(len(lg) for lg in sl))
        rr = scoring.runs([_cut(lg, t) for lg in rl])
        sr = scoring.runs([_cut(lg, t) for lg in sl])
        mr, ms, scale = scoring.table(rr), scoring.table(sr), scoring.scales(rr)
        pr, ps = scoring.pair_of(rr, centre), scoring.pair_of(sr, centre)
        fl = halves_floor(mr, scale, pr, floor_splits, seed) if floor_splits > 0 and len(rl) >= 4 else None
        results.append(GroupResult(spec.to_json(), version_label(spec, system or describe_schema(schema)), scoring.names, len(rl), len(sl), mr.mean(axis=0), ms.mean(axis=0),
                                   table_distances(mr, ms, scale, pr, ps), fl, [lg.name for lg in rl]))
    return results


def _cut(log: Log, t: int) -> Log:
    """The first ``t`` rows of a log (real and simulated runs are scored over the same span)."""
    if len(log) == t:
        return log
    return Log(log.path, log.time[:t], log.states[:t], log.actions[:t], log.meta, log.logged[:t])


def traces(logs: Sequence[Log], channel: int = 0) -> np.ndarray:
    """One state channel of equally long logs as (R, T); longer logs are cut to the shortest."""
    t = min(len(lg) for lg in logs)
    return np.stack([lg.states[:t, channel] for lg in logs])


def version_label(spec: ControllerSpec, system: SystemDescription) -> str:
    """``x=30`` or ``kp_steer=0.8, kp_speed=18``: the version parameters the system names, else the
    controller's own label."""
    params = system.version_of(spec) if system.versions.params else {}
    if not params:
        return spec.label()
    return ", ".join(f"{k}={v:g}" if isinstance(v, (int, float)) else f"{k}={v}" for k, v in params.items())


def _fmt(v: float | None, spec: str) -> str:
    return "-" if v is None or (isinstance(v, float) and math.isnan(v)) else format(v, spec)


def to_markdown(results: Sequence[GroupResult], title: str = "Verification report") -> str:
    """Tables a person reads: accuracy and KLD per controller, then per-goal distances vs the floor."""
    lines = [f"# {title}", "",
             "acc: the paper's verification accuracy over the goal metrics (1 = identical means). W1: "
             "Wasserstein-1 between real and simulated metric distributions, divided by the metric's scale. "
             "KS: two-sample Kolmogorov-Smirnov statistic (p-value). KLD: the authors' safety/comfort KL "
             "divergence (lane keeping only). Floor: the same between two halves of the real runs.", "",
             "| controller | real runs | sim runs | acc | acc floor | KLD | KLD floor |",
             "|---|---:|---:|---:|---:|---:|---:|"]
    for r in results:
        fl = r.floor
        lines.append(f"| {r.version} | {r.n_real} | {r.n_sim} | {r.sim.acc:.2%} | "
                     f"{_fmt(fl.acc if fl else None, '.2%')} | {_fmt(r.sim.kld, '.3f')} | "
                     f"{_fmt(fl.kld if fl else None, '.3f')} |")
    for r in results:
        lines += ["", f"## {r.version}", "",
                  "| goal | real mean | sim mean | W1 | W1 floor | KS (p) | KS floor |",
                  "|---|---:|---:|---:|---:|---:|---:|"]
        for j, m in enumerate(r.goals):
            w1f = f"{r.floor.w1[j]:.4f}" if r.floor else "-"
            ksf = f"{r.floor.ks[j]:.3f}" if r.floor else "-"
            lines.append(f"| {m} | {r.real_mean[j]:.2f} | {r.sim_mean[j]:.2f} | {r.sim.w1[j]:.4f} | {w1f} | "
                         f"{r.sim.ks[j]:.3f} ({r.sim.ks_p[j]:.2g}) | {ksf} |")
        lines += ["", "Real logs: " + ", ".join(r.real_logs)]
    return "\n".join(lines) + "\n"


def to_text(results: Sequence[GroupResult]) -> str:
    """A compact screen table, the floor beside every figure."""
    rows = [f"{'controller':<34} {'real':>5} {'sim':>5} {'acc':>8} {'floor':>8} {'meanW1':>8} {'floorW1':>8} "
            f"{'KLD':>8} {'floorKLD':>8}"]
    for r in results:
        fl = r.floor
        rows.append(f"{r.version[:34]:<34} {r.n_real:>5} {r.n_sim:>5} {r.sim.acc:>8.2%} "
                    f"{_fmt(fl.acc if fl else None, '.2%'):>8} {r.sim.w1.mean():>8.4f} "
                    f"{_fmt(fl.w1.mean() if fl else None, '.4f'):>8} {_fmt(r.sim.kld, '.3f'):>8} "
                    f"{_fmt(fl.kld if fl else None, '.3f'):>8}")
    return "\n".join(rows)


def write_report(results: Sequence[GroupResult], out: Path, title: str = "Verification report",
                 extra: dict[str, Any] | None = None) -> tuple[Path, Path]:
    """``report.md`` and ``report.json`` in ``out``."""
    out.mkdir(parents=True, exist_ok=True)
    md, js = out / "report.md", out / "report.json"
    md.write_text(to_markdown(results, title))
    js.write_text(json.dumps({"title": title, **(extra or {}), "groups": [r.to_json() for r in results]}, indent=1))
    return md, js
