"""Environment models for hardware in the loop: anything that maps a window to the next colour.

The host keeps the last ``history`` rows of (colour, angle) in physical units, exactly as the
closed-loop simulator does, and asks the model for the colour of the next tick. Any callable
``window (history, |s|+|a|) -> colour`` works (:class:`CallableModel`); :class:`CheckpointModel`
runs an envi checkpoint the way ``envi_py.simulate.rollout`` does.
"""

from __future__ import annotations

import importlib
import inspect
from pathlib import Path
from typing import Callable, Protocol

import numpy as np


class EnvironmentModel(Protocol):
    """What HIL needs: how many rows of history, and the next colour from them."""

    history: int
    description: str

    def __call__(self, window: np.ndarray) -> float: ...


def reset(model: EnvironmentModel) -> None:
    """Start a model's run over, for models that keep per-run state (``reset()`` is optional)."""
    fn = getattr(model, "reset", None)
    if fn is not None:
        fn()


class CallableModel:
    """A plain function ``window -> colour`` with the history length it wants."""

    def __init__(self, fn: Callable[[np.ndarray], float], history: int = 1, description: str = "") -> None:
        self.fn = fn
        self.history = int(history)
        self.description = description or getattr(fn, "__qualname__", repr(fn))

    def __call__(self, window: np.ndarray) -> float:
        return float(self.fn(window))


class CheckpointModel:
    """An envi checkpoint (``envi_py.model.Checkpoint``) stepped one window at a time.

    Windows go through the checkpoint's own encode/decode (``encode_rows``, ``next_state``), the
    ones every simulation engine uses, so a HIL run and a simulation of the same model see the same
    environment. A context vector, when the model has one, comes from the first window (sigma_0).
    A seed ensemble's members take the runs in turn (run r is member r mod K), as a simulation
    shares its runs out among them.
    """

    def __init__(self, ckpt, description: str = "") -> None:
        import torch

        self.ensemble = ckpt
        self.ckpt = ckpt.member(0)
        self.history = ckpt.config.history
        self.description = description or f"envi checkpoint ({ckpt.record.algorithm})"
        self._torch = torch
        self._context = None
        self._step = 0
        self._runs = 0

    def reset(self) -> None:
        """A new run: the next window is sigma_0 again (row index 0, fresh context), stepped by the
        ensemble's next member."""
        self._context = None
        self._step = 0
        self._runs += 1
        self.ckpt = self.ensemble.member(self._runs % self.ensemble.size)

    def __call__(self, window: np.ndarray) -> float:
        torch = self._torch
        rows = self.ckpt.encode_rows(np.asarray(window, dtype=np.float64)[None], self._step)  # row index: 'phase'
        self._step += 1
        if self._context is None and self.ckpt.config.context:
            self._context = torch.from_numpy(self.ckpt.context(rows))
        x = self.ckpt.model_input(torch.from_numpy(rows), self._context)
        return float(self.ckpt.next_state(x)[0, 0])


class WorldModel:
    """A world of the simulated brick (the stand-in, or the twin) used as the environment model.

    HIL then needs no trained model: the world turns by the brick's last angle for one period and
    is read. Useful to check the HIL path itself, and to compare a model against its ground truth.
    """

    history = 1

    def __init__(self, world=None, period_s: float = 0.04, seed: int = 0) -> None:
        from .world import EdgeWorld

        self.world = world if world is not None else EdgeWorld(seed=seed)
        self.period_s = period_s
        self.seed = seed
        self.description = f"world {type(self.world).__name__} (seed {seed})"

    def reset(self) -> None:
        self.world.reset(self.seed)

    def __call__(self, window: np.ndarray) -> float:
        self.world.apply(float(window[-1, 1]), self.period_s)
        return self.world.read_color()


def load_model(spec: str) -> EnvironmentModel:
    """``path/to/model.pt`` (envi checkpoint), or ``package.module:name`` naming a model class
    (instantiated without arguments), a model object, or a plain function ``window -> colour``."""
    if ":" in spec and not Path(spec).exists():
        module, _, attr = spec.partition(":")
        try:
            obj = getattr(importlib.import_module(module), attr)
        except (ImportError, AttributeError) as exc:  # a typo in --inject: one line, not a traceback
            raise ValueError(f"--inject {spec}: cannot import {attr!r} from {module!r} ({exc})") from None
        if inspect.isclass(obj):
            obj = obj()
        return obj if hasattr(obj, "history") else CallableModel(obj, description=spec)
    from envi_py.model import Checkpoint

    return CheckpointModel(Checkpoint.load(spec), description=str(spec))
