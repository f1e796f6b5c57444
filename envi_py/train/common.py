"""What every training algorithm shares: model set-up, the training record and closed-loop selection.

Model selection is by closed-loop error on held-out validation logs: each validation log's
controller is simulated against the candidate model from the log's own sigma_0 and the goal-metric
distributions are compared (:func:`closed_loop_score`). One-step loss alone picks
models that drift in closed loop (the compounding error the paper warns about). With a few
validation logs one evaluation is noisy, so several runs are simulated per log, the choice is made
on a moving average of the curve, and training stops on a plateau (:class:`Selector`).
"""

from __future__ import annotations

import copy
from dataclasses import dataclass, field
from typing import Any, Callable, Sequence

import numpy as np
import torch

from ..dataset import Normaliser, interval_quantiles
from ..logs import Log, group_by_controller
from ..model import Checkpoint, EnvModel, ModelConfig, TrainingRecord
from ..goals.evaluate import signals_of
from ..goals.presets import goals_of
from ..goals.selection import SelectionScore, runaway_states, selection_score
from ..simulate import simulate_versions
from ..system import Channel, LogSchema, SystemDescription, describe_schema


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
    """The model's configuration for ``logs``; unless given, simulated states are clamped to the range
    the training logs show and rounded to the resolution the schema declares (the real readings are
    on that grid). Measured on the real lane-keeping logs (n = 20, one model, 10 vs 10 runs per
    version): the same model's mean KLD over x = 10..50 went from 1.40 unrounded to 1.07 rounded and
    0.97 rounded and clamped to the observed range (``benchmarks/fidelity_real.py``)."""
    extra.setdefault("limit_events", limit_events(logs))
    extra.setdefault("round_to", declared_resolution(logs))
    extra.setdefault("limits", observed_limits(logs, extra["limit_events"]))
    return ModelConfig(
        n_state=logs[0].states.shape[1],
        n_action=logs[0].actions.shape[1],
        history=history,
        hidden=tuple(hidden),
        head=head,
        **extra,
    )


def declared_resolution(logs: Sequence[Log]) -> tuple[float, ...] | None:
    """Each state's declared resolution, or None unless every state declares one."""
    steps = tuple(ch.resolution for ch in logs[0].meta.schema.states)
    return steps if all(r is not None and r > 0 for r in steps) else None


def observed_limits(logs: Sequence[Log], events: Sequence[tuple[int, float]] = ()) -> tuple[tuple[float, float], ...]:
    """Each state's smallest and largest reading over ``logs``; for a state with a limit event
    (``events``: state index and reading) the range of its other readings, the sensor's in-range
    ones. Why: the event head draws the limit reading; what the value head draws is an in-range
    reading, and clamped to the full range it took values no real log holds. The car twin's
    ultrasonic sensor reads 12-152 cm or 255 (no echo); a car model started with the echo lost drew
    its first readings at 190-250 cm (median 213; real ones 18-153) and so closed in late. Measured
    with benchmarks/fidelity_car.py (default training, seeds 0-3, 20 test sets of 20 runs per
    version, pooled ratios, 2026-11-28): closest approach 1.4-4.0x its real-vs-real floor before,
    0.9-2.2x after; cells above 1.5x 7, 5, 7, 5 of 15 before, 2, 2, 6, 0 after (README, "Fidelity
    on the car twin")."""
    states = np.concatenate([lg.states for lg in logs])
    out = [(float(lo), float(hi)) for lo, hi in zip(states.min(axis=0), states.max(axis=0))]
    for i, level in events:
        other = states[~logs[0].meta.schema.states[i].reads(states[:, i], level), i]
        if other.size:
            out[i] = (float(other.min()), float(other.max()))
    return tuple(out)


