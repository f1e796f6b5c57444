"""Training algorithms for environment models: each module turns logs into a :class:`Checkpoint`.

``bc`` (behaviour cloning), ``random`` (the paper's baseline); every algorithm shares
:mod:`.common` for data preparation, closed-loop model selection and the training record.
"""

from __future__ import annotations

import sys
from pathlib import Path
from typing import Any, Callable, Sequence

from ..logs import Log
from ..model import Checkpoint
from ..system import MAX_MEMBERS, STEP_NOISES, SystemDescription, describe_schema
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
    ``[training]`` defaults (residual head, input noise, step-noise shape, ensemble members) apply
    unless ``kwargs`` say otherwise. ``step_noise="student-t"`` fits a Gaussian head's tails after
    training (:mod:`.step_noise`). ``members=K`` trains K models from seeds ``seed``..``seed+K-1``
    and returns them as one seed ensemble (:meth:`Checkpoint.ensemble`); a resumable training keeps
    one state file per member (``<state>.member<k>`` beyond the first)."""
    if not train_logs:
        raise ValueError("no training logs")
    system = system or describe_schema(train_logs[0].meta.schema)
    kwargs = {**system.training.for_algorithm(name), **kwargs}
    step_noise = kwargs.pop("step_noise", "gaussian")
    if step_noise not in STEP_NOISES:  # before training, not after it
        raise ValueError(f"step noise must be one of {', '.join(STEP_NOISES)}, not {step_noise!r}")
    members = kwargs.pop("members", 1)
    if isinstance(members, bool) or not isinstance(members, int) or not 1 <= members <= MAX_MEMBERS:
        raise ValueError(f"members must be a whole number in 1..{MAX_MEMBERS}, not {members!r}")
    if members > 1 and name == "random":
        raise ValueError("the random baseline has no training to repeat: members must be 1")
    seed, state = kwargs.pop("seed", 0), kwargs.pop("state_path", None)
    states = None if state is None else member_state_paths(Path(state), members)
    ckpts = []
    for k in range(members):
        if states is not None:
            kwargs["state_path"] = states[k]
        if members > 1 and kwargs.get("progress"):
            print(f"member {k + 1} of {members} (seed {seed + k})", file=sys.stderr)
        ckpt = get_trainer(name)(train_logs, val_logs, system=system, seed=seed + k, **kwargs)
        with_step_noise(ckpt, step_noise, val_logs, train_logs)
        ckpts.append(ckpt)
    return Checkpoint.ensemble(ckpts)


def member_state_paths(state: Path, members: int) -> list[Path]:
    """The resumable state files of a training of ``members`` members (see :func:`train`)."""
    return [state if k == 0 else Path(f"{state}.member{k}") for k in range(members)]
