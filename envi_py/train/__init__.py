"""Training algorithms for environment models: each module turns logs into a :class:`Checkpoint`.

``bc`` (behaviour cloning), ``random`` (the paper's baseline); every algorithm shares
:mod:`.common` for data preparation, closed-loop model selection and the training record.
"""

from __future__ import annotations

import sys
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any, Callable, Sequence

from ..executor import LocalExecutor
from ..logs import Log
from ..model import Checkpoint
from ..system import STEP_NOISES, SystemDescription, check_members, describe_schema
from .common import SelectionSettings
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


def default_selection(system: SystemDescription) -> SelectionSettings:
    """How a training of ``system`` chooses its epoch unless told otherwise: the trainer's settings
    with the description's ``[training] select_runs`` (a system whose rare failures need more
    validation runs to be seen says so once, for the API and ``envi train`` alike)."""
    runs = system.training.select_runs
    return SelectionSettings(runs=runs) if runs else SelectionSettings()


def train(
    name: str,
    train_logs: Sequence[Log],
    val_logs: Sequence[Log] = (),
    system: SystemDescription | None = None,
    jobs: int = 1,
    **kwargs: Any,
) -> Checkpoint:
    """Train with the named algorithm. The system description the logs were read with is recorded
    in the checkpoint (from their schema when none is given), so the model says what it reads; its
    ``[training]`` defaults (residual head, input noise, step-noise shape, ensemble members, hidden
    widths, validation runs) apply unless ``kwargs`` say otherwise (``selection`` for the runs).
    ``step_noise="student-t"`` or ``"two-scale"`` fits a Gaussian head's tails after training
    (:mod:`.step_noise`).
    ``members=K`` trains K models from seeds ``seed``..``seed+K-1``
    and returns them as one seed ensemble (:meth:`Checkpoint.ensemble`); a resumable training keeps
    one state file per member (``<state>.member<k>`` beyond the first), and GAIL's loss curves are
    the first member's. ``jobs`` above 1 trains up to that many members at once, each in a spawned
    process of one torch thread (:class:`~envi_py.executor.LocalExecutor`): measured on this 2-core
    machine, two such trainings at n = 20 took 34 s together against 32 s for one on two threads;
    a member's weights then differ in the last bits from a one-process training of its seed."""
    if not train_logs:
        raise ValueError("no training logs")
    refuse_shared_logs(train_logs, val_logs)
    system = system or describe_schema(train_logs[0].meta.schema)
    kwargs = {**system.training.for_algorithm(name), **kwargs}
    if name != "random" and "selection" not in kwargs:
        kwargs["selection"] = default_selection(system)
    step_noise = kwargs.pop("step_noise", "gaussian")
    if step_noise not in STEP_NOISES:  # before training, not after it
        raise ValueError(f"step noise must be one of {', '.join(STEP_NOISES)}, not {step_noise!r}")
    members = check_members(kwargs.pop("members", 1))
    if members > 1 and name == "random":
        raise ValueError("the random baseline has no training to repeat: members must be 1")
    seed, state = kwargs.pop("seed", 0), kwargs.pop("state_path", None)
    states = None if state is None else member_state_paths(Path(state), members)
    plans = []
    for k in range(members):
        own = {**kwargs, "seed": seed + k}
        if states is not None:
            own["state_path"] = states[k]
            if k > 0 and own.get("resume") and not states[k].exists():
                own["resume"] = False  # a member the killed training never reached starts afresh
        if k > 0:
            own.pop("curves_dir", None)  # one file of loss curves: the first member's
        plans.append(MemberPlan(name, train_logs, val_logs, system, step_noise, own))
    workers = min(max(1, jobs), members)
    if workers > 1:  # progress bars of workers would interleave
        plans = [replace(p, kwargs={**p.kwargs, "progress": False}) for p in plans]
    progress = members > 1 and bool(kwargs.get("progress"))
    if progress:
        print(f"training {members} members (seeds {seed}..{seed + members - 1}), {workers} at a time", file=sys.stderr)
    done: dict[int, Checkpoint] = {}
    pool = LocalExecutor(workers if workers > 1 else 0)  # 0: one after another in this process
    try:
        for k, ckpt in pool.map(train_member, plans):
            done[k] = ckpt
            if progress:
                epoch = ckpt.record.selection.get("best_epoch", "-")
                print(f"member {k + 1} of {members} (seed {seed + k}) trained: epoch {epoch}", file=sys.stderr)
    finally:
        pool.close()
    return Checkpoint.ensemble([done[k] for k in range(members)])


def refuse_shared_logs(train_logs: Sequence[Log], val_logs: Sequence[Log]) -> None:
    """A validation log with a training log's rows (the same file, or a copy) is an error: the epoch
    would be chosen on data the model was fitted to, which cannot see it overfit."""
    seen = {lg.sha256(): lg for lg in train_logs}
    for lg in val_logs:
        twin = seen.get(lg.sha256())
        if twin is not None:
            other = twin.path or twin.name
            same = "is" if (lg.path or lg.name) == other else f"holds the rows of {other},"
            raise ValueError(
                f"{lg.path or lg.name}: this validation log {same} a training log; model selection needs "
                "logs the model was not fitted to"
            )


@dataclass(frozen=True)
class MemberPlan:
    """One training of :func:`train`: what a worker process needs to train one member."""

    algorithm: str
    train_logs: Sequence[Log]
    val_logs: Sequence[Log]
    system: SystemDescription
    step_noise: str
    kwargs: dict[str, Any]


def train_member(plan: MemberPlan) -> Checkpoint:
    """One model, its step-noise shape fitted: a member of :func:`train`'s ensemble (a module-level
    function, so a spawned worker can run it)."""
    ckpt = get_trainer(plan.algorithm)(plan.train_logs, plan.val_logs, system=plan.system, **plan.kwargs)
    with_step_noise(ckpt, plan.step_noise, plan.val_logs, plan.train_logs)
    return ckpt


def member_state_paths(state: Path, members: int) -> list[Path]:
    """The resumable state files of a training of ``members`` members (see :func:`train`)."""
    return [state if k == 0 else Path(f"{state}.member{k}") for k in range(members)]
