"""How far the gap shrinks: retrain with a candidate effect added (same data, same seed, same
hyper-parameters), simulate the confirmation logs with both models, compare the gaps on the
system's goals against the fair floor, with a bootstrap interval of the shrink over confirmation logs.

A fix that leaves the model's configuration as it is (a Gaussian head for noise on a model that has
one) is not retrained and is reported as ``unchanged``: it cannot shrink anything. Retraining adds an
effect only when the training logs show it; when they do not (a model of a clean robot verified
against a worn one), :mod:`.layers` fits the effect on the logs that show the gap instead."""

from __future__ import annotations

from dataclasses import asdict
from typing import Any, Sequence

import numpy as np
from scipy import stats

from ..controllers import ControllerSpec
from ..logs import Log, group_by_controller
from ..model import Checkpoint
from ..simulate import simulate_logs
from ..system import SystemDescription
from ..train import train
from ..verify import Scoring
from .effects import Finding
from .gap import LEVEL, cut_logs, goal_gaps

#: (version label, real logs, simulated logs), both cut to the same length.
Group = tuple[str, list[Log], list[Log]]


def scoring_of(ckpt: Checkpoint, skip: int | None = None) -> Scoring:
    """How the diagnosis scores runs: the system's goals over the rows after the initial window
    (sigma_0, which a simulation copies from its real log; ``skip`` rows, by default the history)."""
    return Scoring.of(ckpt.system, ckpt.schema, ckpt.config.history if skip is None else skip, ckpt.period_ms)


def _config_of(ckpt: Checkpoint) -> dict[str, Any]:
    """The model settings a retraining repeats (the step-noise shape is fitted after training, from
    the ``step_noise`` setting, not set)."""
    fitted = ("n_state", "n_action", "kind", "noise_dof", "noise_mix")
    return {k: v for k, v in asdict(ckpt.config).items() if k not in fitted}


def changes_model(ckpt: Checkpoint, finding: Finding) -> bool:
    """Does the finding's fix change the model's configuration at all?"""
    cfg = _config_of(ckpt)
    return any(
        cfg.get(k) != (list(v) if isinstance(v, tuple) and isinstance(cfg.get(k), list) else v)
        for k, v in finding.fix.items()
    )


def train_options(fix: dict[str, Any]) -> str:
    """A fix as the ``envi train`` options that make the same model change; a change the command line
    cannot express is given as the Python API's keyword (``envi_py.api.train(..., key=value)``)."""
    parts = []
    for key, value in fix.items():
        if key == "history":
            parts.append(f"--history {value}")
        elif key == "head":
            parts.append(f"--head {value}")
        elif key == "extras":
            parts.append("--extras " + " ".join(value))
        elif key == "play_width":
            parts.append(f"--play-width {value:g}")
        elif key == "context":
            parts.append("--context" if value else "--no-context")  # explicit: a description may default either way
        else:
            parts.append(f"(API: {key}={list(value) if isinstance(value, tuple) else value})")
    return " ".join(p for p in parts if p)


def retrain_with(ckpt: Checkpoint, finding: Finding, train_logs: Sequence[Log], val_logs: Sequence[Log]) -> Checkpoint:
    """The same training as ``ckpt`` with the finding's model change applied: one model, as the
    diagnosis reads one (a seed ensemble is diagnosed through its first member)."""
    rec = ckpt.record
    cfg = _config_of(ckpt)
    cfg.update(finding.fix)
    keys = ("epochs", "lr", "eval_every", "multistep", "input_noise", "step_noise")
    hyper = {k: rec.hyper[k] for k in keys if k in rec.hyper}
    return train(rec.algorithm, train_logs, val_logs, seed=rec.seed, members=1, **hyper, **cfg)


def simulate_groups(ckpt: Checkpoint, logs: Sequence[Log], runs: int, seed: int) -> list[Group]:
    """(version label, real logs, simulated logs) per controller version, cut to one length."""
    out = []
    for spec, group in group_by_controller(logs).items():
        sims = simulate_logs(ckpt, spec, group, runs=runs, seed=seed)
        t = min(min(len(lg) for lg in group), min(len(lg) for lg in sims))
        out.append((version_label(ckpt.system, spec), cut_logs(group, t), cut_logs(sims, t)))
    return out


def version_label(system: SystemDescription | None, spec: ControllerSpec) -> str:
    """The version as the system names it (``kp_steer=0.8,kp_speed=18``); the controller's own label
    when the system has no description or names parameters this controller lacks (a PID steering
    the lane-keeping twin has no ``x``)."""
    if system is None or any(p not in system.version_of(spec) for p in system.versions.params):
        return spec.label()
    return system.version_label(spec)


