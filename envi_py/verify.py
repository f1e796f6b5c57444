"""Verification: real runs vs simulated runs of the same controller, metric by metric.

Runs are grouped by controller (name and parameters), because a metric distribution only means
something for one controller version. For each group the report gives the paper's accuracy, the
per-metric Wasserstein-1 and KS distances, the safety/comfort KLD, and the same figures between
two halves of the real runs (the FOT-vs-FOT floor) so a reader sees whether simulation is already
inside real-vs-real variation.
"""

from __future__ import annotations

import json
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Sequence

import numpy as np

from .logs import Log, group_by_controller
from .metrics import METRIC_NAMES, Distances, MetricConfig, distances, driving_metrics, floor


def traces(logs: Sequence[Log], channel: int = 0) -> np.ndarray:
    """The scored channel of equally long logs as (R, T); longer logs are cut to the shortest."""
    t = min(len(lg) for lg in logs)
    return np.stack([lg.states[:t, channel] for lg in logs])


def _dist_json(d: Distances) -> dict[str, Any]:
    return {"acc": d.acc, "kld": d.kld,
            "w1": dict(zip(METRIC_NAMES, d.w1.tolist())),
            "ks": dict(zip(METRIC_NAMES, d.ks.tolist())),
            "ks_p": dict(zip(METRIC_NAMES, d.ks_p.tolist()))}


@dataclass
class GroupResult:
    """Verification of one controller version."""

    controller: dict[str, Any]
    n_real: int
    n_sim: int
    real_mean: np.ndarray
    sim_mean: np.ndarray
    sim: Distances
    floor: Distances | None
    real_logs: list[str] = field(default_factory=list)

    def to_json(self) -> dict[str, Any]:
        return {"controller": self.controller, "n_real": self.n_real, "n_sim": self.n_sim,
                "real_mean": dict(zip(METRIC_NAMES, self.real_mean.tolist())),
                "sim_mean": dict(zip(METRIC_NAMES, self.sim_mean.tolist())),
                "sim_vs_real": _dist_json(self.sim),
                "floor": None if self.floor is None else _dist_json(self.floor),
                "real_logs": self.real_logs}


def verify(real: Sequence[Log], sim: Sequence[Log], cfg: MetricConfig = MetricConfig(),
           floor_splits: int = 20, seed: int = 0) -> list[GroupResult]:
    """Compare real and simulated logs per controller. A controller with no simulated runs is an error."""
    real_g, sim_g = group_by_controller(real), group_by_controller(sim)
    results = []
    for spec, rl in real_g.items():
        if spec not in sim_g:
            raise ValueError(f"no simulated runs for controller {spec.label()}; simulated: "
                             f"{', '.join(s.label() for s in sim_g) or 'none'}")
        sl = sim_g[spec]
        rt, st = traces(rl, cfg.channel), traces(sl, cfg.channel)
        t = min(rt.shape[1], st.shape[1])
        rt, st = rt[:, :t], st[:, :t]
        fl = floor(rt, cfg, floor_splits, seed) if floor_splits > 0 and len(rl) >= 4 else None
        results.append(GroupResult(spec.to_json(), len(rl), len(sl), driving_metrics(rt, cfg).mean(axis=0),
                                   driving_metrics(st, cfg).mean(axis=0), distances(rt, st, cfg), fl,
                                   [lg.name for lg in rl]))
    return results


def closed_loop_error(results: Sequence[GroupResult]) -> float:
    """One number for model selection: mean normalised W1 over metrics and controller versions.

    W1 compares whole distributions, so it penalises a model that gets the mean right with the wrong
    spread, which the paper's accuracy does not.
    """
    return float(np.mean([r.sim.w1.mean() for r in results]))


def _label(c: dict[str, Any]) -> str:
    params = ", ".join(f"{k}={v:g}" if isinstance(v, (int, float)) else f"{k}={v}" for k, v in c.get("params", {}).items())
    return f"{c.get('name')}({params})"


def to_markdown(results: Sequence[GroupResult], title: str = "Verification report") -> str:
    """Tables a person reads: accuracy and KLD per controller, then per-metric distances vs the floor."""
    lines = [f"# {title}", "",
             "acc: the paper's verification accuracy (1 = identical metric means). W1: Wasserstein-1 "
             "between real and simulated metric distributions, divided by the metric's possible range. "
             "KS: two-sample Kolmogorov-Smirnov statistic (p-value). Floor: the same between two halves of "
             "the real runs; simulation at or below the floor is as close as reality is to itself.", "",
             "| controller | real runs | sim runs | acc | acc floor | KLD (safety, comfort) | KLD floor |",
             "|---|---:|---:|---:|---:|---:|---:|"]
    for r in results:
        fa = f"{r.floor.acc:.2%}" if r.floor else "-"
        fk = f"{r.floor.kld:.3f}" if r.floor else "-"
        lines.append(f"| {_label(r.controller)} | {r.n_real} | {r.n_sim} | {r.sim.acc:.2%} | {fa} | "
                     f"{r.sim.kld:.3f} | {fk} |")
    for r in results:
        lines += ["", f"## {_label(r.controller)}", "",
                  "| metric | real mean | sim mean | W1 | W1 floor | KS (p) | KS floor |",
                  "|---|---:|---:|---:|---:|---:|---:|"]
        for j, m in enumerate(METRIC_NAMES):
            w1f = f"{r.floor.w1[j]:.4f}" if r.floor else "-"
            ksf = f"{r.floor.ks[j]:.3f}" if r.floor else "-"
            lines.append(f"| {m} | {r.real_mean[j]:.2f} | {r.sim_mean[j]:.2f} | {r.sim.w1[j]:.4f} | {w1f} | "
                         f"{r.sim.ks[j]:.3f} ({r.sim.ks_p[j]:.2g}) | {ksf} |")
        lines += ["", "Real logs: " + ", ".join(r.real_logs)]
    return "\n".join(lines) + "\n"


def to_text(results: Sequence[GroupResult]) -> str:
    """A compact screen table."""
    rows = [f"{'controller':<28} {'real':>5} {'sim':>5} {'acc':>8} {'floor':>8} {'meanW1':>8} {'floorW1':>8} {'KLD':>8}"]
    for r in results:
        rows.append(f"{_label(r.controller):<28} {r.n_real:>5} {r.n_sim:>5} {r.sim.acc:>8.2%} "
                    f"{(r.floor.acc if r.floor else float('nan')):>8.2%} {r.sim.w1.mean():>8.4f} "
                    f"{(r.floor.w1.mean() if r.floor else float('nan')):>8.4f} {r.sim.kld:>8.3f}")
    return "\n".join(rows)


def write_report(results: Sequence[GroupResult], out: Path, title: str = "Verification report",
                 extra: dict[str, Any] | None = None) -> tuple[Path, Path]:
    """``report.md`` and ``report.json`` in ``out``."""
    out.mkdir(parents=True, exist_ok=True)
    md, js = out / "report.md", out / "report.json"
    md.write_text(to_markdown(results, title))
    js.write_text(json.dumps({"title": title, **(extra or {}), "groups": [r.to_json() for r in results]}, indent=1))
    return md, js
