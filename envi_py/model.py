"""The environment model delta_v: a window of l (state, action) rows -> the next state.

The paper's structure is an MLP l*(|s|+|a|) -> 256 -> tanh -> 256 -> tanh -> |s| -> tanh on values
normalised to [-1, 1]. Everything an unmodelled effect may need later is a field of
:class:`ModelConfig` rather than a new class: a longer ``history``, a ``gaussian`` head (mean and
log-std) for stochastic simulation, ``extras`` for derived input channels (``dt``, ``phase``, ``play``),
``context`` for a per-run context vector appended to the input, and output post-processing (``round_to`` sensor resolution, clamping to the valid range)
applied by the simulator. The diagnosis retrains by changing the config, not the code.

Checkpoints are a ``torch.save`` of plain tensors, numbers and strings, loaded with
``weights_only=True``: opening a model file never runs code from it.
"""

from __future__ import annotations

import platform
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any, Sequence

import numpy as np
import torch
from torch import nn

from . import __version__
from .dataset import Normaliser
from .logs import LogSchema

CHECKPOINT_FORMAT = "envi-model"
CHECKPOINT_VERSION = 1
LOG_STD_MIN, LOG_STD_MAX = -7.0, 1.0


@dataclass
class ModelConfig:
    """Shape and behaviour of an environment model."""

    n_state: int
    n_action: int
    history: int = 10
    hidden: tuple[int, ...] = (256, 256)
    head: str = "deterministic"  # or "gaussian"
    kind: str = "mlp"  # or "random": the paper's baseline, a state drawn at random each step
    extras: tuple[str, ...] = ()  # derived per-row channels, see envi_py.dataset.EXTRA_CHANNELS
    phase_rows: int = 100  # rows over which the 'phase' channel runs from -1 to 1
    play_width: float = 0.0  # the 'play' channel's full width, as a fraction of the first action's range
    context: bool = False  # append the per-run context of sigma_0 (envi_py.dataset.context_of)
    round_to: tuple[float, ...] | None = None  # per-state resolution in physical units (None: no rounding)
    clamp: bool = True  # keep simulated states inside the valid range: ``limits``, else the schema's
    limits: tuple[tuple[float, float], ...] | None = None  # per-state (low, high) observed physical limits
    intervals: tuple[float, ...] | None = None  # quantiles of the training logs' 'dt' channel: simulation draws from them

    def __post_init__(self) -> None:
        self.hidden = tuple(int(h) for h in self.hidden)
        self.extras = tuple(self.extras)
        if self.round_to is not None:
            self.round_to = tuple(float(r) for r in self.round_to)
        if self.limits is not None:
            self.limits = tuple((float(lo), float(hi)) for lo, hi in self.limits)
        if self.intervals is not None:
            self.intervals = tuple(float(q) for q in self.intervals)
        if self.head not in ("deterministic", "gaussian"):
            raise ValueError(f"model head must be 'deterministic' or 'gaussian', not {self.head!r}")
        if self.kind not in ("mlp", "random"):
            raise ValueError(f"model kind must be 'mlp' or 'random', not {self.kind!r}")
        if self.history < 1:
            raise ValueError("history must be at least 1")
        if "play" in self.extras and not self.play_width > 0:
            raise ValueError("the 'play' channel needs a play_width > 0 (a fraction of the action range)")

    @property
    def channels(self) -> int:
        """Logged channels of a window row (states and actions)."""
        return self.n_state + self.n_action

    @property
    def row_width(self) -> int:
        """Width of a window row as the model sees it: logged channels plus derived ones."""
        return self.channels + len(self.extras)

    @property
    def context_dim(self) -> int:
        return 2 * self.n_state if self.context else 0

    @property
    def in_features(self) -> int:
        return self.history * self.row_width + self.context_dim

    @property
    def plain(self) -> bool:
        """True for the paper's structure (no derived channels, no context): what the exporters support."""
        return not self.extras and not self.context

    @property
    def stochastic(self) -> bool:
        return self.kind == "random" or self.head == "gaussian"


def mlp(in_features: int, hidden: Sequence[int], activation: type[nn.Module], out_features: int | None = None) -> nn.Sequential:
    """Linear + activation per hidden width, then an optional linear output layer: the one network
    shape the environment model, the GAIL discriminator and the PPO critic share."""
    layers: list[nn.Module] = []
    width = in_features
    for h in hidden:
        layers += [nn.Linear(width, h), activation()]
        width = h
    if out_features is not None:
        layers.append(nn.Linear(width, out_features))
    return nn.Sequential(*layers)


