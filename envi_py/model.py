"""The environment model delta_v: a window of l (state, action) rows -> the next state.

The paper's structure is an MLP l*(|s|+|a|) -> 256 -> tanh -> 256 -> tanh -> |s| -> tanh on values
normalised to [-1, 1]. Everything an unmodelled effect may need later is a field of
:class:`ModelConfig` rather than a new class: a longer ``history``, a ``gaussian`` head (mean and
log-std) for stochastic simulation, ``extras`` for derived input channels (``dt``, ``phase``, ``play``),
``context`` for a per-run context vector appended to the input, a ``residual`` mean head (the change
from the window's last state: a stopped car's constant distance is then a zero output), and output
post-processing (``round_to``
sensor resolution, clamping to the valid range)
applied by the simulator. The diagnosis retrains by changing the config, not the code.

Checkpoints are a ``torch.save`` of plain tensors, numbers and strings, loaded with
``weights_only=True``: opening a model file never runs code from it.
"""

from __future__ import annotations

import hashlib
import json
import math
import platform
from collections.abc import Sequence
from dataclasses import asdict, dataclass, field, replace
from pathlib import Path
from typing import Any

import numpy as np
import torch
from torch import nn

from . import __version__
from .atomic import atomic_write
from .dataset import Dataset, Normaliser, actuator_position, context_of, extra_channels, play_offsets
from .effect_layers import MAX_LAYERS, Layer
from .logs import Log, LogError, LogMeta, read_log, sidecar_path
from .system import MAX_HIDDEN_WEIGHTS, LogSchema, SystemDescription

