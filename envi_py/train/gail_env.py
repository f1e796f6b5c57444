"""The environment of GAIL's policy: the controller under test and the sliding window.

With the roles of imitation learning inverted (paper, Section 4.3), the environment model is the
policy: its observation is the window of the last l (state, action) rows, its action the next
state. The "environment" then asks each log's own controller for its answer to that state and
slides the window. All start windows of all training logs are simulated at once as one batch, so a
rollout is a loop over time steps only, with the controller (numpy, batched) in the loop.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch

from ..dataset import actuator_position, extra_channels, play_offsets
from ..logs import Log, group_by_controller
from ..model import Checkpoint


@dataclass
class Rollout:
    """H steps of B simulations: what PPO and the discriminator need, all normalised, float32."""

    obs: torch.Tensor  # (B, H, in_features): the model's input at each step
    action: torch.Tensor  # (B, H, |s|): the sampled next state, before clamping (what log_prob scores)
    log_prob: torch.Tensor  # (B, H)
    next_state: torch.Tensor  # (B, H, |s|): the state that entered the window (clamped, rounded)
    to_go: torch.Tensor  # (B, H): remaining fraction of the horizon, 1 at the first step
    last_obs: torch.Tensor  # (B, in_features): the window after the last step, for bootstrapping
    last_to_go: torch.Tensor  # (B,)

    @property
    def pairs(self) -> tuple[torch.Tensor, torch.Tensor]:
        """(window, next state) pairs flattened over batch and time, as the discriminator sees them."""
        return self.obs.reshape(-1, self.obs.shape[-1]), self.next_state.reshape(-1, self.next_state.shape[-1])


class WindowEnv:
    """Fixed-horizon closed-loop rollouts from windows of the training logs.

    Start windows are taken every ``stride`` rows of each log (sigma_0 included) as long as
    ``horizon`` real rows follow, so the model is trained on the states the robot actually visits,
    not only on the first second of each run. Simulated rows get the derived channels they would
    have in simulation (nominal ``dt``, ``phase`` by row index, ``play`` from the simulated
    actions), as :mod:`envi_py.simulate` does.
    """

    def __init__(self, ckpt: Checkpoint, logs: list[Log], horizon: int = 40, stride: int = 10) -> None:
        cfg = ckpt.config
        self.ckpt, self.horizon = ckpt, horizon
        hist = cfg.history
        data = ckpt.dataset(logs, cut_at_breaks=True)
        period = ckpt.period_ms
        windows, starts, contexts, extras, log_idx = [], [], [], [], []
        for z, (i, first), run_context in zip(data.z, data.origin, data.contexts):
            for o in range(0, len(z) - hist - horizon + 1, stride):
                windows.append(z[o : o + hist])
                starts.append(logs[i].values[first + o : first + o + hist])
                contexts.append(run_context)
                # 'play' depends on the simulated actions: a placeholder here, filled in by the rollout
                extras.append(
                    extra_channels(
                        period * np.arange(horizon),
                        cfg.extras,
                        period,
                        cfg.phase_rows,
                        first + o + hist,
                        np.zeros(horizon),
                        cfg.play_width,
                    )
                )
                log_idx.append(i)
        used = set(log_idx)
        for i, lg in enumerate(logs):
            if i not in used:  # pieces between lost rows count, not the whole log
                raise ValueError(
                    f"{lg.path or lg.name}: no stretch of history {hist} + horizon {horizon} rows"
                    + (" between its lost rows" if lg.meta.breaks else f" (it has {len(lg)})")
                )
        self.window0 = torch.from_numpy(np.stack(windows).astype(np.float32))
        self.start_rows = np.stack(starts)  # physical (B, l, C): what each controller is warmed up on
        self.context = torch.from_numpy(np.stack(contexts).astype(np.float32)) if cfg.context else None
        self.extras = torch.from_numpy(np.stack(extras).astype(np.float32))
        log_idx_np = np.array(log_idx)
        pos = {id(lg): i for i, lg in enumerate(logs)}
        self.groups = [
            (spec, np.flatnonzero(np.isin(log_idx_np, [pos[id(lg)] for lg in g])))
            for spec, g in group_by_controller(logs).items()
        ]
        self.centre = torch.from_numpy(ckpt.norm.centre)
        self.half = torch.from_numpy(ckpt.norm.half)

    @property
    def batch(self) -> int:
        return self.window0.shape[0]

    def _obs(self, window: torch.Tensor) -> torch.Tensor:
        x = window.reshape(window.shape[0], -1)
        return x if self.context is None else torch.cat([x, self.context], dim=1)

    @torch.no_grad()
    def rollout(self, generator: torch.Generator) -> Rollout:
        """Sample H steps of every start window from the (Gaussian) model, controller in the loop."""
        cfg = self.ckpt.config
        ns, b, h = cfg.n_state, self.batch, self.horizon
        model = self.ckpt.model
        controllers = []
        for spec, idx in self.groups:
            ctrl = spec.build(ns, cfg.n_action, self.ckpt.period_ms)
            ctrl.reset(len(idx))
            ctrl.warmup(self.start_rows[idx, :, :ns], self.start_rows[idx, :, ns:])
            controllers.append((ctrl, idx))
        window = self.window0.clone()
        obs, acts, logps, nexts = [], [], [], []
        for t in range(h):
            x = self._obs(window)
            mean, log_std = model(x)
            if log_std is None:
                raise ValueError("GAIL needs a stochastic policy: build the model with head='gaussian'")
            std = log_std.exp()
            a = mean + std * torch.randn(mean.shape, generator=generator)
            logp = torch.distributions.Normal(mean, std).log_prob(a).sum(-1)
            s = self.ckpt.decode_states_torch(a)
            act = np.empty((b, cfg.n_action))
            s_np = s.numpy()
            for ctrl, idx in controllers:
                act[idx] = ctrl(s_np[idx])
            phys = torch.cat([s, torch.from_numpy(act)], dim=1)
            z_row = ((phys - self.centre) / self.half).float()
            ex = self.extras[:, t]
            if "play" in cfg.extras:
                ex = ex.clone()
                start = actuator_position(window.numpy(), ns, cfg.channels, cfg.extras)
                play = play_offsets(z_row[:, ns : ns + 1].numpy(), 2.0 * cfg.play_width, start)
                ex[:, cfg.extras.index("play")] = torch.from_numpy(play[:, 0].astype(np.float32))
            row = torch.cat([z_row, ex], dim=1)
            obs.append(x), acts.append(a), logps.append(logp), nexts.append(z_row[:, :ns])
            window = torch.cat([window[:, 1:], row.unsqueeze(1)], dim=1)
        to_go = 1.0 - torch.arange(h, dtype=torch.float32) / h
        return Rollout(
            torch.stack(obs, 1),
            torch.stack(acts, 1),
            torch.stack(logps, 1),
            torch.stack(nexts, 1),
            to_go.expand(b, h).contiguous(),
            self._obs(window),
            torch.zeros(b),
        )
