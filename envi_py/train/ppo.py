"""The PPO pieces GAIL needs: a value function, generalised advantage estimation, the clipped loss.

Kept free of anything GAIL-specific so each piece can be checked on a toy problem with a known
answer (tests/test_ppo.py). The authors' code never trained its critic; here :func:`value_loss` is
minimised every epoch, so the advantages come from a value function that tracks the returns.
"""

from __future__ import annotations

from typing import Sequence

import torch
from torch import nn

from ..model import mlp


class ValueNet(nn.Module):
    """V(window, time-to-go): an MLP with tanh hidden layers, one output.

    Rollouts have a fixed horizon, so the value of a window depends on how many rewards remain; the
    time-to-go (1 at the first step, 0 after the last) is an input, otherwise the critic would have
    to average over horizons it cannot tell apart.
    """

    def __init__(self, in_features: int, hidden: Sequence[int] = (256, 256)) -> None:
        super().__init__()
        self.net = mlp(in_features + 1, hidden, nn.Tanh, 1)

    def forward(self, obs: torch.Tensor, to_go: torch.Tensor) -> torch.Tensor:
        return self.net(torch.cat([obs, to_go.unsqueeze(-1)], dim=-1)).squeeze(-1)


def gae(
    rewards: torch.Tensor, values: torch.Tensor, last_value: torch.Tensor, gamma: float = 0.99, lam: float = 0.95
) -> tuple[torch.Tensor, torch.Tensor]:
    """Generalised advantage estimates and value targets of fixed-horizon rollouts.

    ``rewards`` and ``values`` are (B, H): step t of rollout b. The horizon is a truncation, not a
    terminal state (the robot keeps driving), so the tail is bootstrapped with ``last_value`` (B,),
    the critic's value of the window after the last step. Returns (advantages, returns), each (B, H),
    with returns = advantages + values (the TD(lambda) targets).
    """
    horizon = rewards.shape[1]
    adv = torch.zeros_like(rewards)
    running = torch.zeros_like(last_value)
    next_value = last_value
    for t in reversed(range(horizon)):
        delta = rewards[:, t] + gamma * next_value - values[:, t]
        running = delta + gamma * lam * running
        adv[:, t] = running
        next_value = values[:, t]
    return adv, adv + values


def normalise(adv: torch.Tensor, eps: float = 1e-8) -> torch.Tensor:
    """Zero mean, unit spread over the batch: the step size no longer depends on the reward scale."""
    return (adv - adv.mean()) / (adv.std() + eps)


def clipped_surrogate(
    log_prob: torch.Tensor, old_log_prob: torch.Tensor, adv: torch.Tensor, clip: float = 0.2
) -> tuple[torch.Tensor, torch.Tensor]:
    """PPO's clipped objective as a loss to minimise, and the fraction of samples that were clipped."""
    ratio = (log_prob - old_log_prob).exp()
    unclipped = ratio * adv
    clipped = ratio.clamp(1 - clip, 1 + clip) * adv
    frac = ((ratio - 1).abs() > clip).float().mean()
    return -torch.min(unclipped, clipped).mean(), frac


def value_loss(value: ValueNet, obs: torch.Tensor, to_go: torch.Tensor, returns: torch.Tensor) -> torch.Tensor:
    """Mean squared error of the critic against the GAE returns."""
    return nn.functional.mse_loss(value(obs, to_go), returns)
