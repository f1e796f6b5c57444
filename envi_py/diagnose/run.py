"""The whole diagnosis of one model against real logs: choose on one set of logs, confirm on another."""

from __future__ import annotations

from dataclasses import dataclass, field, replace
from typing import Any, Sequence

import numpy as np

from ..dataset import split_logs
from ..logs import Log, group_by_controller
from ..metrics import MetricConfig
from ..model import Checkpoint
from ..simulate import initial_windows, rollout
from .effects import MIN_SHARE, Finding, misfit_share, run_candidates
from .gap import by_run, by_version, coverage, horizon_gap, metric_gaps, residual_map, windows_of
from .residuals import one_step_residuals
from .shrink import shrink, simulate_groups


@dataclass
class Diagnosis:
    """Everything the report shows; plain data so it serialises to JSON as it is."""

    findings: list[Finding]
    gaps: list[dict[str, Any]]  # per controller version: ranked metric gaps
    horizon: list[dict[str, Any]]
    residual_map: dict[str, Any]
    versions: list[dict[str, Any]]
    coverage: dict[str, Any]
    shrink: dict[str, Any] | None
    runs: list[dict[str, Any]] = field(default_factory=list)  # per choose log, largest residual first
    misfit: float = 0.0  # share of the one-step residual that is a smooth function of the window
    choose_logs: list[str] = field(default_factory=list)
    confirm_logs: list[str] = field(default_factory=list)

    @property
    def significant(self) -> list[Finding]:
        return [f for f in self.findings if f.significant]

    @property
    def no_gap(self) -> bool:
        """True when every goal metric of every controller version is within its real-vs-real floor."""
        return not has_gap(self.gaps)

    def verdict(self) -> str:
        """One paragraph a person reads first."""
        gaps = [g["gaps"][0] for g in self.gaps]
        worst = max(gaps, key=lambda g: g["ratio"])
        size = (
            "the real runs never differ in it, the simulated ones do"
            if worst["ratio"] == float("inf")
            else f"{worst['ratio']:.1f}x the real-vs-real floor"
        )
        text = (
            f"The largest closed-loop gap is in {worst['metric']} ({size}). "
            f"Simulated runs leave the band of real runs after a median of {self.horizon[0]['median_exit_step']:.0f} "
            f"steps; {self.coverage['outside_share']:.0%} of simulated windows lie outside the training data. "
        )
        sig = self.significant
        if self.no_gap:
            return text + (
                "Every goal metric is within its real-vs-real floor: there is no closed-loop gap to "
                "attribute, so no candidate effect is called significant (their tests are listed "
                "for information)."
            )
        if self.misfit >= 0.5:
            text += (
                f"{self.misfit:.0%} of the one-step residual is a smooth function of the window: the model is "
                f"wrong where it has seen similar windows, as when these logs come from a world the training "
                f"logs do not show; training on such logs, not an added effect, closes that part. "
            )
        if not sig:
            return text + "No candidate effect explains a significant share of the one-step residuals."
        names = ", ".join(
            f"{f.effect} ({f.share:.0%} of residual mean square)"
            if f.share >= f.what_if
            else f"{f.effect} (its what-if removes {f.what_if:.0%} of the residual mean square)"
            for f in sig
        )
        text += f"Significant candidate effects, most important first: {names}. "
        if self.shrink and self.shrink["after"]:
            best = max(self.shrink["after"], key=lambda a: a["shrink"])
            b = self.shrink["before"]
            text += (
                f"Adding {best['effect']} changes the mean normalised W1 on the confirmation logs from "
                f"{b['mean_w1']:.4f} to {best['mean_w1']:.4f} ({best['shrink']:+.0%} shrink; floor "
                f"{b['mean_floor']:.4f}); {best['inside_floor']}/8 metrics within 1.5x the floor."
            )
        return text

    def to_json(self) -> dict[str, Any]:
        return {
            "verdict": self.verdict(),
            "findings": [f.to_json() for f in self.findings],
            "gaps": self.gaps,
            "horizon": self.horizon,
            "residual_map": self.residual_map,
            "versions": self.versions,
            "coverage": self.coverage,
            "shrink": self.shrink,
            "runs": self.runs,
            "misfit": self.misfit,
            "choose_logs": self.choose_logs,
            "confirm_logs": self.confirm_logs,
        }


