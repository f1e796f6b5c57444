"""How far the gap shrinks: retrain with a candidate effect added (same data, same seed, same
hyper-parameters), simulate the confirmation logs with both models, compare the gaps."""

from __future__ import annotations

from dataclasses import asdict
from typing import Any, Sequence

import numpy as np

from ..logs import Log, group_by_controller
from ..metrics import MetricConfig
from ..model import Checkpoint
from ..simulate import simulate_logs
from ..train import train
from ..verify import traces
from .effects import Finding
from .gap import metric_gaps


def retrain_with(ckpt: Checkpoint, finding: Finding, train_logs: Sequence[Log], val_logs: Sequence[Log]) -> Checkpoint:
    """The same training as ``ckpt`` with the finding's model change applied."""
    rec = ckpt.record
    cfg = {k: v for k, v in asdict(ckpt.config).items() if k not in ("n_state", "n_action", "kind")}
    cfg.update(finding.fix)
    hyper = {k: rec.hyper[k] for k in ("epochs", "lr", "eval_every") if k in rec.hyper}
    return train(rec.algorithm, train_logs, val_logs, seed=rec.seed, **hyper, **cfg)


def simulate_groups(
    ckpt: Checkpoint, logs: Sequence[Log], runs: int, seed: int
) -> list[tuple[str, np.ndarray, np.ndarray]]:
    """(label, real traces, simulated traces) per controller version."""
    out = []
    for spec, group in group_by_controller(logs).items():
        sims = simulate_logs(ckpt, spec, group, runs=runs, seed=seed)
        real, sim = traces(group), traces(sims)
        t = min(real.shape[1], sim.shape[1])
        out.append((spec.label(), real[:, :t], sim[:, :t]))
    return out


def gap_summary(
    groups: Sequence[tuple[str, np.ndarray, np.ndarray]], metric: MetricConfig, seed: int
) -> dict[str, Any]:
    """Per-metric W1 (with interval) and floor, averaged over controller versions."""
    per = [metric_gaps(real, sim, metric, boot=100, seed=seed) for _, real, sim in groups]
    names = [g["metric"] for g in per[0]]
    rows = {}
    for name in names:
        items = [next(g for g in gs if g["metric"] == name) for gs in per]
        rows[name] = {
            "w1": float(np.mean([i["w1"] for i in items])),
            "ci": [float(np.mean([i["ci"][0] for i in items])), float(np.mean([i["ci"][1] for i in items]))],
            "floor": float(np.mean([i["floor"] for i in items])),
        }
    mean_w1 = float(np.mean([r["w1"] for r in rows.values()]))
    mean_floor = float(np.mean([r["floor"] for r in rows.values()]))
    return {
        "metrics": rows,
        "mean_w1": mean_w1,
        "mean_floor": mean_floor,
        "inside_floor": sum(r["w1"] <= r["floor"] * 1.5 for r in rows.values()),
    }


def shrink(
    ckpt: Checkpoint,
    findings: Sequence[Finding],
    train_logs: Sequence[Log],
    val_logs: Sequence[Log],
    confirm_logs: Sequence[Log],
    metric: MetricConfig,
    runs: int = 10,
    seed: int = 0,
) -> dict[str, Any]:
    """Before/after gaps on the confirmation logs for each finding, plus the untouched model."""
    before = gap_summary(simulate_groups(ckpt, confirm_logs, runs, seed), metric, seed)
    after = []
    for f in findings:
        fixed = retrain_with(ckpt, f, train_logs, val_logs)
        summary = gap_summary(simulate_groups(fixed, confirm_logs, runs, seed), metric, seed)
        after.append(
            {
                "effect": f.effect,
                "fix": f.to_json()["fix"],
                **summary,
                "shrink": 1 - summary["mean_w1"] / max(before["mean_w1"], 1e-12),
            }
        )
    return {"before": before, "after": after, "confirm_logs": [lg.name for lg in confirm_logs]}
