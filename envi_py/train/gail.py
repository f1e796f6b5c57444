"""GAIL and BCxGAIL for environment models (paper, Algorithm 2, roles of imitation inverted).

The environment model is the policy (a Gaussian head gives the log-probability PPO needs); the
controller under test and the sliding window are its environment (:mod:`.gail_env`). Each epoch:

1. roll out every start window of every training log for ``horizon`` steps, each log with its own
   controller, all in one batch;
2. train the discriminator ``disc_iters`` times with binary cross-entropy, real (window, next
   state) pairs of the logs against the rollout's pairs (:mod:`.discriminator`);
3. reward each step with the discriminator's logit, log D - log(1 - D) (why: see
   :meth:`Discriminator.reward`), estimate advantages with GAE against a trained critic;
4. ``policy_iters`` PPO steps (clipped surrogate, normalised advantages), each with a critic step.

BCxGAIL adds the behaviour-cloning loss (:func:`envi_py.train.bc.bc_loss`, the Gaussian NLL of the
real next state) to every PPO step on the same model: ``loss = ppo + bc_weight * bc``, full batch
of real pairs, ``bc_weight`` 1 by default. With normalised advantages the PPO term is O(1) and the
NLL of a fitted model is O(1) too, so equal weight lets BC anchor the model on the data while GAIL
corrects what one-step fitting gets wrong in closed loop (compounding error).

Defaults are the paper's Table 2 (model lr 5e-5, discriminator lr 0.01, 10 + 10 iterations per
epoch, 300 epochs) with PPO's usual clip 0.2, gamma 0.99, lambda 0.95; all are keyword overrides.
Model selection is by closed-loop validation error, as for BC (:class:`.common.Selector`).
"""

from __future__ import annotations

import csv
from dataclasses import asdict, dataclass, fields
from pathlib import Path
from typing import Any, Sequence

import numpy as np
import torch
from tqdm import tqdm

from ..logs import Log
from ..system import SystemDescription
from ..model import Checkpoint
from .bc import bc_loss, one_step_loss
from .common import SelectionSettings, Selector, model_config, new_checkpoint
from .discriminator import Discriminator, bce_loss
from .gail_env import Rollout, WindowEnv
from .ppo import ValueNet, clipped_surrogate, gae, normalise, value_loss
from .state import TrainingState


@dataclass
class GailConfig:
    """Hyper-parameters of GAIL / BCxGAIL; every field is a keyword of :func:`train_gail`."""

    lr: float = 5e-5  # model (policy) learning rate, paper Table 2
    disc_lr: float = 0.01  # discriminator learning rate, paper Table 2
    value_lr: float = 1e-3  # critic learning rate
    policy_iters: int = 10
    disc_iters: int = 10
    clip: float = 0.2
    gamma: float = 0.99
    lam: float = 0.95
    horizon: int = 40  # steps per rollout (1.6 s at 40 ms)
    stride: int = 10  # rows between start windows of one log
    init_log_std: float = -2.0  # initial log-std of the Gaussian head: std ~0.14 of the half-range
    entropy: float = 0.0  # entropy bonus weight
    bc_weight: float = 0.0  # 0: pure GAIL; BCxGAIL uses 1
    disc_hidden: tuple[int, ...] = (256, 256)  # paper Table 4
    value_hidden: tuple[int, ...] = (256, 256)
    minibatch: int = 256  # samples per discriminator / policy iteration (each side, for the discriminator)
    eval_every: int = 10  # epochs between closed-loop validation scores


CURVE_FIELDS = (
    "epoch",
    "disc_loss",
    "disc_acc",
    "policy_loss",
    "value_loss",
    "bc_loss",
    "clip_frac",
    "reward",
    "std",
    "val_error",
)


