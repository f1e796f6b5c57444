"""The paper's comparison baseline: a model whose next state is drawn uniformly at random over the
range seen in training, whatever the action. Nothing is learnt; it exists so every report can show
how far above chance a learnt model is."""

from __future__ import annotations

from typing import Any, Sequence

from ..logs import Log
from ..model import Checkpoint
from ..system import SystemDescription
from .common import model_config, new_checkpoint


def train_random(
    train_logs: Sequence[Log],
    val_logs: Sequence[Log] = (),
    seed: int = 0,
    history: int = 10,
    system: SystemDescription | None = None,
    **_: Any,
) -> Checkpoint:
    """A random-state model with the normaliser of ``train_logs``."""
    cfg = model_config(train_logs, history=history, hidden=(), kind="random", limit_events=())
    ckpt = new_checkpoint("random", train_logs, val_logs, cfg, seed, {"history": history}, system=system)
    ckpt.record.selection = {"criterion": "none (random baseline)"}
    return ckpt
