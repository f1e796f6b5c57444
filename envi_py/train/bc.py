"""Behaviour cloning (paper, Algorithm 1): supervised regression of the next state on the window.

As in the paper, one Adam step per log per epoch (each log's windows form one batch) and 300 epochs
by default, but lr 1e-3, not the paper's 5e-5: at 5e-5 the 300 epochs stop far short of a fit.
Measured with ``benchmarks/fidelity_real.py`` (2 folds, the authors' KLD, 10 real vs 10 simulated
runs per version): mean over x = 10..50 of 1.62 at n = 3 and 0.93 at n = 20 training logs per
version, against 4.14 and 1.70 at 5e-5; on the car twin (``benchmarks/fidelity_car.py``) the
exchangeability test passes on more versions and goals at 1e-3.

The loss is MSE for a deterministic model and the Gaussian negative log-likelihood for a
stochastic one. Every ``eval_every`` epochs the model is simulated in closed loop on the
validation logs; the epoch kept and when training stops (``epochs`` is a cap) are decided by
:class:`.common.Selector` with :class:`.common.SelectionSettings`.
"""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path
from typing import Any, Callable, Sequence

import numpy as np
import torch
from torch import nn
from tqdm import tqdm

from ..dataset import Dataset
from ..logs import Log
from ..system import LR_SCHEDULES, SystemDescription
from ..model import EnvModel, Checkpoint
from .common import SelectionSettings, Selector, model_config, new_checkpoint
from .input_noise import InputNoise
from .multistep import MultiStepLoss
from .state import TrainingState


def bc_loss(model: EnvModel, x: torch.Tensor, y: torch.Tensor, events: torch.Tensor | None = None) -> torch.Tensor:
    """MSE for a deterministic head, Gaussian NLL for a stochastic one; with limit events
    (``events`` (N, e): which targets are a saturating sensor's limit reading), binary
    cross-entropy for the event head, and the value head is not trained on those targets."""
    return head_loss(model, model.heads(x), y, events)


def head_loss(
    model: EnvModel,
    heads: tuple[torch.Tensor, torch.Tensor | None, torch.Tensor | None],
    y: torch.Tensor,
    events: torch.Tensor | None = None,
) -> torch.Tensor:
    """:func:`bc_loss` of the model's already computed heads (the multi-step loss scores each
    unrolled step with it)."""
    mean, log_std, logit = heads
    if log_std is None:
        per = (mean - y) ** 2
    else:
        per = nn.functional.gaussian_nll_loss(mean, y, (2 * log_std).exp(), full=False, reduction="none")
    if logit is None or events is None:
        return per.mean()
    keep = torch.ones_like(per, dtype=torch.bool)
    for k, (i, _) in enumerate(model.config.limit_events):
        keep[:, i] = ~events[:, k]
    value = (per * keep).sum() / keep.sum().clamp(min=1)
    return value + nn.functional.binary_cross_entropy_with_logits(logit, events.float())