def split_choose_confirm(logs: Sequence[Log], seed: int) -> tuple[list[Log], list[Log]]:
    """Half of each controller version's logs to choose the effect, half to confirm it."""
    choose, confirm = [], []
    for group in group_by_controller(logs).values():
        a, b = split_logs(group, [0.5, 0.5], seed)
        choose += a
        confirm += b
    return choose, confirm


def has_gap(gaps: Sequence[dict[str, Any]]) -> bool:
    """Is any goal metric of any controller version beyond its real-vs-real floor? Without such a
    gap an effect may be detectable in the one-step residuals yet causes nothing worth fixing: a
    negative control of a robot that never leaves its set-point (every metric equal in every run)
    otherwise shows residual structure of a thousandth of a colour unit as an effect."""
    return any(row["ratio"] > 1.0 for g in gaps for row in g["gaps"])


def diagnose(
    ckpt: Checkpoint,
    real: Sequence[Log],
    confirm: Sequence[Log] | None = None,
    train_logs: Sequence[Log] | None = None,
    val_logs: Sequence[Log] | None = None,
    metric: MetricConfig = MetricConfig(),
    runs: int = 10,
    top: int = 2,
    retrain: bool = True,
    alpha: float = 0.05,
    min_share: float = MIN_SHARE,
    seed: int = 0,
) -> Diagnosis:
    """Diagnose ``ckpt`` on ``real`` logs; effects are confirmed on ``confirm`` (default: half of ``real``)."""
    choose, confirm_l = (list(real), list(confirm)) if confirm else split_choose_confirm(real, seed)
    res = one_step_residuals(ckpt, choose)
    groups = simulate_groups(ckpt, choose, runs, seed)
    gaps = [{"controller": label, "gaps": metric_gaps(r, s, metric, seed=seed)} for label, r, s in groups]
    findings = run_candidates(res, ckpt, alpha, min_share, logs=choose)
    if not has_gap(gaps):
        findings = [replace(f, significant=False) for f in findings]
    horizon = [{"controller": label, **horizon_gap(r, s, metric.skip, seed)} for label, r, s in groups]
    train_logs = list(train_logs) if train_logs is not None else ckpt.recorded_logs("data")
    if val_logs is None:
        val_logs = ckpt.recorded_logs("validation") if ckpt.record.validation else []
    hist = ckpt.config.history
    train_w = np.concatenate(ckpt.dataset(train_logs).X)[:, : hist * ckpt.config.row_width]
    sims_full = []
    for spec, group in group_by_controller(choose).items():
        sims_full.append(
            rollout(ckpt, spec, initial_windows(group, hist), min(len(g) for g in group) - hist, runs=1, seed=seed)
        )
    sim_w = np.concatenate([windows_of(s, ckpt.norm.encode, hist, metric.skip) for s in sims_full])
    cov = (
        coverage(train_w, sim_w.astype(np.float32), seed)
        if ckpt.config.plain
        else {
            "threshold": float("nan"),
            "outside_share": float("nan"),
            "median_distance": float("nan"),
            "train_median_distance": float("nan"),
        }
    )
    sig = [f for f in findings if f.significant][:top]
    shrunk = shrink(ckpt, sig, train_logs, val_logs, confirm_l, metric, runs, seed) if retrain and sig else None
    return Diagnosis(
        findings,
        gaps,
        horizon,
        residual_map(res),
        by_version(groups, metric),
        cov,
        shrunk,
        by_run(res, [lg.name for lg in choose]),
        misfit_share(res),
        [lg.name for lg in choose],
        [lg.name for lg in confirm_l],
    )