class EnvModel(nn.Module):
    """delta_v on normalised values. ``forward`` gives the mean next state (and log-std if Gaussian)."""

    def __init__(self, config: ModelConfig) -> None:
        super().__init__()
        self.config = config
        self.body = mlp(config.in_features, config.hidden, nn.Tanh)
        width = config.hidden[-1] if config.hidden else config.in_features
        self.mean = nn.Linear(width, config.n_state)
        self.log_std = nn.Linear(width, config.n_state) if config.head == "gaussian" else None

    def forward(self, x: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor | None]:
        h = self.body(x)
        mean = torch.tanh(self.mean(h))
        if self.log_std is None:
            return mean, None
        return mean, self.log_std(h).clamp(LOG_STD_MIN, LOG_STD_MAX)

    def step(self, x: torch.Tensor, generator: torch.Generator | None) -> torch.Tensor:
        """The next normalised state: the mean, or a sample when Gaussian and a generator is given."""
        if self.config.kind == "random":
            return torch.rand(x.shape[0], self.config.n_state, generator=generator) * 2 - 1
        mean, log_std = self(x)
        if log_std is None or generator is None:
            return mean
        return mean + log_std.exp() * torch.randn(mean.shape, generator=generator)


@dataclass
class TrainingRecord:
    """Everything needed to reproduce a model: data and hashes, seed, hyper-parameters, versions."""

    algorithm: str
    seed: int
    hyper: dict[str, Any] = field(default_factory=dict)
    data: list[dict[str, str]] = field(default_factory=list)  # [{"file", "sha256"}]
    validation: list[dict[str, str]] = field(default_factory=list)
    controllers: list[dict[str, Any]] = field(default_factory=list)
    period_ms: float | None = None
    selection: dict[str, Any] = field(default_factory=dict)  # which epoch won and why
    versions: dict[str, str] = field(default_factory=lambda: {
        "envi": __version__, "torch": str(torch.__version__), "numpy": str(np.__version__),
        "python": platform.python_version()})


@dataclass
class Checkpoint:
    """A trained model with its normaliser, log schema and training record."""

    model: EnvModel
    norm: Normaliser
    schema: LogSchema
    record: TrainingRecord

    @property
    def config(self) -> ModelConfig:
        return self.model.config

    def save(self, path: str | Path) -> Path:
        path = Path(path)
        path.parent.mkdir(parents=True, exist_ok=True)
        cfg = asdict(self.config)
        blob = {
            "format": CHECKPOINT_FORMAT,
            "version": CHECKPOINT_VERSION,
            "config": cfg,
            "norm": self.norm.to_json(),
            "schema": self.schema.to_json(),
            "record": asdict(self.record),
            "state_dict": {k: v.detach().clone() for k, v in self.model.state_dict().items()},
        }
        tmp = path.with_name("." + path.name + ".tmp")
        torch.save(blob, tmp)
        tmp.replace(path)
        return path

    @staticmethod
    def load(path: str | Path) -> "Checkpoint":
        path = Path(path)
        try:
            blob = torch.load(path, map_location="cpu", weights_only=True)
        except FileNotFoundError:
            raise ValueError(f"{path}: no such model file") from None
        except Exception as exc:  # torch raises many types for a foreign or corrupt file
            raise ValueError(f"{path}: not an envi model checkpoint ({type(exc).__name__}: {exc})") from None
        if not isinstance(blob, dict) or blob.get("format") != CHECKPOINT_FORMAT:
            raise ValueError(f"{path}: not an envi model checkpoint (no '{CHECKPOINT_FORMAT}' header)")
        if blob.get("version") != CHECKPOINT_VERSION:
            raise ValueError(f"{path}: checkpoint version {blob.get('version')} is not supported")
        try:
            cfg = blob["config"]
            cfg["hidden"] = tuple(cfg["hidden"])
            cfg["extras"] = tuple(cfg.get("extras", ()))
            model = EnvModel(ModelConfig(**cfg))
            model.load_state_dict(blob["state_dict"])
            rec = TrainingRecord(**blob["record"])
            return Checkpoint(model.eval(), Normaliser.from_json(blob["norm"]),
                              LogSchema.from_json(blob["schema"]), rec)
        except (KeyError, TypeError, RuntimeError, ValueError) as exc:
            raise ValueError(f"{path}: damaged envi checkpoint ({exc})") from None