def train_bc(
    train_logs: Sequence[Log],
    val_logs: Sequence[Log] = (),
    *,
    epochs: int = 300,
    lr: float = 1e-3,
    seed: int = 0,
    history: int = 10,
    hidden: Sequence[int] = (256, 256),
    head: str = "gaussian",
    eval_every: int = 10,
    selection: SelectionSettings | None = None,
    system: SystemDescription | None = None,
    progress: bool = False,
    state_path: str | Path | None = None,
    resume: bool = False,
    multistep: int = 0,
    input_noise: float = 0.0,
    lr_schedule: str = "constant",
    **model_extra: Any,
) -> Checkpoint:
    """Train a model by behaviour cloning on ``train_logs``; select on ``val_logs`` by closed-loop error.

    ``epochs`` is a cap: with validation logs, training stops once the smoothed validation score has
    not improved for ``selection.patience`` evaluations (:class:`.common.SelectionSettings`).

    ``multistep`` > 0 adds the loss of the model unrolled that many steps on its own predictions
    (:class:`.multistep.MultiStepLoss`) to each log's one-step loss; ``input_noise`` > 0 perturbs
    the states of the training windows by that many times their typical step (:class:`.input_noise.InputNoise`).
    ``lr_schedule`` "cosine" anneals the step size to 0 over ``epochs`` (:func:`learning_rate`) and then
    trains to that cap, whatever ``selection.patience`` says: the annealed end is the part of the
    training whose closed loop no longer jumps from one evaluation to the next.

    With ``state_path`` the whole training state is written there (atomically) after every
    validation, and ``resume`` continues from it: a run killed at any moment and resumed gives
    the same checkpoint as an uninterrupted one (see :class:`.state.TrainingState`)."""
    if lr_schedule not in LR_SCHEDULES:  # before any work, not at the first epoch
        raise ValueError(f"lr schedule must be one of {', '.join(LR_SCHEDULES)}, not {lr_schedule!r}")
    cfg = model_config(train_logs, history, hidden, head, **model_extra)
    selection = selection or SelectionSettings()
    if lr_schedule != "constant":  # an annealed schedule runs to its end: its small last steps are its point
        selection = replace(selection, patience=0)
    hyper = {
        "epochs": epochs,
        "lr": lr,
        "history": history,
        "hidden": list(hidden),
        "head": head,
        "eval_every": eval_every,
        "batch": "one log per step",
        "selection": selection.to_json(),
        "multistep": multistep,
        "input_noise": input_noise,
        "lr_schedule": lr_schedule,
    }
    ckpt = new_checkpoint("bc", train_logs, val_logs, cfg, seed, hyper, system=system)
    data = ckpt.dataset(train_logs, cut_at_breaks=True)
    xs, ys, evs, pieces = per_log_batches(ckpt, data)
    unrolled = (
        MultiStepLoss(data, cfg.context, list(map(ckpt.limit_event_targets, data.Y)), multistep) if multistep else None
    )
    noisy = InputNoise(data, cfg.row_width, input_noise) if input_noise else None
    # fused: one kernel over all parameters; the per-tensor loop was a third of a step at this size
    opt = torch.optim.Adam(ckpt.model.parameters(), lr=lr, fused=True)
    rng = np.random.default_rng(seed)
    selector = Selector(val_logs, selection, one_step_loss(ckpt, val_logs))
    saver = TrainingState(Path(state_path), ckpt) if state_path is not None else None
    start = saver.restore(ckpt, opt, rng, selector) + 1 if saver is not None and resume else 1
    ckpt.model.train()
    bar = tqdm(range(start, epochs + 1), desc="bc", disable=not progress, leave=False)
    for epoch in bar:
        for group in opt.param_groups:
            group["lr"] = learning_rate(lr, lr_schedule, epoch, epochs)
        total = 0.0
        for i in rng.permutation(len(xs)):
            loss = bc_loss(ckpt.model, xs[i] if noisy is None else noisy(xs[i], rng), ys[i], evs[i])
            if unrolled is not None:  # over the log's pieces (entries of the dataset)
                loss = loss + sum(unrolled(ckpt.model, k, head_loss) for k in pieces[i]) / len(pieces[i])
            opt.zero_grad()
            loss.backward()
            opt.step()
            total += loss.item()
        if epoch % eval_every == 0 or epoch == epochs:
            score = selector.consider(ckpt, epoch, total / len(xs))
            bar.set_postfix(loss=f"{total / len(xs):.2e}", val=f"{score:.4f}")
            if saver is not None:
                saver.save(epoch, ckpt, opt, rng, selector)
            if selector.should_stop():
                return selector.finish(ckpt, epoch)
    return selector.finish(ckpt, epochs)


def learning_rate(lr: float, schedule: str, epoch: int, epochs: int) -> float:
    """The step size of ``epoch`` (1-based) of ``epochs``: ``lr`` throughout, or annealed from ``lr``
    towards 0 along half a cosine over the epoch cap. A function of the epoch alone, so a resumed
    training continues on the same schedule."""
    if schedule == "constant":
        return lr
    # "cosine"
    return lr * 0.5 * (1.0 + float(np.cos(np.pi * (epoch - 1) / max(epochs, 1))))


def one_step_loss(ckpt: Checkpoint, logs: Sequence[Log]) -> Callable[[Checkpoint], float] | None:
    """The mean :func:`bc_loss` over ``logs``' windows (each log weighs alike, as in training): the
    selector's tie-break. None without logs."""
    if not logs:
        return None
    batches = list(zip(*per_log_batches(ckpt, ckpt.dataset(logs, cut_at_breaks=True))[:3]))
    return lambda c: float(np.mean([bc_loss(c.model, x, y, e).item() for x, y, e in batches]))


def per_log_batches(
    ckpt: Checkpoint, data: Dataset
) -> tuple[list[torch.Tensor], list[torch.Tensor], list[torch.Tensor | None], list[list[int]]]:
    """One batch per log (the paper's BC step): the pairs of its pieces joined (none spans a break), so a
    log with lost rows weighs as any other rather than once per piece; with each log's dataset entries."""
    pieces: dict[int, list[int]] = {}
    for k, (li, _) in enumerate(data.origin):
        pieces.setdefault(li, []).append(k)
    groups = list(pieces.values())
    xs = [torch.tensor(np.concatenate([data.X[k] for k in g])) for g in groups]
    ys = [np.concatenate([data.Y[k] for k in g]) for g in groups]
    evs = [None if e is None else torch.from_numpy(e) for e in map(ckpt.limit_event_targets, ys)]
    return xs, [torch.tensor(y) for y in ys], evs, groups