def limit_events(logs: Sequence[Log]) -> tuple[tuple[int, float], ...]:
    """(state index, reading) for each state the schema declares a saturating sensor and whose
    training readings reach a limit of its declared range (the upper one first: an ultrasonic
    sensor reads its maximum without echo): what :class:`~envi_py.model.EnvModel` predicts as events."""
    out = []
    for i, ch in enumerate(logs[0].meta.schema.states):
        if not ch.saturates:
            continue
        values = np.concatenate([lg.states[:, i] for lg in logs])
        for limit in (ch.high, ch.low):
            if np.isfinite(limit) and np.any(ch.reads(values, limit)):
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


def closed_loop_score(ckpt: Checkpoint, logs: Sequence[Log], seed: int = 0, runs: int = 1) -> SelectionScore:
    """Closed-loop error of ``ckpt`` on ``logs`` (lower is better): ``runs`` simulated runs from each
    log's sigma_0 under its controller, the system's goal metrics compared version by version (W1
    over each goal's scale; default goals on every state when the system declares none), and runs
    that diverge beyond what the real runs do make the score infinite (:mod:`envi_py.goals.selection`).
    The same ``seed`` at every epoch makes successive scores differ by the model, not by the draws."""
    sims = simulate_versions(ckpt, logs, runs=runs, seed=seed)
    skip, period = ckpt.config.history, ckpt.period_ms
    simulated = {c.name for c in ckpt.schema.channels}
    goals = tuple(g for g in (goals_of(ckpt.system) if ckpt.system else ()) if g.signal in simulated)
    real = {spec: signals_of(g, ckpt.schema, skip, period) for spec, g in group_by_controller(logs).items()}
    sim = {spec: signals_of(g, g[0].meta.schema, skip, period) for spec, g in group_by_controller(sims).items()}
    observed = {c.name: (float(ckpt.norm.low[i]), float(ckpt.norm.high[i])) for i, c in enumerate(ckpt.schema.states)}
    schema = LogSchema(ckpt.schema.states, ckpt.schema.actions)
    return selection_score(real, sim, schema, goals, observed, limits=divergence_limits(ckpt))


def divergence_limits(ckpt: Checkpoint) -> list[Channel]:
    """The limits a diverged run of ``ckpt`` rests at: a saturating sensor's (one with limit events)
    at the range its simulated states are clamped to, its no-echo reading excepted
    (:func:`~envi_py.goals.selection.runaway_states`); every other state at its declared range. Why:
    a car model whose distance collapses onto its 12 cm clamp (the closest the training logs came)
    sits inside the declared and the observed range, so the selection kept such epochs; on this
    machine the car's default training did at seeds 0-3 (122, 126, 38 and 81 of 400 simulated test
    runs collapsed)."""
    clamped = runaway_states(
        ckpt.schema.states, [(float(lo), float(hi)) for lo, hi in zip(*ckpt.limits())], ckpt.config.limit_events
    )
    saturating = {i for i, _ in ckpt.config.limit_events}
    return [clamped[i] if i in saturating else ch for i, ch in enumerate(ckpt.schema.states)]


@dataclass(frozen=True)
class SelectionSettings:
    """How the best epoch is chosen; why each default (measured with ``benchmarks/fidelity_real.py``):

    - ``runs`` simulated runs per validation window: with one, a window's W1 is one draw of a
      stochastic model, and the curve's minimum picks the luckiest draw (at n = 3 the chosen epoch
      was noise); the runs of all windows are one batch, so 5 cost little more than 1.
    - ``smooth``: evaluations in the centred moving average the choice is made on, so one lucky
      evaluation does not win alone (1 = the raw curve).
    - ``tie``: smoothed scores within this fraction of the best are a tie, broken by the lower one-step
      validation loss (NLL; MSE for a deterministic head); 0 keeps the plain minimum.
    - ``patience``: evaluations without a new best smoothed score before training stops (0: never);
      ``epochs`` is then a cap, not the length of every training.
    """

    runs: int = 5
    smooth: int = 3
    tie: float = 0.0
    patience: int = 10

    def __post_init__(self) -> None:
        if self.runs < 1 or self.smooth < 1 or self.patience < 0 or not 0 <= self.tie < 1:
            raise ValueError(
                f"selection settings need runs >= 1, smooth >= 1, patience >= 0 and 0 <= tie < 1; got {self}"
            )

    def to_json(self) -> dict[str, Any]:
        return {"runs": self.runs, "smooth": self.smooth, "tie": self.tie, "patience": self.patience}