CHECKPOINT_FORMAT = "envi-model"
CHECKPOINT_VERSION = 1
LOG_STD_MIN, LOG_STD_MAX = -7.0, 1.0
#: what a residual mean head multiplies its tanh output by (a change of up to the whole normalised range),
#: and how far (normalised) a reading may sit from its limit level and still count as at the limit; the
#: exported graph and the C++ engine use the same two numbers (``envi.residual`` metadata)
RESIDUAL_SCALE = 2.0
LIMIT_LEVEL_TOL = 1e-5
#: the Student-t step noise's degrees of freedom (a variance needs more than 2; beyond 30 it is normal to
#: within what a few hundred windows can tell, and the native engine draws one normal per degree)
MIN_DOF, MAX_DOF = 3, 30
#: a two-scale normal step noise's bounds: the share of wide steps below one half (a larger one is the
#: narrow steps' mixture turned round), their scale ratio above 1 and at most 20
MAX_MIX_SHARE, MAX_MIX_SCALE = 0.5, 20.0


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
    intervals: tuple[float, ...] | None = (
        None  # quantiles of the training logs' 'dt' channel: simulation draws from them
    )
    # (state index, reading) of each saturating sensor whose training data jump to a limit (an
    # ultrasonic sensor reading 255 when its echo is lost): the jump is predicted as an event with
    # its own probability, not as Gaussian noise (see :class:`EnvModel`)
    limit_events: tuple[tuple[int, float], ...] = ()
    # the mean head predicts the change from the window's last state rather than the state itself:
    # "the state stays put" is then a zero output, not a value the network must hit to within a
    # sensor step of its normalised range (on the car twin 1 cm is 0.008 of it; the plain head's bias
    # of that size made a stopped car creep toward the lead in closed loop)
    residual: bool = False
    # the shape of a Gaussian head's step noise, per state: 0 draws it from a normal distribution, a
    # whole nu >= 3 from a Student-t with nu degrees of freedom scaled to unit variance (the same
    # spread, heavier tails; fitted after training by :mod:`envi_py.train.step_noise`). Empty: all normal.
    noise_dof: tuple[int, ...] = ()
    # or, per state, a two-scale normal (p, k): a share p of steps drawn with k times the scale of the
    # rest, scaled to unit variance (occasional sharp steps, their size bounded; fitted as the dof are).
    # (0, 1) draws that state as noise_dof says. Empty: none.
    noise_mix: tuple[tuple[float, float], ...] = ()

    def __post_init__(self) -> None:
        self.hidden = tuple(int(h) for h in self.hidden)
        self.extras = tuple(self.extras)
        if self.round_to is not None:
            self.round_to = tuple(float(r) for r in self.round_to)
        if self.limits is not None:
            self.limits = tuple((float(lo), float(hi)) for lo, hi in self.limits)
        if self.intervals is not None:
            self.intervals = tuple(float(q) for q in self.intervals)
        self.limit_events = tuple((int(i), float(v)) for i, v in self.limit_events)
        self.noise_dof = tuple(self.noise_dof)
        valid = [type(d) is int and (d == 0 or MIN_DOF <= d <= MAX_DOF) for d in self.noise_dof]
        if self.noise_dof and (len(self.noise_dof) != self.n_state or not all(valid)):
            raise ValueError(
                f"noise_dof must give each of the {self.n_state} states 0 (normal) or a whole number of "
                f"degrees of freedom in {MIN_DOF}..{MAX_DOF}, not {self.noise_dof}"
            )
        self.noise_mix = tuple((float(p), float(k)) for p, k in self.noise_mix)
        none = [(p, k) == (0.0, 1.0) for p, k in self.noise_mix]
        mixed = [0 < p < MAX_MIX_SHARE and 1 < k <= MAX_MIX_SCALE for p, k in self.noise_mix]
        if self.noise_mix and (len(self.noise_mix) != self.n_state or not all(a or b for a, b in zip(none, mixed))):
            raise ValueError(
                f"noise_mix must give each of the {self.n_state} states (0, 1) (none) or a share "
                f"0 < p < {MAX_MIX_SHARE} of steps at k times the others' scale, 1 < k <= {MAX_MIX_SCALE:g}, "
                f"not {self.noise_mix}"
            )
        if any(d and m for d, m in zip(self.noise_dof, mixed)):
            raise ValueError(
                "a state's step noise is a Student-t (noise_dof) or a two-scale normal (noise_mix), not both"
            )
        if any(not 0 <= i < self.n_state for i, _ in self.limit_events):
            raise ValueError(f"limit events name states outside 0..{self.n_state - 1}: {self.limit_events}")
        if self.head not in ("deterministic", "gaussian"):
            raise ValueError(f"model head must be 'deterministic' or 'gaussian', not {self.head!r}")
        if self.kind not in ("mlp", "random"):
            raise ValueError(f"model kind must be 'mlp' or 'random', not {self.kind!r}")
        if self.history < 1:
            raise ValueError("history must be at least 1")
        widths = (self.in_features, *self.hidden)
        weights = sum(a * b for a, b in zip(widths[:-1], widths[1:]))
        if self.kind == "mlp" and weights > MAX_HIDDEN_WEIGHTS:  # the input layer too: l = 10000 rows once passed
            raise ValueError(
                f"a network of {self.in_features:,} inputs ({self.history} rows of history) and hidden widths "
                f"{','.join(map(str, self.hidden))} has {weights:,} weights, more than {MAX_HIDDEN_WEIGHTS:,}; "
                "ask for fewer rows of history or narrower layers"
            )
        # post-processing a damaged file could hold: reversed limits once pinned every state to one edge
        if self.round_to is not None and (
            len(self.round_to) != self.n_state or not all(math.isfinite(r) and r > 0 for r in self.round_to)
        ):
            raise ValueError(f"round_to must give each of the {self.n_state} states a resolution > 0: {self.round_to}")
        if self.limits is not None and (
            len(self.limits) != self.n_state
            or not all(math.isfinite(lo) and math.isfinite(hi) and lo <= hi for lo, hi in self.limits)
        ):
            raise ValueError(f"limits must give each of the {self.n_state} states a finite low <= high: {self.limits}")
        if "play" in self.extras and not self.play_width > 0:
            raise ValueError("the 'play' channel needs a play_width > 0 (a fraction of the action range)")
        if self.play_width and "play" not in self.extras:  # a width that would shape nothing, said not ignored
            raise ValueError("a play width (--play-width) is the 'play' channel's: add that extra (--extras play)")

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
        """True when the model's input is the window alone (no derived channels, no run context). The
        exporter and the native engine run these with any head, and a run context too (not derived channels)."""
        return not self.extras and not self.context

    @property
    def stochastic(self) -> bool:
        return self.kind == "random" or self.head == "gaussian"