def _policy_log_prob(ckpt: Checkpoint, obs: torch.Tensor, action: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    mean, log_std = ckpt.model(obs)
    dist = torch.distributions.Normal(mean, log_std.exp())
    return dist.log_prob(action).sum(-1), dist.entropy().sum(-1)


class _Trainer:
    """One GAIL run: the model, critic, discriminator, their optimisers and the epoch loop."""

    def __init__(self, ckpt: Checkpoint, train_logs: Sequence[Log], hp: GailConfig, seed: int) -> None:
        self.ckpt, self.hp = ckpt, hp
        cfg = ckpt.config
        with torch.no_grad():
            ckpt.model.log_std.bias.fill_(hp.init_log_std)
        torch.manual_seed(seed + 1)
        self.disc = Discriminator(cfg.in_features + cfg.n_state, hp.disc_hidden)
        self.value = ValueNet(cfg.in_features, hp.value_hidden)
        self.opt = torch.optim.Adam(ckpt.model.parameters(), lr=hp.lr)
        self.disc_opt = torch.optim.Adam(self.disc.parameters(), lr=hp.disc_lr)
        self.value_opt = torch.optim.Adam(self.value.parameters(), lr=hp.value_lr)
        self.env = WindowEnv(ckpt, list(train_logs), hp.horizon, hp.stride)
        x, y = ckpt.dataset(train_logs, cut_at_breaks=True).stacked()
        self.real_x, self.real_y = torch.from_numpy(x), torch.from_numpy(y)
        self.gen = torch.Generator().manual_seed(seed)
        self.rng = np.random.default_rng(seed)
        self.reward_var: float | None = None

    def _minibatch(self, n: int) -> torch.Tensor:
        """Random indices of one iteration's minibatch out of ``n`` samples (all if fewer)."""
        return torch.from_numpy(self.rng.permutation(n)[: self.hp.minibatch])

    def _real_sample(self, n: int) -> tuple[torch.Tensor, torch.Tensor]:
        idx = torch.from_numpy(self.rng.integers(0, len(self.real_x), n))
        return self.real_x[idx], self.real_y[idx]

    def _train_disc(self, ro: Rollout) -> tuple[float, float]:
        fake_x, fake_y = ro.pairs
        loss, acc = torch.tensor(0.0), 0.0
        for _ in range(self.hp.disc_iters):
            idx = self._minibatch(len(fake_x))
            loss, acc = bce_loss(self.disc, self._real_sample(len(idx)), (fake_x[idx], fake_y[idx]))
            self.disc_opt.zero_grad()
            loss.backward()
            self.disc_opt.step()
        return loss.item(), acc

    def _train_policy(self, ro: Rollout) -> dict[str, float]:
        hp = self.hp
        b, h = ro.log_prob.shape
        raw = self.disc.reward(*ro.pairs).reshape(b, h)
        # The logit's scale drifts with the discriminator's confidence; dividing by a running spread
        # keeps the critic's targets on one scale across epochs (advantages are normalised anyway).
        var = raw.var().item()
        self.reward_var = var if self.reward_var is None else 0.9 * self.reward_var + 0.1 * var
        rewards = raw / (self.reward_var**0.5 + 1e-8)
        with torch.no_grad():
            values = self.value(ro.obs, ro.to_go)
            last = self.value(ro.last_obs, ro.last_to_go)
        adv, returns = gae(rewards, values, last, hp.gamma, hp.lam)
        adv = normalise(adv).reshape(-1)
        obs, act = ro.obs.reshape(b * h, -1), ro.action.reshape(b * h, -1)
        old_logp, to_go, returns = ro.log_prob.reshape(-1), ro.to_go.reshape(-1), returns.reshape(-1)
        stats = {"policy_loss": 0.0, "value_loss": 0.0, "bc_loss": float("nan"), "clip_frac": 0.0}
        for _ in range(hp.policy_iters):
            i = self._minibatch(b * h)
            logp, ent = _policy_log_prob(self.ckpt, obs[i], act[i])
            surrogate, frac = clipped_surrogate(logp, old_logp[i], adv[i], hp.clip)
            loss = surrogate - hp.entropy * ent.mean()
            if hp.bc_weight > 0:
                bc = bc_loss(self.ckpt.model, *self._real_sample(len(i)))
                loss = loss + hp.bc_weight * bc
                stats["bc_loss"] = bc.item()
            self.opt.zero_grad()
            loss.backward()
            self.opt.step()
            vloss = value_loss(self.value, obs[i], to_go[i], returns[i])
            self.value_opt.zero_grad()
            vloss.backward()
            self.value_opt.step()
            stats.update(policy_loss=surrogate.item(), value_loss=vloss.item(), clip_frac=frac.item())
        stats["reward"] = raw.mean().item()
        return stats

    def state(self) -> dict[str, Any]:
        """What the epochs to come depend on besides the model, its optimiser and ``rng``: critic,
        discriminator, their optimisers, the rollout generator, torch's global generator and the
        running reward spread (for :class:`.state.TrainingState`)."""
        return {
            "disc": self.disc.state_dict(),
            "value": self.value.state_dict(),
            "disc_opt": self.disc_opt.state_dict(),
            "value_opt": self.value_opt.state_dict(),
            "rollout_generator": self.gen.get_state(),
            "torch_rng": torch.get_rng_state(),
            "reward_var": self.reward_var,
        }

    def load_state(self, state: dict[str, Any]) -> None:
        """Continue from :meth:`state`'s result."""
        self.disc.load_state_dict(state["disc"])
        self.value.load_state_dict(state["value"])
        self.disc_opt.load_state_dict(state["disc_opt"])
        self.value_opt.load_state_dict(state["value_opt"])
        self.gen.set_state(state["rollout_generator"])
        torch.set_rng_state(state["torch_rng"])
        self.reward_var = None if state["reward_var"] is None else float(state["reward_var"])

    def epoch(self) -> dict[str, float]:
        self.ckpt.model.train()
        ro = self.env.rollout(self.gen)
        disc_loss, disc_acc = self._train_disc(ro)
        stats = self._train_policy(ro)
        with torch.no_grad():
            _, log_std = self.ckpt.model(ro.obs[:, 0])
        return {"disc_loss": disc_loss, "disc_acc": disc_acc, **stats, "std": log_std.exp().mean().item()}


def write_curves(rows: list[dict[str, float]], out: Path, title: str) -> tuple[Path, Path]:
    """``curves.csv`` and ``curves.png`` (losses, discriminator accuracy, validation error by epoch)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    out.mkdir(parents=True, exist_ok=True)
    csv_path, png_path = out / "curves.csv", out / "curves.png"
    with csv_path.open("w", newline="") as f:
        w = csv.DictWriter(f, fieldnames=CURVE_FIELDS)
        w.writeheader()
        w.writerows(rows)
    ep = [r["epoch"] for r in rows]
    fig, axes = plt.subplots(2, 2, figsize=(10, 7))
    panels = [("disc_loss", "policy_loss", "value_loss", "bc_loss"), ("disc_acc",), ("reward", "std"), ("val_error",)]
    for ax, keys in zip(axes.ravel(), panels):
        for k in keys:
            ys = np.array([r[k] for r in rows], dtype=float)
            ok = np.isfinite(ys)
            if ok.any():
                ax.plot(np.array(ep)[ok], ys[ok], marker="." if k == "val_error" else None, label=k)
        ax.set_xlabel("epoch")
        if ax.get_legend_handles_labels()[0]:  # a panel whose series are all NaN (one epoch) has none
            ax.legend(fontsize=8)
    axes[0, 0].set_yscale("symlog", linthresh=1e-2)  # critic loss and policy loss differ by orders
    axes[1, 1].set_ylabel("closed-loop mean normalised W1")
    fig.suptitle(title)
    fig.tight_layout()
    fig.savefig(png_path, dpi=100)
    plt.close(fig)
    return csv_path, png_path


def _train(
    algorithm: str,
    train_logs: Sequence[Log],
    val_logs: Sequence[Log],
    epochs: int,
    seed: int,
    history: int,
    hidden: Sequence[int],
    system: SystemDescription | None,
    progress: bool,
    curves_dir: str | Path | None,
    state_path: str | Path | None,
    resume: bool,
    hyper: dict[str, Any],
) -> Checkpoint:
    known = {f.name for f in fields(GailConfig)}
    selection = hyper.pop("selection", None) or SelectionSettings()
    model_extra = {k: v for k, v in hyper.items() if k not in known and k != "head"}
    hp = GailConfig(**{k: v for k, v in hyper.items() if k in known})
    # limit events are not trained adversarially yet: a GAIL model keeps the plain Gaussian head
    cfg = model_config(train_logs, history, hidden, "gaussian", **{"limit_events": (), **model_extra})
    record = {
        "epochs": epochs,
        "history": history,
        "hidden": list(hidden),
        "head": "gaussian",
        "reward": "log D - log(1 - D)",
        "selection": selection.to_json(),
        **{k: (list(v) if isinstance(v, tuple) else v) for k, v in asdict(hp).items()},
    }
    ckpt = new_checkpoint(algorithm, train_logs, val_logs, cfg, seed, record, system=system)
    trainer = _Trainer(ckpt, train_logs, hp, seed)
    selector = Selector(val_logs, selection, one_step_loss(ckpt, val_logs))
    rows: list[dict[str, float]] = []
    saver = TrainingState(Path(state_path), ckpt) if state_path is not None else None
    start = 1
    if saver is not None and resume:
        start = saver.restore(ckpt, trainer.opt, trainer.rng, selector) + 1
        trainer.load_state(saver.extra)
        rows = [dict(r) for r in saver.extra["curves"]]
    bar = tqdm(range(start, epochs + 1), desc=algorithm, disable=not progress, leave=False)
    for epoch in bar:
        row = {"epoch": epoch, **trainer.epoch(), "val_error": float("nan")}
        validated = epoch % hp.eval_every == 0 or epoch == epochs
        if validated:
            row["val_error"] = selector.consider(ckpt, epoch)
            bar.set_postfix(dacc=f"{row['disc_acc']:.2f}", val=f"{row['val_error']:.4f}")
        rows.append(row)
        if validated and saver is not None:
            saver.save(epoch, ckpt, trainer.opt, trainer.rng, selector, {**trainer.state(), "curves": rows})
        if validated and selector.should_stop():
            break
    if curves_dir is not None:
        write_curves(rows, Path(curves_dir), f"{algorithm}: {len(train_logs)} training logs, seed {seed}")
    return selector.finish(ckpt, rows[-1]["epoch"] if rows else epochs)


def train_gail(
    train_logs: Sequence[Log],
    val_logs: Sequence[Log] = (),
    *,
    epochs: int = 300,
    seed: int = 0,
    history: int = 10,
    hidden: Sequence[int] = (256, 256),
    system: SystemDescription | None = None,
    progress: bool = False,
    curves_dir: str | Path | None = None,
    state_path: str | Path | None = None,
    resume: bool = False,
    **hyper: Any,
) -> Checkpoint:
    """Train a Gaussian environment model by GAIL; ``hyper`` overrides :class:`GailConfig` fields
    (other keywords go to the model config, e.g. ``extras``). With ``state_path`` the whole training
    state is written there after every validation and ``resume`` continues from it, as for BC
    (:class:`.state.TrainingState`): a killed run resumed gives the uninterrupted run's checkpoint."""
    return _train(
        "gail",
        train_logs,
        val_logs,
        epochs,
        seed,
        history,
        hidden,
        system,
        progress,
        curves_dir,
        state_path,
        resume,
        hyper,
    )


def train_bcxgail(
    train_logs: Sequence[Log],
    val_logs: Sequence[Log] = (),
    *,
    epochs: int = 300,
    seed: int = 0,
    history: int = 10,
    hidden: Sequence[int] = (256, 256),
    system: SystemDescription | None = None,
    progress: bool = False,
    curves_dir: str | Path | None = None,
    state_path: str | Path | None = None,
    resume: bool = False,
    **hyper: Any,
) -> Checkpoint:
    """GAIL with the behaviour-cloning loss added to every policy step (``bc_weight``, default 1);
    ``state_path`` and ``resume`` as for :func:`train_gail`."""
    hyper.setdefault("bc_weight", 1.0)
    return _train(
        "bcxgail",
        train_logs,
        val_logs,
        epochs,
        seed,
        history,
        hidden,
        system,
        progress,
        curves_dir,
        state_path,
        resume,
        hyper,
    )
