"""The native engine (``cpp/``) behind the same call as :func:`envi_py.simulate.rollout`.

On x86-64 the build carries the engine three times, compiled for the baseline instruction set,
AVX2+FMA and AVX-512; the best one this CPU runs is imported (``ENVI_NATIVE_ISA=portable|avx2|
avx512`` forces one). Each is a separate shared object, so Eigen compiled for different
instruction sets never meets in one link.
"""

from __future__ import annotations

import copy
import importlib
import json
import os
from collections.abc import Iterator
from contextlib import contextmanager
from functools import cache
from pathlib import Path
from types import ModuleType
from typing import Any

import numpy as np

from .controllers import ControllerError, ControllerSpec
from .metrics import MetricConfig
from .model import Checkpoint

#: variant -> CPU features it needs (numpy's names), best first
_VARIANTS: dict[str, tuple[str, ...]] = {
    "avx512": ("AVX512F", "AVX512VL", "AVX512DQ", "AVX512BW", "AVX2", "FMA3", "F16C"),
    "avx2": ("AVX2", "FMA3", "F16C"),
    "portable": (),
}


def _cpu_features() -> dict[str, bool]:
    try:
        from numpy._core._multiarray_umath import __cpu_features__  # numpy >= 2
    except ImportError:  # pragma: no cover - numpy 1.x
        from numpy.core._multiarray_umath import __cpu_features__
    return dict(__cpu_features__)


@cache
def _module() -> ModuleType | None:
    forced = os.environ.get("ENVI_NATIVE_ISA")
    feats = _cpu_features()
    for name, needs in _VARIANTS.items():
        if forced and name != forced:
            continue
        if not all(feats.get(f, False) for f in needs):
            continue
        try:
            return importlib.import_module("envi_py._native" + ("" if name == "portable" else f"_{name}"))
        except ImportError:
            continue
    return None


def available() -> bool:
    """True when the compiled engine can be imported (it is built by ``pip install``)."""
    return _module() is not None


def variant() -> str:
    """Which build is in use and the vector instructions it was compiled with."""
    mod = _module()
    if mod is None:
        return "unavailable"
    return f"{mod.__name__.rsplit('.', 1)[-1]} ({mod.simd()})"


def _native() -> ModuleType:
    mod = _module()
    if mod is None:
        raise RuntimeError("the native engine is not built; run 'pip install -e .' (or ./dev.sh setup)")
    return mod


def unsupported(ckpt: Checkpoint, controller: ControllerSpec, mean: bool = False) -> str | None:
    """Why the native engine cannot run this model with this controller (by its ``mean`` when asked),
    or None when it can.

    It runs exported MLPs fed by the window (a residual mean head included: the engine adds its base
    from the window) and a run context (the engine computes it from sigma_0), with every registered
    controller (bang-bang, lane-keeping, pid and combine; its C++ twins are tested against them,
    warm-up included); derived channels, the random baseline and a user's controller given by import
    path stay with the PyTorch engine. Widths are not judged here: a controller that does not fit
    the model is an error (WidthError) in both engines, not a reason to switch."""
    from .controllers import REGISTRY

    if not available():
        return "the native module is not built"
    if ckpt.config.kind != "mlp":
        return f"the model is {ckpt.config.kind!r}, not an MLP"
    if ckpt.config.extras:
        return "the model has derived channels"
    if ckpt.config.context and not ckpt.config.hidden:
        return "the model has a run context but no hidden layer"
    if controller.name not in REGISTRY:
        return f"controller {controller.name!r} is not a registered one"
    if mean and ckpt.config.stochastic and ckpt.config.limit_events:
        return "mean mode of a model with limit events (the engine samples whenever the head is Gaussian)"
    return None


def mean_model(ckpt: Checkpoint) -> Checkpoint:
    """The model without its spread: a copy whose head is the mean alone, which the engine runs
    deterministically (limit events would need the Gaussian head, so such models stay with PyTorch,
    see :func:`unsupported`). The original is not touched."""
    if not ckpt.config.stochastic:
        return ckpt
    copy_ = copy.deepcopy(ckpt)
    copy_.config.head = "deterministic"
    copy_.model.log_std = None
    return copy_


def onnx_bytes(model: str | os.PathLike | Checkpoint | bytes) -> bytes:
    """An exported model's bytes: an ``.onnx`` file as is, a checkpoint exported on the fly."""
    if isinstance(model, bytes):
        return model
    if not isinstance(model, Checkpoint):
        path = Path(model)
        if path.suffix == ".onnx":
            try:
                return path.read_bytes()
            except OSError as exc:
                raise ValueError(f"{path}: cannot read ({exc.strerror})") from None
        model = Checkpoint.load(path)
    from .export import to_onnx

    return to_onnx(model).SerializeToString()