def mlp(
    in_features: int, hidden: Sequence[int], activation: type[nn.Module], out_features: int | None = None
) -> nn.Sequential:
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
    """delta_v on normalised values. ``forward`` gives the mean next state (and log-std if Gaussian).

    A saturating sensor that jumps to its limit (``config.limit_events``: an ultrasonic sensor
    losing its echo reads 255 for a tick or for as long as nothing is in range) gets an ``event``
    head: one logit per such state, the probability that the next reading is the limit. Without it
    a Gaussian head must stretch its spread over the 200 cm jumps of a few readings, and every
    simulated reading then carries that noise (on the car twin, simulated distance steps of sd 14
    cm against 1.2 cm in reality); with it, the value head is trained on in-range readings only.
    """

    def __init__(self, config: ModelConfig) -> None:
        super().__init__()
        self.config = config
        self.body = mlp(config.in_features, config.hidden, nn.Tanh)
        width = config.hidden[-1] if config.hidden else config.in_features
        self.mean = nn.Linear(width, config.n_state)
        self.log_std = nn.Linear(width, config.n_state) if config.head == "gaussian" else None
        self.event = nn.Linear(width, len(config.limit_events)) if config.limit_events else None
        if config.residual and config.limit_events:
            # each limit reading, normalised (set with the normaliser: see :meth:`Checkpoint.fit_limit_levels`)
            self.register_buffer("limit_levels", torch.ones(len(config.limit_events)))

    def heads(self, x: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor | None, torch.Tensor | None]:
        """Mean, log-std (None when deterministic) and limit-event logits (None without events)."""
        h = self.body(x)
        mean = torch.tanh(self.mean(h))
        if self.config.residual:
            mean = RESIDUAL_SCALE * mean + self.residual_base(x)  # a change of up to the whole range, from anywhere
        log_std = None if self.log_std is None else self.log_std(h).clamp(LOG_STD_MIN, LOG_STD_MAX)
        return mean, log_std, None if self.event is None else self.event(h)

    def residual_base(self, x: torch.Tensor) -> torch.Tensor:
        """What a residual head adds its change to (B, |s|): each state's last reading in the window;
        for a saturating sensor its last reading *not* at the limit (a lost echo's 255 says nothing of
        where the lead is; from there the sensor comes back near where it left), the limit only when
        the whole window is at it."""
        cfg = self.config
        rows = x[:, : cfg.history * cfg.row_width].reshape(x.shape[0], cfg.history, cfg.row_width)
        base = rows[:, -1, : cfg.n_state]
        if not cfg.limit_events:
            return base
        base = base.clone()
        order = torch.arange(cfg.history)
        for k, (i, _) in enumerate(cfg.limit_events):
            col = rows[..., i]
            in_range = (col - self.limit_levels[k]).abs() > LIMIT_LEVEL_TOL
            last = torch.where(in_range, order, -1).max(dim=1).values
            picked = col.gather(1, last.clamp(min=0).unsqueeze(1)).squeeze(1)
            base[:, i] = torch.where(last >= 0, picked, col[:, -1])
        return base

    def forward(self, x: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor | None]:
        mean, log_std, _ = self.heads(x)
        return mean, log_std

    def step_noise(self, shape: torch.Size, generator: torch.Generator) -> torch.Tensor:
        """Unit-variance draws (B, |s|) of each state's step-noise shape: a normal one, a Student-t
        (``config.noise_dof``) as a normal over the root of a chi-square of nu normals, scaled by
        sqrt((nu - 2) / nu), or a two-scale normal (``config.noise_mix``), k times wider at a share p
        of steps, scaled by 1 / sqrt(1 - p + p k^2). Heavy tails, not more spread: on the real
        lane-keeping logs the largest jerk of a run (the comfort metric) has a tail a normal step
        noise never draws."""
        z = torch.randn(shape, generator=generator)
        for i, nu in enumerate(self.config.noise_dof):
            if nu:
                chi2 = (torch.randn(shape[0], nu, generator=generator) ** 2).sum(dim=1)
                z[:, i] = z[:, i] * torch.sqrt((nu - 2) / chi2)
        for i, (p, k) in enumerate(self.config.noise_mix):
            if p:
                wide = torch.rand(shape[0], generator=generator) < p
                z[:, i] = z[:, i] * torch.where(wide, k, 1.0) / math.sqrt(1 - p + p * k * k)
        return z

    def step(self, x: torch.Tensor, generator: torch.Generator | None) -> tuple[torch.Tensor, torch.Tensor | None]:
        """The next normalised state (the mean, or a sample when Gaussian and a generator is given)
        and which limit events happen (B, events): drawn with the event probability when sampling,
        else where that probability exceeds one half. None without events."""
        if self.config.kind == "random":
            return torch.rand(x.shape[0], self.config.n_state, generator=generator) * 2 - 1, None
        mean, log_std, logit = self.heads(x)
        z = (
            mean
            if log_std is None or generator is None
            else mean + log_std.exp() * self.step_noise(mean.shape, generator)
        )
        if logit is None:
            return z, None
        if generator is None:
            return z, logit > 0
        return z, torch.rand(logit.shape, generator=generator) < torch.sigmoid(logit)


