"""What every training algorithm shares: model set-up, the training record and closed-loop selection.

Model selection is by closed-loop error on held-out validation logs: each validation log's
controller is simulated against the candidate model from the log's own sigma_0 and the goal-metric
distributions are compared (:func:`envi_py.verify.closed_loop_error`). One-step loss alone picks
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
from ..metrics import MetricConfig
from ..model import Checkpoint, EnvModel, ModelConfig, TrainingRecord
from ..simulate import simulate_versions
from ..verify import closed_loop_error, verify


def data_record(logs: Sequence[Log]) -> list[dict[str, Any]]:
    """Each log's file, content hash and controller version: enough to read it back exactly, even
    when its version came from a file-name pattern."""
    return [{"file": str(lg.path) if lg.path else lg.name, "sha256": lg.sha256(), "controller": lg.meta.controller}
            for lg in logs]


def controllers_of(logs: Sequence[Log]) -> list[dict[str, Any]]:
    return [spec.to_json() for spec in group_by_controller(logs)]


def model_config(logs: Sequence[Log], history: int = 10, hidden: Sequence[int] = (256, 256),
                 head: str = "deterministic", **extra: Any) -> ModelConfig:
    return ModelConfig(n_state=logs[0].states.shape[1], n_action=logs[0].actions.shape[1], history=history,
                       hidden=tuple(hidden), head=head, **extra)


def new_checkpoint(algorithm: str, train_logs: Sequence[Log], val_logs: Sequence[Log], config: ModelConfig,
                   seed: int, hyper: dict[str, Any], norm: Normaliser | None = None) -> Checkpoint:
    """A freshly initialised model (seeded) with its normaliser fitted on the training logs only."""
    torch.manual_seed(seed)
    norm = norm or Normaliser.fit(train_logs)
    periods = [float(np.median(np.diff(lg.time))) for lg in train_logs if len(lg) > 1]
    period = float(np.median(periods)) if periods else None
    record = TrainingRecord(algorithm=algorithm, seed=seed, hyper=hyper, data=data_record(train_logs),
                            validation=data_record(val_logs), controllers=controllers_of(train_logs),
                            period_ms=period)
    if "dt" in config.extras and config.intervals is None:
        config.intervals = interval_quantiles(train_logs, period or 40.0)
    return Checkpoint(EnvModel(config), norm, train_logs[0].meta.schema, record)


def closed_loop_score(ckpt: Checkpoint, logs: Sequence[Log], metric: MetricConfig, seed: int = 0) -> float:
    """Closed-loop error of ``ckpt`` on ``logs`` (lower is better)."""
    sims = simulate_versions(ckpt, logs, runs=1, seed=seed)
    return closed_loop_error(verify(logs, sims, metric, floor_splits=0))


@dataclass
class Selector:
    """Keeps the weights with the lowest closed-loop validation error seen so far."""

    val_logs: Sequence[Log]
    metric: MetricConfig = field(default_factory=MetricConfig)
    best_score: float = float("inf")
    best_epoch: int = -1
    best_state: dict[str, torch.Tensor] | None = None
    history: list[tuple[int, float]] = field(default_factory=list)

    def consider(self, ckpt: Checkpoint, epoch: int) -> float:
        if not self.val_logs:
            return float("nan")
        ckpt.model.eval()
        score = closed_loop_score(ckpt, self.val_logs, self.metric)
        ckpt.model.train()
        self.history.append((epoch, score))
        if score < self.best_score:
            self.best_score, self.best_epoch = score, epoch
            self.best_state = copy.deepcopy(ckpt.model.state_dict())
        return score

    def finish(self, ckpt: Checkpoint, last_epoch: int) -> Checkpoint:
        """Restore the best weights and record the choice in the checkpoint."""
        if self.best_state is not None:
            ckpt.model.load_state_dict(self.best_state)
            ckpt.record.selection = {"criterion": "closed-loop mean normalised W1 on validation logs",
                                     "best_epoch": self.best_epoch, "best_score": self.best_score,
                                     "curve": self.history}
        else:
            ckpt.record.selection = {"criterion": "last epoch (no validation logs)", "best_epoch": last_epoch}
        ckpt.model.eval()
        return ckpt