def period_ms(ckpt: Checkpoint) -> float:
    """The control period a PID integrates over unless its spec sets ``dt``: the checkpoint's
    resolved period where it has one (it may come from the system description), else the
    training record's; 0 leaves the engine to the file's ``envi.period_ms`` (and then 40 ms)."""
    return float(getattr(ckpt, "period_ms", None) or ckpt.record.period_ms or 0.0)


def load(model: str | os.PathLike | Checkpoint | bytes) -> Any:
    """The compiled model (``envi_py._native.Model``); ValueError on anything it cannot run.

    Compiled from a checkpoint, it carries that checkpoint's period for PIDs without ``dt``, so
    both engines integrate over the same period."""
    try:
        compiled = _native().Model(onnx_bytes(model))
    except ValueError as exc:  # the engine does not know the file's name: say it, as envi_sim does
        if isinstance(model, (str, os.PathLike)) and Path(model).suffix == ".onnx":
            raise ValueError(f"{Path(model)}: {exc}") from None
        raise
    if isinstance(model, Checkpoint) and period_ms(model) > 0:
        compiled.period_ms = period_ms(model)
    return compiled


def _compiled(model: Any) -> Any:
    """A model compiled once by :func:`load` is reused as is; anything else is loaded now."""
    return model if isinstance(model, _native().Model) else load(model)


def _spec_json(controller: ControllerSpec) -> str:
    return json.dumps(controller.to_json())


def rollout(
    model: str | os.PathLike | Checkpoint | bytes | Any,
    controller: ControllerSpec,
    init: np.ndarray,
    steps: int,
    runs: int = 1,
    seed: int = 0,
    threads: int = 0,
) -> np.ndarray:
    """Same contract as :func:`envi_py.simulate.rollout`: ``init`` (K, l, C) physical ->
    (K*runs, l+steps, C), run ``k*runs + r`` from window k. The controller is reset and warmed up
    on each window's rows before the first step. Stochastic draws are keyed by (seed, run, step),
    so the result does not depend on ``threads`` (0 = one per core)."""
    init = np.ascontiguousarray(init, dtype=np.float64)
    with _commands_named(controller):
        return _native().rollout(
            _compiled(model), _spec_json(controller), init, int(steps), int(runs), int(seed), int(threads)
        )


def rollout_metrics(
    model: str | os.PathLike | Checkpoint | bytes | Any,
    controller: ControllerSpec,
    init: np.ndarray,
    steps: int,
    runs: int = 1,
    seed: int = 0,
    threads: int = 0,
    metric: MetricConfig | None = None,
) -> np.ndarray:
    """The eight driving metrics of every run, (K*runs, 8), scored while simulating: no traces kept.
    They are the lane-keeping preset's: a model of another system is refused here (its goals are scored
    from traces)."""
    metric = metric or MetricConfig()
    if metric.channel != 0:
        raise ValueError("the native engine scores the first state channel")
    compiled = _compiled(model)
    system = json.loads(dict(compiled.metadata).get("envi.system", "null"))
    if system is not None and system.get("preset") != "lane-keeping":
        raise ValueError(
            f"the native metrics are the lane-keeping preset's eight, and this model's system "
            f"{system.get('name', '?')!r} declares other goals: simulate traces and score them with its goals"
        )
    init = np.ascontiguousarray(init, dtype=np.float64)
    with _commands_named(controller):
        return _native().rollout_metrics(
            compiled,
            _spec_json(controller),
            init,
            int(steps),
            int(runs),
            int(seed),
            int(threads),
            centre=metric.centre,
            band=metric.band,
            skip=metric.skip,
        )


@contextmanager
def _commands_named(controller: ControllerSpec) -> Iterator[None]:
    """The engine's refusal of a command outside its declared range as the PyTorch engine words it
    (:func:`envi_py.controllers.in_range`): a ControllerError naming the controller with its parameters,
    where the engine knows only its name."""
    try:
        yield
    except ValueError as exc:
        engine_words = f"controller {controller.name!r} commanded "
        if not str(exc).startswith(engine_words):
            raise
        raise ControllerError(f"controller {controller.label()!r} commanded {str(exc)[len(engine_words) :]}") from None


def peak_flops(threads: int = 0, seconds: float = 0.5) -> float:
    """FLOP/s of register-only multiply-adds on the engine's vectors: the hard ceiling for benchmarks.

    A library GEMM's rate is the ceiling the speed targets name, but it sits below this one when the
    library does not use the widest vectors the machine has; benchmarks report both."""
    return float(_native().peak_flops(int(threads), float(seconds)))