@dataclass
class TrainingRecord:
    """Everything needed to reproduce a model: data and hashes, seed, hyper-parameters, versions."""

    algorithm: str
    seed: int
    hyper: dict[str, Any] = field(default_factory=dict)
    data: list[dict[str, Any]] = field(default_factory=list)  # [{"file", "sha256", "controller"}]
    validation: list[dict[str, Any]] = field(default_factory=list)
    controllers: list[dict[str, Any]] = field(default_factory=list)
    period_ms: float | None = None
    selection: dict[str, Any] = field(default_factory=dict)  # which epoch won and why
    versions: dict[str, str] = field(
        default_factory=lambda: {
            "envi": __version__,
            "torch": str(torch.__version__),
            "numpy": str(np.__version__),
            "python": platform.python_version(),
        }
    )

    def __post_init__(self) -> None:
        ok = isinstance(self.period_ms, (int, float)) and not isinstance(self.period_ms, bool)
        if self.period_ms is not None and not (ok and 0 < self.period_ms < 1e6):  # NaN fails too
            raise ValueError(f"period_ms must be a positive number of milliseconds, not {self.period_ms!r}")


def _content_hash(
    config: dict[str, Any],
    norm: dict[str, Any],
    state_dict: dict[str, torch.Tensor],
    members: Sequence[dict[str, Any]] = (),
) -> str:
    """What a checkpoint's numbers hash to: a flipped byte anywhere in the weights is caught on load.
    An ensemble's further ``members`` (config and state_dict each) are hashed after the first."""
    h = hashlib.sha256(json.dumps({"config": config, "norm": norm}, sort_keys=True, default=str).encode())
    for m, (cfg, sd) in enumerate([(None, state_dict), *((m["config"], m["state_dict"]) for m in members)]):
        if cfg is not None:
            h.update(json.dumps({"member": m, "config": cfg}, sort_keys=True, default=str).encode())
        for k in sorted(sd):
            h.update(k.encode())
            h.update(sd[k].detach().cpu().contiguous().numpy().tobytes())
    return h.hexdigest()


def _members_agree(first: Checkpoint, members: Sequence[EnvModel]) -> None:
    """Refuse ensemble members that would not read and say what ``first`` does: one configuration
    (but for the step-noise shape each fits after training); schema and normaliser are shared."""
    base = replace(first.config, noise_dof=(), noise_mix=())
    for k, m in enumerate(members):
        if replace(m.config, noise_dof=(), noise_mix=()) != base:
            raise ValueError(f"member {k} reads or says other things than member 0 (another configuration)")


def _env_model(config: dict[str, Any], state_dict: dict[str, torch.Tensor]) -> EnvModel:
    """A saved model's network: its config (lists as tuples) and weights."""
    cfg = dict(config, hidden=tuple(config["hidden"]), extras=tuple(config.get("extras", ())))
    model = EnvModel(ModelConfig(**cfg))
    model.load_state_dict(state_dict)
    return model


def _is_zip(path: Path) -> bool:
    """Whether ``path`` starts as a zip archive does, as every file torch.save writes."""
    try:
        with open(path, "rb") as f:
            return f.read(4) == b"PK\x03\x04"
    except OSError:
        return False


def load_torch_file(path: Path, missing: str, foreign: str, *, reason: bool = True) -> Any:
    """What an envi torch file (checkpoint, training state) holds, read with ``weights_only`` so no
    code in it runs. torch raises many types for a foreign or corrupt file: each becomes one
    ValueError naming the file, ``missing`` when it does not exist, else ``foreign`` with the
    exception's type (and its message when ``reason``). One owner, so every such file fails alike."""
    if Path(path).suffix.lower() == ".onnx" and Path(path).is_file() and not _is_zip(Path(path)):
        # an ONNX protobuf, not torch's zip: torch would talk about weights_only
        raise ValueError(f"{path}: an exported ONNX model, not an envi checkpoint: give the .pt it was exported from")
    try:
        return torch.load(path, map_location="cpu", weights_only=True)
    except FileNotFoundError:
        raise ValueError(f"{path}: {missing}") from None
    except Exception as exc:  # noqa: BLE001 - torch raises many types for a foreign or corrupt file
        # torch's own words can run to pages (a zip reader's internals) or advise loading with
        # weights_only=False, which would run the file's code: keep the first line, never that advice
        text = str(exc).strip()
        said = reason and text and "weights_only" not in text
        why = f"{type(exc).__name__}: {text.splitlines()[0][:200]}" if said else type(exc).__name__
        raise ValueError(f"{path}: {foreign} ({why})") from None


