"""Training algorithms for environment models: each module turns logs into a :class:`Checkpoint`.

``bc`` (behaviour cloning), ``random`` (the paper's baseline); every algorithm shares
:mod:`.common` for data preparation, closed-loop model selection and the training record.
"""

from __future__ import annotations

from typing import Any, Callable, Sequence

from ..logs import Log
from ..model import Checkpoint
from ..system import STEP_NOISES, SystemDescription, describe_schema
from .step_noise import with_step_noise

Trainer = Callable[..., Checkpoint]


def get_trainer(name: str) -> Trainer:
    """The training function of an algorithm by name; imported lazily so each stays independent."""
    if name == "bc":
        from .bc import train_bc

        return train_bc
    if name == "random":
        from .random import train_random

        return train_random
    if name in ("gail", "bcxgail"):
        from . import gail

        return gail.train_gail if name == "gail" else gail.train_bcxgail
    raise ValueError(f"unknown algorithm {name!r}; known: bc, gail, bcxgail, random")


def train(
    name: str,
    train_logs: Sequence[Log],
    val_logs: Sequence[Log] = (),
    system: SystemDescription | None = None,
    **kwargs: Any,
) -> Checkpoint:
    """Train with the named algorithm. The system description the logs were read with is recorded
    in the checkpoint (from their schema when none is given), so the model says what it reads; its
    ``[training]`` defaults (residual head, input noise, step-noise shape) apply unless ``kwargs``
    say otherwise. ``step_noise="student-t"`` fits a Gaussian head's tails after training
    (:mod:`.step_noise`)."""
    if not train_logs:
        raise ValueError("no training logs")
    system = system or describe_schema(train_logs[0].meta.schema)
    kwargs = {**system.training.for_algorithm(name), **kwargs}
    step_noise = kwargs.pop("step_noise", "gaussian")
    if step_noise not in STEP_NOISES:  # before training, not after it
        raise ValueError(f"step noise must be one of {', '.join(STEP_NOISES)}, not {step_noise!r}")
    ckpt = get_trainer(name)(train_logs, val_logs, system=system, **kwargs)
    with_step_noise(ckpt, step_noise, val_logs, train_logs)
    return ckpt
