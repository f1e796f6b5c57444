"""What every training algorithm shares: model set-up, the training record and closed-loop selection.

Model selection is by closed-loop error on held-out validation logs: each validation log's
controller is simulated against the candidate model from the log's own sigma_0 and the goal-metric
distributions are compared (:func:`closed_loop_score`). One-step loss alone picks
models that drift in closed loop (the compounding error the paper warns about).
"""

from __future__ import annotations

import copy
from dataclasses import dataclass, field
from typing import Any, Sequence

import numpy as np
import torch

from ..dataset import Normaliser, interval_quantiles
from ..logs import Log, group_by_controller
from ..model import Checkpoint, EnvModel, ModelConfig, TrainingRecord
from ..goals.evaluate import signals_of
from ..goals.presets import goals_of
from ..goals.selection import SelectionScore, selection_score
from ..simulate import simulate_versions
from ..system import LogSchema, SystemDescription, describe_schema


def data_record(logs: Sequence[Log]) -> list[dict[str, Any]]:
    """Each log's file, content hash and controller version: enough to read it back exactly, even
    when its version came from a file-name pattern."""
    return [
        {"file": str(lg.path) if lg.path else lg.name, "sha256": lg.sha256(), "controller": lg.meta.controller}
        for lg in logs
    ]


def controllers_of(logs: Sequence[Log]) -> list[dict[str, Any]]:
    return [spec.to_json() for spec in group_by_controller(logs)]


def model_config(
    logs: Sequence[Log],
    history: int = 10,
    hidden: Sequence[int] = (256, 256),
    head: str = "deterministic",
    **extra: Any,
) -> ModelConfig:
    extra.setdefault("limit_events", limit_events(logs))
    return ModelConfig(
        n_state=logs[0].states.shape[1],
        n_action=logs[0].actions.shape[1],
        history=history,
        hidden=tuple(hidden),
        head=head,
        **extra,
    )


def limit_events(logs: Sequence[Log]) -> tuple[tuple[int, float], ...]:
    """(state index, reading) for each state the schema declares a saturating sensor and whose
    training readings reach a limit of its declared range (the upper one first: an ultrasonic
    sensor reads its maximum without echo): what :class:`~envi_py.model.EnvModel` predicts as events."""
    out = []
    for i, ch in enumerate(logs[0].meta.schema.states):
        if not ch.saturates:
            continue
        tol = ch.resolution / 2 if ch.resolution else 0.0
        values = np.concatenate([lg.states[:, i] for lg in logs])
        for limit in (ch.high, ch.low):
            if np.isfinite(limit) and np.any(np.abs(values - limit) <= tol):
                out.append((i, float(limit)))
                break
    return tuple(out)


def new_checkpoint(
    algorithm: str,
    train_logs: Sequence[Log],
    val_logs: Sequence[Log],
    config: ModelConfig,
    seed: int,
    hyper: dict[str, Any],
    norm: Normaliser | None = None,
    system: SystemDescription | None = None,
) -> Checkpoint:
    """A freshly initialised model (seeded) with its normaliser fitted on the training logs only; it
    records ``system`` (by default the description matching the logs' schema)."""
    torch.manual_seed(seed)
    norm = norm or Normaliser.fit(train_logs)
    periods = [float(np.median(np.diff(lg.time))) for lg in train_logs if len(lg) > 1]
    period = float(np.median(periods)) if periods else None
    record = TrainingRecord(
        algorithm=algorithm,
        seed=seed,
        hyper=hyper,
        data=data_record(train_logs),
        validation=data_record(val_logs),
        controllers=controllers_of(train_logs),
        period_ms=period,
    )
    if "dt" in config.extras and config.intervals is None:
        config.intervals = interval_quantiles(train_logs, period or 40.0)
    schema = train_logs[0].meta.schema
    ckpt = Checkpoint(EnvModel(config), norm, schema, record, system or describe_schema(schema))
    ckpt.fit_limit_levels()
    return ckpt


def closed_loop_score(ckpt: Checkpoint, logs: Sequence[Log], seed: int = 0) -> SelectionScore:
    """Closed-loop error of ``ckpt`` on ``logs`` (lower is better): each log's controller simulated
    from its sigma_0, the system's goal metrics compared version by version (W1 over each goal's
    scale; default goals on every state when the system declares none), and runs that diverge
    beyond what the real runs do make the score infinite (:mod:`envi_py.goals.selection`)."""
    sims = simulate_versions(ckpt, logs, runs=1, seed=seed)
    skip, period = ckpt.config.history, ckpt.period_ms
    simulated = {c.name for c in ckpt.schema.channels}
    goals = tuple(g for g in (goals_of(ckpt.system) if ckpt.system else ()) if g.signal in simulated)
    real = {spec: signals_of(g, ckpt.schema, skip, period) for spec, g in group_by_controller(logs).items()}
    sim = {spec: signals_of(g, g[0].meta.schema, skip, period) for spec, g in group_by_controller(sims).items()}
    observed = {c.name: (float(ckpt.norm.low[i]), float(ckpt.norm.high[i])) for i, c in enumerate(ckpt.schema.states)}
    return selection_score(real, sim, LogSchema(ckpt.schema.states, ckpt.schema.actions), goals, observed)


@dataclass
class Selector:
    """Keeps the weights with the lowest closed-loop validation error seen so far; a model whose
    simulated runs diverge scores infinity and is never kept when any epoch did better."""

    val_logs: Sequence[Log]
    best_score: float = float("inf")
    best_epoch: int = -1
    best_state: dict[str, torch.Tensor] | None = None
    history: list[tuple[int, float]] = field(default_factory=list)
    diverged: list[int] = field(default_factory=list)

    def consider(self, ckpt: Checkpoint, epoch: int) -> float:
        if not self.val_logs:
            return float("nan")
        ckpt.model.eval()
        result = closed_loop_score(ckpt, self.val_logs)
        ckpt.model.train()
        self.history.append((epoch, result.distance))
        if result.diverged:
            self.diverged.append(epoch)
        if result.score < self.best_score:
            self.best_score, self.best_epoch = result.score, epoch
            self.best_state = copy.deepcopy(ckpt.model.state_dict())
        return result.distance

    def finish(self, ckpt: Checkpoint, last_epoch: int) -> Checkpoint:
        """Restore the best weights and record the choice in the checkpoint."""
        criterion = "closed-loop W1 of the goal metrics on validation logs, divergence excluded"
        if self.best_state is not None:
            ckpt.model.load_state_dict(self.best_state)
            ckpt.record.selection = {
                "criterion": criterion,
                "best_epoch": self.best_epoch,
                "best_score": self.best_score,
                "curve": self.history,
                "diverged_epochs": self.diverged,
            }
        elif self.val_logs:
            ckpt.record.selection = {
                "criterion": criterion,
                "best_epoch": last_epoch,
                "curve": self.history,
                "diverged_epochs": self.diverged,
                "warning": "every evaluated epoch diverged in closed loop on the validation "
                "logs; the last epoch is kept and should not be trusted",
            }
        else:
            ckpt.record.selection = {"criterion": "last epoch (no validation logs)", "best_epoch": last_epoch}
        ckpt.model.eval()
        return ckpt