@dataclass
class Checkpoint:
    """A trained model with its normaliser, log schema, system description and training record.

    It owns what the model sees and says: :meth:`encode_rows` turns physical log rows into the
    model's normalised rows (derived channels included), :meth:`decode_states` turns its output into
    physical states after the declared post-processing, :meth:`next_state` steps it. Every engine
    (simulation, GAIL rollouts, the diagnosis, hardware-in-the-loop) goes through these, so what
    one engine feeds the model is what every other feeds it.

    ``layers`` are effect layers simulated around the learnt model (:mod:`envi_py.effect_layers`):
    they are not saved with it (a layers file travels beside it, and the export embeds them).

    ``members`` makes it a seed ensemble: models of one configuration trained on the same logs from
    different seeds (``model`` is the first), each simulated run drawn by one member
    (:func:`envi_py.simulate.rollout`). Why: where logs are few the trainings disagree, and a single
    model's runs carry its own step noise but not that disagreement; on the real lane-keeping logs
    three members' runs scored a KLD 0.59-0.92x their members' at n = 1-20 (README, "Fidelity on the
    real logs"). Empty for a single model. One-step consumers (training, the diagnosis, HIL) use
    :meth:`member` to pick one.
    """

    model: EnvModel
    norm: Normaliser
    schema: LogSchema
    record: TrainingRecord
    system: SystemDescription | None = None
    layers: tuple[Layer, ...] = ()
    members: tuple[EnvModel, ...] = ()

    @property
    def config(self) -> ModelConfig:
        return self.model.config

    @property
    def size(self) -> int:
        """How many models simulate runs: the ensemble's members, 1 for a single model."""
        return max(1, len(self.members))

    def member(self, k: int) -> Checkpoint:
        """Member ``k`` as a single model (normaliser, schema and layers shared, not copied), with its
        own seed and selection as its record and ``hyper["member"]`` saying which of how many it is:
        what an export of it says, so ``envi_sim`` given some members only can say so."""
        if not 0 <= k < self.size:
            raise ValueError(f"member {k}: the model has {self.size} member(s), numbered 0..{self.size - 1}")
        if not self.members:
            return self
        own = dict(self.record.selection["members"][k])
        hyper = {key: v for key, v in self.record.hyper.items() if key != "members"}
        hyper["member"] = {"index": k, "of": self.size}
        record = replace(self.record, seed=own.pop("seed"), hyper=hyper, selection=own)
        return replace(self, model=self.members[k], members=(), record=record)

    @staticmethod
    def ensemble(checkpoints: Sequence[Checkpoint]) -> Checkpoint:
        """One seed ensemble of single models trained on the same logs, in the order given. They must
        read and say the same (schema, normaliser, configuration but for the fitted step-noise shape);
        the record is the first's, with each member's seed and selection under ``selection["members"]``."""
        if not checkpoints:
            raise ValueError("an ensemble needs at least one member")
        first = checkpoints[0]
        if len(checkpoints) == 1:
            return first
        for k, ck in enumerate(checkpoints):
            if ck.members:
                raise ValueError(f"member {k} is itself an ensemble")
            if ck.schema.to_json() != first.schema.to_json() or ck.norm.to_json() != first.norm.to_json():
                raise ValueError(f"member {k} reads or says other things than member 0 (trained on other logs?)")
        _members_agree(first, [ck.model for ck in checkpoints])
        record = replace(first.record, hyper={**first.record.hyper, "members": len(checkpoints)})
        record.selection = {
            **first.record.selection,
            "members": [{"seed": ck.record.seed, **ck.record.selection} for ck in checkpoints],
        }
        warnings = [f"member {k}: {w}" for k, ck in enumerate(checkpoints) if (w := ck.record.selection.get("warning"))]
        if warnings:
            record.selection["warning"] = "; ".join(warnings)
        return replace(first, record=record, members=tuple(ck.model for ck in checkpoints))

    def with_layers(self, layers: Sequence[Layer]) -> Checkpoint:
        """The same learnt model (shared, not copied) simulated with ``layers`` around it."""
        if len(layers) > MAX_LAYERS:
            raise ValueError(f"{len(layers)} effect layers, at most {MAX_LAYERS}")
        for layer in layers:  # clipping limits that miss a state's range pin it to the range's edge, unsaid
            if layer.kind != "saturation":
                continue
            for c in self.schema.states:
                if layer.low > c.high or layer.high < c.low:
                    raise ValueError(
                        f"effect layer {layer.text()} lies outside state {c.name!r}'s range [{c.low:g}, {c.high:g}]: "
                        "every reading would be the range's edge"
                    )
        return replace(self, layers=tuple(layers))

    @property
    def period_ms(self) -> float:
        """The control period the model was trained at (its logs' median interval)."""
        return self.record.period_ms or (self.system.period_ms if self.system and self.system.period_ms else 40.0)

    # ------------------------------------------------------------------ what the model sees

    def encode_rows(
        self,
        values: np.ndarray,
        first_row: int = 0,
        rng: np.random.Generator | None = None,
        previous: np.ndarray | None = None,
    ) -> np.ndarray:
        """Physical rows (B, n, C) -> the model's normalised rows (B, n, W), derived channels appended.

        ``phase`` follows the row index. ``dt`` is drawn per run and row from the training logs'
        intervals (``config.intervals``) with ``rng``: a model told the interval must be simulated
        with intervals like the real ones, or a jittery robot is simulated as a punctual one.
        Without recorded intervals every interval is the nominal one (``dt`` = 0). ``play``
        continues the backlash filter from the actuator position of the ``previous`` model rows
        (B, m, W), or starts it at the first row's command, as :class:`~envi_py.dataset.Dataset`
        does for a log.
        """
        cfg = self.config
        z = self.norm.encode(values)
        if not cfg.extras:
            return z.astype(np.float32)
        b, n = values.shape[:2]
        period = self.period_ms
        clock = [name for name in cfg.extras if name != "play"]
        ex = np.zeros((b, n, len(cfg.extras)))
        ex[..., [cfg.extras.index(name) for name in clock]] = extra_channels(
            period * np.arange(n), clock, period, cfg.phase_rows, first_row
        )
        if "dt" in cfg.extras and cfg.intervals is not None and rng is not None:
            q = np.asarray(cfg.intervals)
            ex[..., cfg.extras.index("dt")] = np.interp(rng.random((b, n)), np.linspace(0, 1, len(q)), q)
        if "play" in cfg.extras:
            start = None if previous is None else actuator_position(previous, cfg.n_state, cfg.channels, cfg.extras)
            ex[..., cfg.extras.index("play")] = play_offsets(z[..., cfg.n_state], 2.0 * cfg.play_width, start)
        return np.concatenate([z, ex], axis=2).astype(np.float32)

    def context(self, rows: np.ndarray) -> np.ndarray | None:
        """The per-run context of the encoded initial window(s) (B, l, W), when the model takes one."""
        return context_of(rows, self.config.n_state).astype(np.float32) if self.config.context else None

    def model_input(self, window: torch.Tensor, context: torch.Tensor | None) -> torch.Tensor:
        """Encoded window rows (B, l, W) [+ context] -> the network's input (B, in_features)."""
        x = window.reshape(window.shape[0], -1)
        return x if context is None else torch.cat([x, context], dim=1)

    def dataset(self, logs: Sequence[Log], cut_at_breaks: bool = False) -> Dataset:
        """Pairs of ``logs`` laid out as this model sees them (derived channels, context); training cuts
        logs at their lost rows (:meth:`Dataset.build`)."""
        cfg = self.config
        return Dataset.build(
            logs,
            cfg.history,
            self.norm,
            cfg.extras,
            self.period_ms,
            cfg.phase_rows,
            cfg.context,
            cfg.play_width,
            cut_at_breaks,
        )

    # ------------------------------------------------------------------ what the model says

    def limits(self) -> tuple[np.ndarray, np.ndarray]:
        """Per-state (low, high) physical limits simulated states are clamped to: the observed range
        recorded at training when there is one, else the declared valid range."""
        lim = self.config.limits or [(c.low, c.high) for c in self.schema.states]
        return np.array([lo for lo, _ in lim], dtype=np.float64), np.array([hi for _, hi in lim], dtype=np.float64)

    def post_process(self, states: np.ndarray, rounded: bool = True) -> np.ndarray:
        """Physical-unit output post-processing declared by the model: clamp, then round (unless not
        ``rounded``: see :meth:`decode_states`)."""
        cfg = self.config
        if cfg.clamp:
            states = np.clip(states, *self.limits())
        if rounded and cfg.round_to is not None:
            res = np.asarray(cfg.round_to)
            states = np.round(states / res) * res
        return states

    def decode_states(self, z: np.ndarray, events: np.ndarray | None = None, rounded: bool = True) -> np.ndarray:
        """The model's normalised next states (B, |s|) -> physical states, post-processed; where a
        limit event happens (``events`` (B, e) from :meth:`EnvModel.step`) the state is its limit.

        ``rounded=False`` keeps the clamp but not the rounding to the sensor's resolution: the
        model's expected reading, which one-step residuals compare with the real one. Rounding is how
        a simulated state is read; a rounded *prediction* adds its own rounding error (step^2/12 of
        variance) to every residual, an error of no world, and it drowns small effects: in the tuned
        twin world (seeds 0-4) a 2-tick delay's median share of the residuals between similar
        situations was 1.1 % against 4.1 % unrounded, a lag's 0.8 % against 12 %."""
        ns = self.config.n_state
        s = self.post_process(
            np.asarray(z, dtype=np.float64) * self.norm.half[:ns] + self.norm.centre[:ns], rounded=rounded
        )
        if events is not None:
            for k, (i, value) in enumerate(self.config.limit_events):
                s[:, i] = np.where(events[:, k], value, s[:, i])
        return s

    def decode_states_torch(self, z: torch.Tensor, events: torch.Tensor | None = None) -> torch.Tensor:
        """:meth:`decode_states` in torch (float64), for GAIL's rollouts; tested against the numpy form."""
        cfg, ns = self.config, self.config.n_state
        s = z.double() * torch.from_numpy(self.norm.half[:ns]) + torch.from_numpy(self.norm.centre[:ns])
        if cfg.clamp:
            low, high = self.limits()
            s = torch.maximum(torch.minimum(s, torch.from_numpy(high)), torch.from_numpy(low))
        if cfg.round_to is not None:
            res = torch.tensor(cfg.round_to, dtype=torch.float64)
            s = torch.round(s / res) * res
        if events is not None:
            for k, (i, value) in enumerate(cfg.limit_events):
                s[:, i] = torch.where(events[:, k], torch.tensor(value, dtype=torch.float64), s[:, i])
        return s

    def fit_limit_levels(self) -> None:
        """Tell a residual model where its limit readings sit in normalised units (its normaliser's
        encoding of each limit event's reading)."""
        if self.config.residual and self.config.limit_events:
            levels = [(v - self.norm.centre[i]) / self.norm.half[i] for i, v in self.config.limit_events]
            with torch.no_grad():
                self.model.limit_levels.copy_(torch.tensor(levels, dtype=torch.float32))

    def limit_event_targets(self, y: np.ndarray) -> np.ndarray | None:
        """Which normalised next states (N, |s|) are at a limit event's reading (N, e): the targets
        of the event head, and the rows its value head is not trained on. None without events."""
        if not self.config.limit_events:
            return None
        ns = self.config.n_state
        phys = np.asarray(y, dtype=np.float64) * self.norm.half[:ns] + self.norm.centre[:ns]
        out = np.empty((phys.shape[0], len(self.config.limit_events)), dtype=bool)
        for k, (i, value) in enumerate(self.config.limit_events):
            out[:, k] = self.schema.states[i].reads(phys[:, i], value)
        return out

    @torch.no_grad()
    def next_state(self, x: torch.Tensor, generator: torch.Generator | None = None) -> np.ndarray:
        """One step of the model on its input (B, in_features): the physical next states (B, |s|),
        sampled when the head is Gaussian and a generator is given, else the mean (and limit
        events where likelier than not)."""
        if self.members:  # never member 0 silently: which member steps a run is the caller's draw
            raise ValueError(f"an ensemble of {self.size} members steps one member at a time (Checkpoint.member)")
        z, events = self.model.eval().step(x, generator)
        return self.decode_states(z.numpy(), None if events is None else events.numpy())

    # ------------------------------------------------------------------ files

    def recorded_logs(self, which: str = "data", missing_ok: bool = False) -> list[Log]:
        """The training (``data``) or ``validation`` logs the checkpoint names, each checked against its
        recorded hash and read with the controller version recorded for it (so logs whose version came
        from a file-name pattern read back without it). ``missing_ok`` skips files that are gone."""
        out = []
        for e in getattr(self.record, which):
            path = Path(e["file"])
            if not path.is_file():
                if missing_ok:
                    continue
                raise LogError(f"{path}: recorded in the model's {which} but missing; pass the logs explicitly")
            meta = None
            if not sidecar_path(path).exists():
                controller = e.get("controller")
                if controller is None and len(self.record.controllers) == 1:
                    controller = self.record.controllers[0]  # older checkpoints: their one controller
                meta = LogMeta(schema=self.schema, controller=controller, run_id=path.stem)
            lg = read_log(path, meta, ignore=self.system.ignore if self.system else ())
            if lg.sha256() != e["sha256"]:
                raise LogError(f"{path}: content differs from the log the model was trained on (hash mismatch)")
            out.append(lg)
        return out

    def check_finite(self, where: str) -> None:
        """Weights and normaliser must be finite, with non-empty ranges: a model with a NaN weight
        would be scored as a perfect steady state."""
        for m, model in enumerate(self.members or (self.model,)):
            for k, v in model.state_dict().items():
                if not torch.isfinite(v).all():
                    who = f"member {m}'s weight" if self.members else "weight"
                    raise ValueError(f"{where}: damaged model: {who} {k!r} holds NaN or inf")
        if not (
            np.isfinite(self.norm.low).all()
            and np.isfinite(self.norm.high).all()
            and (self.norm.high > self.norm.low).all()
        ):
            raise ValueError(f"{where}: damaged model: the normaliser has an empty or non-finite range")

    def save(self, path: str | Path) -> Path:
        path = Path(path)
        path.parent.mkdir(parents=True, exist_ok=True)
        self.check_finite(str(path))
        cfg = asdict(self.config)
        norm = self.norm.to_json()
        state = {k: v.detach().clone() for k, v in self.model.state_dict().items()}
        others = [
            {"config": asdict(m.config), "state_dict": {k: v.detach().clone() for k, v in m.state_dict().items()}}
            for m in self.members[1:]
        ]
        blob = {
            "format": CHECKPOINT_FORMAT,
            "version": CHECKPOINT_VERSION,
            "config": cfg,
            "norm": norm,
            "schema": self.schema.to_json(),
            "system": None if self.system is None else json.dumps(self.system.to_json()),
            "record": asdict(self.record),
            "state_dict": state,
            "members": others,  # the ensemble's further members (none for a single model)
            "sha256": _content_hash(cfg, norm, state, others),
        }
        return atomic_write(path, lambda fh: torch.save(blob, fh))  # a reader never sees half a model

    @staticmethod
    def load(path: str | Path) -> Checkpoint:
        path = Path(path)
        if path.exists() and not path.is_file():
            raise ValueError(f"{path}: not a regular file")
        blob = load_torch_file(path, "no such model file", "not an envi model checkpoint")
        if not isinstance(blob, dict) or blob.get("format") != CHECKPOINT_FORMAT:
            raise ValueError(f"{path}: not an envi model checkpoint (no '{CHECKPOINT_FORMAT}' header)")
        if blob.get("version") != CHECKPOINT_VERSION:
            raise ValueError(f"{path}: checkpoint version {blob.get('version')} is not supported")
        try:
            cfg = blob["config"]
            want = blob.get("sha256")
            others = blob.get("members") or []
            if want is not None and _content_hash(cfg, blob["norm"], blob["state_dict"], others) != want:
                raise ValueError("its content does not match its hash (a changed or corrupted file)")
            model = _env_model(cfg, blob["state_dict"])
            members = (model, *(_env_model(m["config"], m["state_dict"]) for m in others)) if others else ()
            rec = TrainingRecord(**blob["record"])
            system = blob.get("system")
            ckpt = Checkpoint(
                model.eval(),
                Normaliser.from_json(blob["norm"]),
                LogSchema.from_json(blob["schema"]),
                rec,
                None if system is None else SystemDescription.from_json(json.loads(system)),
                members=tuple(m.eval() for m in members),
            )
            if members:
                _members_agree(ckpt, members)
        except (KeyError, TypeError, RuntimeError, ValueError, AttributeError) as exc:
            raise ValueError(f"{path}: damaged envi checkpoint ({exc})") from None
        ckpt.check_finite(str(path))
        return ckpt
