"""Multi-step (rollout) loss for behaviour cloning: the model fed its own predictions.

One-step behaviour cloning trains the model on windows of real rows only; in closed loop its
windows hold its own predictions, and an error that pushes them off the training data compounds
(the paper's warning; issue 14's car drifted to its sensor limits). This loss unrolls the model
``horizon`` steps from windows of the training logs, each predicted mean entering the window as
the next state beside the logged action of that row, and scores every step's prediction against
the logged state with the one-step loss (:func:`envi_py.train.bc.head_loss`). Gradients flow
through the whole unroll, so the model learns to correct the drift its own errors start.

The logged actions are replayed rather than the controller being asked (as GAIL's rollouts do):
the loss stays differentiable and cheap, and it still feeds the model the states it will see.
A saturating sensor's limit readings (``limit_events``) are not predicted by the value head: where
the logged next state is such a reading it enters the window as logged (teacher forcing).
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np
import torch

from ..dataset import Dataset
from ..model import EnvModel

#: the per-step loss: (model, heads(x), targets (B, |s|), events (B, e) or None) -> scalar
HeadLoss = Callable[
    [EnvModel, tuple[torch.Tensor, torch.Tensor | None, torch.Tensor | None], torch.Tensor, torch.Tensor | None],
    torch.Tensor,
]


class MultiStepLoss:
    """Unrolled loss over start windows taken every ``stride`` rows of each training log.

    Per log ``i`` it holds the start windows (B, l, W), the logged rows that follow (B, H, W),
    the run context (B, 2|s|) when the model takes one, and which following states are limit
    readings (B, H, e). A log too short for ``history + horizon`` rows has no start window and
    contributes zero."""

    def __init__(
        self,
        data: Dataset,
        context: bool,
        events: list[np.ndarray | None],
        horizon: int,
        stride: int = 5,
    ) -> None:
        if horizon < 1 or stride < 1:
            raise ValueError(f"multi-step loss: horizon and stride must be positive, got {horizon} and {stride}")
        self.horizon, self.n_state = horizon, data.n_state
        hist = data.history
        self.windows: list[torch.Tensor | None] = []
        self.future: list[torch.Tensor] = []
        self.context: list[torch.Tensor | None] = []
        self.events: list[torch.Tensor | None] = []
        for z, ev, run_context in zip(data.z, events, data.contexts):
            starts = np.arange(0, len(z) - hist - horizon + 1, stride)
            if len(starts) == 0:
                self.windows.append(None), self.future.append(torch.empty(0)), self.context.append(None)
                self.events.append(None)
                continue
            self.windows.append(torch.from_numpy(np.stack([z[o : o + hist] for o in starts])))
            self.future.append(torch.from_numpy(np.stack([z[o + hist : o + hist + horizon] for o in starts])))
            ctx = run_context.astype(np.float32) if context else None
            self.context.append(None if ctx is None else torch.from_numpy(np.tile(ctx, (len(starts), 1))))
            # events of the log's pairs: pair j predicts row hist + j, so start o's step k is pair o + k
            self.events.append(
                None if ev is None else torch.from_numpy(np.stack([ev[o : o + horizon] for o in starts]))
            )

    def __call__(self, model: EnvModel, i: int, head_loss: HeadLoss) -> torch.Tensor:
        """The mean per-step loss of log ``i``'s unrolls."""
        window = self.windows[i]
        if window is None:
            return torch.zeros(())
        ns, future, ctx, ev = self.n_state, self.future[i], self.context[i], self.events[i]
        total = torch.zeros(())
        for k in range(self.horizon):
            x = window.reshape(window.shape[0], -1)
            if ctx is not None:
                x = torch.cat([x, ctx], dim=1)
            heads = model.heads(x)
            target = future[:, k, :ns]
            step_ev = None if ev is None else ev[:, k]
            total = total + head_loss(model, heads, target, step_ev)
            state = heads[0]
            if step_ev is not None:
                forced = torch.zeros_like(state, dtype=torch.bool)
                for e, (s, _) in enumerate(model.config.limit_events):
                    forced[:, s] = step_ev[:, e]
                state = torch.where(forced, target, state)
            row = torch.cat([state, future[:, k, ns:]], dim=1)
            window = torch.cat([window[:, 1:], row.unsqueeze(1)], dim=1)
        return total / self.horizon
