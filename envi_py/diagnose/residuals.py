"""One-step residuals: the model's prediction on real windows against the real next state, on every
state channel.

Each residual carries what the candidate-effect tests condition on: the run it came from, its row,
the state and action it was predicted from, the actual sampling interval, and the inputs that lie
*before* the window (for memory/delay). A :class:`Residuals` is one state channel in its physical
units (the tests are scale-free); a :class:`ResidualSet` holds every state channel and sums them in
units of each channel's range, so a colour in % and a distance in cm weigh alike.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field, replace
from functools import cached_property
from typing import Any, Sequence

import numpy as np
import torch

from ..dataset import play_offsets
from ..logs import Log
from ..model import Checkpoint

#: How many rows before the window the memory/delay test looks at.
BEYOND = 6

#: Widths of actuator play tried by the backlash test, as fractions of the action's training range:
#: 5% to 80% in steps of sqrt(2), so the true width is never far from one (a play filter of the
#: wrong width leaves part of the hysteresis to the linear memory test).
PLAY_WIDTHS = tuple(round(0.05 * 2 ** (k / 2), 4) for k in range(9))


@dataclass
class Residuals:
    """One state channel's residuals: flat arrays, one entry per predicted row."""

    r: np.ndarray  # real next state - predicted mean (physical units)
    pred_std: np.ndarray | None  # predicted standard deviation (Gaussian head), physical units
    predicted: np.ndarray  # the predicted mean, clamped to the model's range but not rounded
    real_next: np.ndarray
    state: np.ndarray  # last value of this state in the window
    action: np.ndarray  # last value of the action this view looks at (``action_name``)
    run: np.ndarray  # index of the log
    row: np.ndarray  # row index of the predicted state within its log
    dt: np.ndarray  # actual interval (ms) from the window's last row to the predicted row
    window: np.ndarray  # the window (N, l*W) in normalised units, every channel
    beyond: np.ndarray  # (N, BEYOND*C) normalised rows before the window; NaN where the log has none
    play: np.ndarray  # (N, len(PLAY_WIDTHS)): where an actuator with play of each width would sit
    #                   relative to the last command of ``action_name`` (see :func:`play_offsets`)
    other_play: np.ndarray | None = None  # the same for every other action, (N, k*len(PLAY_WIDTHS))
    name: str = "state"  # the state channel
    index: int = 0  # its index among the states
    action_name: str = "action"
    action_index: int = 0  # the index of that action
    unit: str = ""
    scale: float = 1.0  # the channel's range: declared, or the training data's where unbounded
    shared_pairs: Pairs | None = field(default=None, repr=False)  # the pairs, when computed for another view
    memo: dict[str, Any] = field(default_factory=dict, repr=False, compare=False)  # a test's costly search

    def __len__(self) -> int:
        return int(self.r.shape[0])

    @property
    def plays(self) -> np.ndarray:
        """The play offsets of every action (this view's first): what any hysteresis could explain."""
        return self.play if self.other_play is None else np.column_stack([self.play, self.other_play])

    def ms_by_run(self, runs: int) -> np.ndarray:
        """Mean square residual of each of ``runs`` logs (NaN for a log without residuals)."""
        return np.array(
            [float(np.mean(self.r[self.run == i] ** 2)) if np.any(self.run == i) else np.nan for i in range(runs)]
        )

    @cached_property
    def pairs(self) -> "Pairs":
        """Each residual matched with its nearest window from another run (see :class:`Pairs`)."""
        return self.shared_pairs if self.shared_pairs is not None else Pairs.match(self.window, self.run)


@dataclass(frozen=True)
class Pairs:
    """Residual ``i`` paired with ``j``, the residual whose window is nearest to ``i``'s among the
    other runs (normalised units).

    Why: a model's misfit is a smooth function of its window, so it cancels in ``r_i - r_j``; what
    is left is what the window does not determine: noise, and anything that differs between the two
    (time in the run, the sampling interval, the rows before the window, the run itself). The
    candidate tests regress these differences on the differences of the quantity they suspect,
    so the misfit of a well-structured model is not mistaken for an effect.
    """

    i: np.ndarray
    j: np.ndarray
    d2: np.ndarray  # squared window distance of the pair

    @staticmethod
    def match(window: np.ndarray, run: np.ndarray, k: int = 8) -> "Pairs":
        from scipy.spatial import cKDTree

        w = np.asarray(window, dtype=np.float64)
        k = min(k, len(w))
        dist, idx = cKDTree(w).query(w, k=k)
        dist, idx = dist.reshape(len(w), k), idx.reshape(len(w), k)
        other = run[idx] != run[:, None]
        first = np.argmax(other, axis=1)
        ok = other[np.arange(len(w)), first]
        i = np.flatnonzero(ok)
        j = idx[i, first[ok]]
        return Pairs(i, j, dist[i, first[ok]] ** 2)

    def __len__(self) -> int:
        return int(self.i.shape[0])