@dataclass
class Evaluation:
    """One validation: the closed-loop distance, whether it diverged, the one-step validation loss, and
    the epoch's mean training loss (beside the validation loss it tells under- from over-fitting)."""

    epoch: int
    distance: float
    diverged: bool
    one_step: float = float("nan")
    train_loss: float = float("nan")


@dataclass
class Selector:
    """Chooses the epoch to keep from closed-loop validation scores (see :class:`SelectionSettings`).

    Evaluation i's smoothed score is the mean distance over evaluations i-h..i+h (h = smooth // 2,
    truncated at the ends), infinite when i itself diverged; it is final once evaluation i+h is in,
    so the weights of the last h evaluations are held until then. The kept epoch has the lowest
    smoothed score, a tie (within ``tie``) going to the lower one-step loss. A model whose
    simulated runs diverge is never kept when any epoch did better."""

    val_logs: Sequence[Log]
    settings: SelectionSettings = field(default_factory=SelectionSettings)
    one_step: Callable[[Checkpoint], float] | None = None  # validation loss of one-step predictions
    evaluations: list[Evaluation] = field(default_factory=list)
    pending: list[tuple[int, dict[str, torch.Tensor]]] = field(default_factory=list)  # (index, weights)
    best_index: int = -1
    best_smoothed: float = float("inf")
    best_state: dict[str, torch.Tensor] | None = None
    stopped: str = ""

    @property
    def best_epoch(self) -> int:
        return self.evaluations[self.best_index].epoch if self.best_index >= 0 else -1

    def consider(self, ckpt: Checkpoint, epoch: int, train_loss: float = float("nan")) -> float:
        """Score the current weights; returns the raw closed-loop distance (NaN without validation logs).
        ``train_loss``: the epoch's mean training loss, recorded beside the validation curves."""
        if not self.val_logs:
            return float("nan")
        ckpt.model.eval()
        result = closed_loop_score(ckpt, self.val_logs, runs=self.settings.runs)
        loss = self._one_step(ckpt)
        ckpt.model.train()
        self.evaluations.append(Evaluation(epoch, result.distance, result.diverged, loss, train_loss))
        self.pending.append((len(self.evaluations) - 1, copy.deepcopy(ckpt.model.state_dict())))
        self._settle(final=False)
        return result.distance

    def should_stop(self) -> bool:
        """True when the smoothed score has not improved for ``patience`` evaluations."""
        patience = self.settings.patience
        if not patience or self.best_index < 0:
            return False
        settled = len(self.evaluations) - 1 - self.settings.smooth // 2
        if settled - self.best_index < patience:
            return False
        self.stopped = (
            f"stopped at epoch {self.evaluations[-1].epoch}: {patience} evaluations without a better smoothed "
            f"score than epoch {self.best_epoch}'s (the last ones, smoothed over fewer, were weighed at the end)"
        )
        return True

    def smoothed(self, i: int) -> float:
        """Evaluation i's smoothed score over the evaluations seen so far."""
        if self.evaluations[i].diverged:
            return float("inf")
        h = self.settings.smooth // 2
        window = self.evaluations[max(0, i - h) : i + h + 1]
        return float(np.mean([e.distance for e in window]))

    def _one_step(self, ckpt: Checkpoint) -> float:
        if self.one_step is None:
            return float("nan")
        with torch.no_grad():
            return float(self.one_step(ckpt))

    def _settle(self, final: bool) -> None:
        """Decide on every pending evaluation whose smoothing window is complete (all of them when final)."""
        h = self.settings.smooth // 2
        last = len(self.evaluations) - 1
        while self.pending and (final or self.pending[0][0] + h <= last):
            i, state = self.pending.pop(0)
            if self._better(i):
                self.best_index, self.best_smoothed, self.best_state = i, self.smoothed(i), state

    def _better(self, i: int) -> bool:
        score = self.smoothed(i)
        if not np.isfinite(score):
            return False
        if self.best_index < 0:
            return True
        tie = self.settings.tie * self.best_smoothed
        if score < self.best_smoothed - tie:
            return True
        if score <= self.best_smoothed + tie:
            mine, theirs = self.evaluations[i].one_step, self.evaluations[self.best_index].one_step
            return bool(mine < theirs) if np.isfinite(mine) and np.isfinite(theirs) else score < self.best_smoothed
        return False

    def to_state(self) -> dict[str, Any]:
        """What a resumed training needs (tensors, numbers, lists, dicts only)."""
        return {
            "evaluations": [[e.epoch, e.distance, e.diverged, e.one_step, e.train_loss] for e in self.evaluations],
            "pending": [[i, s] for i, s in self.pending],
            "best_index": self.best_index,
            "best_smoothed": self.best_smoothed,
            "best_state": self.best_state,
        }

    def load_state(self, blob: dict[str, Any]) -> None:
        # a state saved before the training loss was recorded has 4 fields per evaluation
        self.evaluations = [
            Evaluation(int(e[0]), float(e[1]), bool(e[2]), float(e[3]), float(e[4]) if len(e) > 4 else float("nan"))
            for e in blob["evaluations"]
        ]
        self.pending = [(int(i), s) for i, s in blob["pending"]]
        self.best_index, self.best_smoothed = int(blob["best_index"]), float(blob["best_smoothed"])
        self.best_state = blob["best_state"]

    def finish(self, ckpt: Checkpoint, last_epoch: int) -> Checkpoint:
        """Restore the chosen weights and record the choice, the curve and why training ended."""
        self._settle(final=True)
        tie = self.settings.tie
        criterion = (
            f"closed-loop W1 of the goal metrics on validation logs ({self.settings.runs} simulated runs per "
            f"window), centred moving average over {self.settings.smooth} evaluations, divergence excluded"
            + (f"; within {tie:.0%} of the best, the lower one-step validation loss" if tie else "")
        )
        curve = [[e.epoch, e.distance] for e in self.evaluations]
        common = {
            "criterion": criterion,
            "settings": self.settings.to_json(),
            "curve": curve,
            "one_step_curve": [[e.epoch, _finite_or_none(e.one_step)] for e in self.evaluations],
            "train_loss_curve": [[e.epoch, _finite_or_none(e.train_loss)] for e in self.evaluations],
            "diverged_epochs": [e.epoch for e in self.evaluations if e.diverged],
            "last_epoch": last_epoch,
            "stopped": self.stopped or f"reached the epoch cap ({last_epoch})",
        }
        if self.best_state is not None:
            ckpt.model.load_state_dict(self.best_state)
            best = self.evaluations[self.best_index]
            ckpt.record.selection = {
                **common,
                "best_epoch": best.epoch,
                "best_score": self.best_smoothed,
                "best_distance": best.distance,
                "best_one_step": _finite_or_none(best.one_step),
                "why": f"lowest smoothed closed-loop score {self.best_smoothed:.4g} at epoch {best.epoch}",
            }
        elif self.val_logs:
            ckpt.record.selection = {
                **common,
                "best_epoch": last_epoch,
                "warning": "every evaluated epoch diverged in closed loop on the validation "
                "logs; the last epoch is kept and should not be trusted",
            }
        else:
            ckpt.record.selection = {"criterion": "last epoch (no validation logs)", "best_epoch": last_epoch}
        ckpt.model.eval()
        return ckpt


def _finite_or_none(value: float) -> float | None:
    """JSON has no NaN, and NaN != NaN would make equal records compare unequal."""
    return value if np.isfinite(value) else None
