"""GAIL's discriminator: is this (window, next state) pair from a real log or from the model?

Paper, Table 4: window plus next state (21 inputs for l=10 and one state, one action) -> 256 ReLU
-> 256 ReLU -> 1 sigmoid. It outputs the logit; the sigmoid is folded into the loss
(``binary_cross_entropy_with_logits``), which is the same BCE but cannot overflow.
"""

from __future__ import annotations

from typing import Sequence

import torch
from torch import nn

from ..model import mlp


class Discriminator(nn.Module):
    """D(window, next state) as a logit; ``sigmoid(logit)`` is the probability that the pair is real."""

    def __init__(self, in_features: int, hidden: Sequence[int] = (256, 256)) -> None:
        super().__init__()
        self.net = mlp(in_features, hidden, nn.ReLU, 1)

    def forward(self, window: torch.Tensor, next_state: torch.Tensor) -> torch.Tensor:
        return self.net(torch.cat([window, next_state], dim=-1)).squeeze(-1)

    @torch.no_grad()
    def reward(self, window: torch.Tensor, next_state: torch.Tensor) -> torch.Tensor:
        """The model's reward: log D - log(1 - D), which is exactly the logit.

        Why this form: with -log(1 - D) the reward is ~0 for every generated pair as soon as the
        discriminator wins (D -> 0), which it does early against an untrained model, so PPO gets no
        signal; log D alone is always negative and rewards ending episodes early. The logit is
        unbounded both ways and does not saturate, and maximising its expectation minimises
        KL(model || real) over (window, next state) pairs. Rollouts have a fixed horizon, so its
        sign carries no survival bias.
        """
        return self(window, next_state)


def bce_loss(
    disc: Discriminator, real: tuple[torch.Tensor, torch.Tensor], fake: tuple[torch.Tensor, torch.Tensor]
) -> tuple[torch.Tensor, float]:
    """Binary cross-entropy with real pairs labelled 1 and model pairs 0 (equal weight to each side),
    and the discriminator's accuracy on this batch."""
    lr, lf = disc(*real), disc(*fake)
    loss = (
        nn.functional.binary_cross_entropy_with_logits(lr, torch.ones_like(lr))
        + nn.functional.binary_cross_entropy_with_logits(lf, torch.zeros_like(lf))
    ) / 2
    acc = ((lr > 0).float().mean() + (lf < 0).float().mean()).item() / 2
    return loss, acc