@dataclass
class ResidualSet:
    """Every state channel's residuals over the same rows, and the play of every action.

    ``states[k]`` looks at the first action; :meth:`view` gives state ``k`` seen against action ``j``
    (for a candidate tied to one action, such as the play of an actuator)."""

    states: tuple[Residuals, ...]
    actions: tuple[str, ...]
    action_values: np.ndarray  # (N, |a|) last command of every action in the window
    play_by_action: np.ndarray  # (N, |a|, len(PLAY_WIDTHS))

    @staticmethod
    def of(channel: Residuals) -> "ResidualSet":
        """A set of one state seen against one action (what a single-channel system has)."""
        return ResidualSet((channel,), (channel.action_name,), channel.action[:, None], channel.play[:, None, :])

    def __len__(self) -> int:
        return len(self.states[0])

    @property
    def run(self) -> np.ndarray:
        return self.states[0].run

    @property
    def row(self) -> np.ndarray:
        return self.states[0].row

    @property
    def names(self) -> list[str]:
        return [s.name for s in self.states]

    def view(self, k: int, j: int) -> Residuals:
        """State ``k`` seen against action ``j``: its ``action`` and ``play`` are that action's."""
        base = self.states[k]
        if base.action_index == j:
            return base
        others = [self.play_by_action[:, i] for i in range(len(self.actions)) if i != j]
        return replace(
            base,
            action=self.action_values[:, j],
            play=self.play_by_action[:, j],
            other_play=np.column_stack(others) if others else None,
            action_name=self.actions[j],
            action_index=j,
            shared_pairs=base.pairs,
            memo={},
        )

    def sq(self) -> np.ndarray:
        """(N,) squared residual in units of each channel's range, averaged over the states."""
        return np.mean([(s.r / s.scale) ** 2 for s in self.states], axis=0)

    def ms_by_run(self, runs: int) -> np.ndarray:
        """Mean square residual of each of ``runs`` logs, in units of each channel's range, averaged
        over the states (NaN for a log without residuals)."""
        return np.mean([s.ms_by_run(runs) / s.scale**2 for s in self.states], axis=0)


def channel_scale(low: float, high: float, half: float) -> float:
    """A state's range: its declared one, or the training data's (``2 * half``) where unbounded."""
    return high - low if math.isfinite(low) and math.isfinite(high) else 2.0 * half


@torch.no_grad()
def one_step_residuals(ckpt: Checkpoint, logs: Sequence[Log]) -> ResidualSet:
    """Feed every real window of ``logs`` to the model and collect the residuals of every state."""
    cfg = ckpt.config
    data = ckpt.dataset(logs)
    hist, ns, ch = cfg.history, cfg.n_state, cfg.channels
    keys = ("r", "pred_std", "predicted", "real_next", "state")
    per: dict[str, list[np.ndarray]] = {k: [] for k in keys}
    shared: dict[str, list[np.ndarray]] = {k: [] for k in ("run", "row", "dt", "window", "beyond", "acts", "play")}
    half = ckpt.norm.half
    for i, (lg, x) in enumerate(zip(logs, data.X)):
        mean, log_std, logit = ckpt.model.heads(torch.from_numpy(np.ascontiguousarray(x)))
        pred = ckpt.decode_states(mean.numpy().astype(np.float64), rounded=False)  # (n, |s|)
        n = len(pred)
        real_next = lg.states[hist:]
        std = np.exp(log_std.numpy()) * half[:ns] if log_std is not None else np.zeros((n, ns))
        if logit is not None:  # a limit event: the prediction is the mixture's mean and spread
            prob = 1.0 / (1.0 + np.exp(-logit.numpy().astype(np.float64)))
            for e, (k, value) in enumerate(cfg.limit_events):
                q, mu = prob[:, e], pred[:, k]
                std[:, k] = np.sqrt((1 - q) * std[:, k] ** 2 + q * (1 - q) * (value - mu) ** 2)
                pred[:, k] = q * value + (1 - q) * mu
        per["r"].append(real_next - pred)
        per["pred_std"].append(std)
        per["predicted"].append(pred)
        per["real_next"].append(real_next)
        per["state"].append(lg.states[hist - 1 : -1])
        rows = np.arange(hist, hist + n)
        shared["run"].append(np.full(n, i))
        shared["row"].append(rows)
        shared["dt"].append(np.diff(lg.time)[hist - 1 :])
        shared["window"].append(x[:, : hist * cfg.row_width])
        shared["acts"].append(lg.actions[hist - 1 : -1])
        z = ckpt.norm.encode(lg.values)
        beyond = np.full((n, BEYOND * ch), np.nan)
        for j, t in enumerate(rows):
            first = t - hist  # first row of the window
            block = z[max(0, first - BEYOND) : first]
            if len(block):
                beyond[j, (BEYOND - len(block)) * ch :] = block.ravel()
        shared["beyond"].append(beyond)
        # play of each action at each width (a fraction of the action's training range), in one pass
        widths = np.outer(2 * half[ns:], PLAY_WIDTHS)  # (|a|, widths)
        commands = np.broadcast_to(lg.actions.T[:, None, :], (*widths.shape, len(lg)))
        play = play_offsets(commands, widths).transpose(2, 0, 1)  # (T, |a|, widths)
        shared["play"].append(play[hist - 1 : -1])
    s = {k: np.concatenate(v) for k, v in shared.items()}
    p = {k: np.concatenate(v) for k, v in per.items()}
    gaussian = cfg.head == "gaussian"
    pairs = Pairs.match(s["window"], s["run"])
    actions = tuple(c.name for c in ckpt.schema.actions)
    first = 0  # each state is first seen against the first action; ResidualSet.view gives the others
    others = [s["play"][:, a] for a in range(cfg.n_action) if a != first]
    states = tuple(
        Residuals(
            r=p["r"][:, k],
            pred_std=p["pred_std"][:, k] if gaussian else None,
            predicted=p["predicted"][:, k],
            real_next=p["real_next"][:, k],
            state=p["state"][:, k],
            action=s["acts"][:, first],
            run=s["run"],
            row=s["row"],
            dt=s["dt"],
            window=s["window"],
            beyond=s["beyond"],
            play=s["play"][:, first],
            other_play=np.column_stack(others) if others else None,
            name=c.name,
            index=k,
            action_name=actions[first],
            action_index=first,
            unit=c.unit,
            scale=channel_scale(c.low, c.high, float(half[k])),
            shared_pairs=pairs,
        )
        for k, c in enumerate(ckpt.schema.states)
    )
    return ResidualSet(states, actions, s["acts"], s["play"])
