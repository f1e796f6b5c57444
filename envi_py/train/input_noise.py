"""Noisy input windows for behaviour cloning (in the spirit of DART): robustness to the model's own errors.

In closed loop the window holds the model's own predictions, each off by about its one-step error;
a model trained on clean logged windows only has never seen such windows, and on the car twin it
read the jitter of its own distance predictions as a closing gap and drifted. Training on windows
whose states carry Gaussian noise, with the logged next state as the target, teaches the model to
predict the real next state from a perturbed history.

The noise of each state is ``scale`` times a robust spread of that state's logged one-step changes
(1.4826 x the median absolute change, in normalised units): scale-free across signals, and the
jumps of a saturating sensor to its limit do not inflate it. Actions, derived channels and the run
context are left as logged (the controller's commands are what they were).
"""

from __future__ import annotations

import numpy as np
import torch

from ..dataset import Dataset

MAD_TO_SD = 1.4826  # the median absolute deviation of a Gaussian times this is its standard deviation


def step_spread(data: Dataset) -> np.ndarray:
    """Per-state robust spread of the logged one-step changes (|s|,), normalised units."""
    steps = np.concatenate([np.diff(z[:, : data.n_state], axis=0) for z in data.z])
    return MAD_TO_SD * np.median(np.abs(steps), axis=0)


class InputNoise:
    """Adds Gaussian noise to the state entries of flattened windows (N, l*W [+ context])."""

    def __init__(self, data: Dataset, row_width: int, scale: float) -> None:
        if not (np.isfinite(scale) and scale >= 0):
            raise ValueError(f"input noise: scale must be a non-negative number, not {scale!r}")
        sd = np.zeros(data.history * row_width, dtype=np.float32)
        spread = step_spread(data) * scale
        for k in range(data.history):
            sd[k * row_width : k * row_width + data.n_state] = spread
        self.sd = torch.from_numpy(sd)

    def __call__(self, x: torch.Tensor, rng: np.random.Generator) -> torch.Tensor:
        """``x`` perturbed with noise seeded from ``rng`` (the training loop's generator, which a
        resumed training restores: the noise repeats exactly after a resume)."""
        generator = torch.Generator().manual_seed(int(rng.integers(2**63 - 1)))
        noise = torch.randn((x.shape[0], self.sd.shape[0]), generator=generator) * self.sd
        if x.shape[1] > self.sd.shape[0]:  # the run context rides along unperturbed
            noise = torch.cat([noise, torch.zeros(x.shape[0], x.shape[1] - self.sd.shape[0])], dim=1)
        return x + noise