def gap_summary(groups: Sequence[Group], scoring: Scoring, seed: int) -> dict[str, Any]:
    """Per goal the matched W1 and the fair floor, averaged over controller versions, and how many
    goals are within the floor in every version (permutation test, p > LEVEL)."""
    per = [goal_gaps(scoring, real, sim, seed, boot=0) for _, real, sim in groups]
    rows = {}
    for goal in scoring.names:
        items = [next(r for r in g["gaps"] if r["goal"] == goal) for g in per]
        rows[goal] = {
            "w1": float(np.mean([i["w1"] for i in items])),
            "floor": float(np.mean([i["floor"] for i in items])),
            "floor_band": [
                float(np.mean([i["floor"] * i["ratio_null_band"][0] for i in items])),
                float(np.mean([i["floor"] * i["ratio_null_band"][1] for i in items])),
            ],
            "within": all(not i["beyond_floor"] for i in items),
        }
    return {
        "goals": rows,
        "mean_w1": float(np.mean([g["mean_w1"] for g in per])),
        "mean_floor": float(np.mean([g["mean_floor"] for g in per])),
        "inside_floor": sum(r["within"] for r in rows.values()),
        "n_goals": len(rows),
        "level": LEVEL,
    }


def _per_log_tables(groups: Sequence[Group], scoring: Scoring) -> list[tuple[np.ndarray, np.ndarray, np.ndarray]]:
    """Per version: the real goal table (R, G), the simulated one reshaped (R, runs, G) by initial
    log, and the goals' scales."""
    out = []
    for _, real, sim in groups:
        rr = scoring.runs(real)
        mr, ms = scoring.table(rr), scoring.table(scoring.runs(sim))
        out.append((mr, ms.reshape(mr.shape[0], -1, mr.shape[1]), scoring.scales(rr)))
    return out


def shrink_interval(
    before: Sequence[Group], after: Sequence[Group], scoring: Scoring, seed: int, boot: int = 500
) -> list[float]:
    """95% bootstrap interval (percentile, :func:`scipy.stats.bootstrap`) of ``1 - gap_after /
    gap_before`` over confirmation logs, resampled within each version with their simulations; the
    gap is the mean normalised W1 over goals of all real against all simulated runs."""
    tb, ta = _per_log_tables(before, scoring), _per_log_tables(after, scoring)
    sizes = [t[0].shape[0] for t in tb]
    owner = np.concatenate([np.full(n, k) for k, n in enumerate(sizes)])
    offsets = np.cumsum([0] + sizes)

    def gap(t: tuple[np.ndarray, np.ndarray, np.ndarray], i: np.ndarray) -> float:
        mr, ms, scale = t
        sim = ms[i].reshape(-1, ms.shape[2])
        return float(np.mean([stats.wasserstein_distance(mr[i, j], sim[:, j]) / scale[j] for j in range(mr.shape[1])]))

    def statistic(idx: np.ndarray) -> float:
        idx = np.asarray(idx, dtype=int)
        b, a = [], []
        for k in range(len(sizes)):
            i = idx[owner[idx] == k] - offsets[k]
            if len(i):
                b.append(gap(tb[k], i))
                a.append(gap(ta[k], i))
        return 1 - float(np.mean(a)) / max(float(np.mean(b)), 1e-12)

    res = stats.bootstrap(
        (np.arange(len(owner)),), statistic, n_resamples=boot, vectorized=False, method="percentile", random_state=seed
    )
    return [float(res.confidence_interval.low), float(res.confidence_interval.high)]


def shrink(
    ckpt: Checkpoint,
    findings: Sequence[Finding],
    train_logs: Sequence[Log],
    val_logs: Sequence[Log],
    confirm_logs: Sequence[Log],
    runs: int = 10,
    seed: int = 0,
    keep: dict[str, Checkpoint] | None = None,
) -> dict[str, Any]:
    """Before/after gaps on the confirmation logs for each finding, plus the untouched model. Every
    model is scored on the same rows: after the longest initial window any of them copies. Each
    retrained fix has ``shrink_ci`` (:func:`shrink_interval`); a fix that changes nothing is
    ``unchanged`` with the untouched model's figures and no interval. Each entry says how to train
    the fixed model (``train_options``); ``keep`` receives the retrained checkpoints whose shrink interval
    lies above 0, by effect (a fix that may as well widen the gap is reported, not offered), so a
    caller can save the model that closed the gap instead of throwing it away."""
    scoring = scoring_of(ckpt, max([ckpt.config.history] + [int(f.fix.get("history", 0)) for f in findings]))
    base_groups = simulate_groups(ckpt, confirm_logs, runs, seed)
    before = gap_summary(base_groups, scoring, seed)
    after = []
    for f in findings:
        if not changes_model(ckpt, f):
            after.append(
                {
                    "effect": f.effect,
                    "fix": f.to_json()["fix"],
                    **before,
                    "shrink": 0.0,
                    "shrink_ci": None,
                    "unchanged": True,
                }
            )
            continue
        fixed = retrain_with(ckpt, f, train_logs, val_logs)
        groups = simulate_groups(fixed, confirm_logs, runs, seed)
        summary = gap_summary(groups, scoring, seed)
        ci = shrink_interval(base_groups, groups, scoring, seed)
        if keep is not None and ci[0] > 0:  # only a fix shown to shrink the gap is offered to the user
            keep[f.effect] = fixed
        after.append(
            {
                "effect": f.effect,
                "fix": f.to_json()["fix"],
                **summary,
                "shrink": 1 - summary["mean_w1"] / max(before["mean_w1"], 1e-12),
                "shrink_ci": ci,
                "unchanged": False,
                "train_options": train_options(f.fix),
            }
        )
    return {"before": before, "after": after, "confirm_logs": [lg.name for lg in confirm_logs]}
