"""Closed-loop simulation: the controller under test against an environment model.

From an initial window sigma_0 (the first l rows of a real log) the model predicts the next state,
the controller answers with its action, and the window slides; N runs per initial window are
batched into one tensor so a whole verification is one loop over time steps. This PyTorch engine
is the reference; the native runtime implements the same loop and is tested against it.
"""

from __future__ import annotations

from typing import Sequence

import numpy as np
import torch

from .controllers import ControllerSpec
from .dataset import actuator_position, context_of, extra_channels, play_offsets
from .logs import Log, LogMeta
from .model import Checkpoint


def post_process(states: np.ndarray, ckpt: Checkpoint) -> np.ndarray:
    """Physical-unit output post-processing declared by the model: clamp, then round."""
    cfg = ckpt.config
    if cfg.clamp:
        limits = cfg.limits or [(c.low, c.high) for c in ckpt.schema.states]
        states = np.clip(states, [lo for lo, _ in limits], [hi for _, hi in limits])
    if cfg.round_to is not None:
        res = np.asarray(cfg.round_to)
        states = np.round(states / res) * res
    return states


def _model_rows(ckpt: Checkpoint, values: np.ndarray, first_row: int,
                rng: np.random.Generator | None = None, previous: np.ndarray | None = None) -> np.ndarray:
    """Physical rows (B, n, C) -> the model's normalised rows, derived channels appended.

    ``phase`` follows the row index. ``dt`` is drawn per run and row from the training logs'
    intervals (``config.intervals``) with ``rng``: a model told the interval must be simulated
    with intervals like the real ones, or a jittery robot is simulated as a punctual one.
    Without recorded intervals every interval is the nominal one (``dt`` = 0). ``play`` continues
    the backlash filter from the actuator position of the ``previous`` model rows (B, m, W), or
    starts it at the first row's command, as :class:`~envi_py.dataset.Dataset` does for a log.
    """
    cfg = ckpt.config
    z = ckpt.norm.encode(values)
    if not cfg.extras:
        return z.astype(np.float32)
    b, n = values.shape[:2]
    period = ckpt.record.period_ms or 40.0
    clock = [name for name in cfg.extras if name != "play"]
    ex = np.zeros((b, n, len(cfg.extras)))
    ex[..., [cfg.extras.index(name) for name in clock]] = extra_channels(
        period * np.arange(n), clock, period, cfg.phase_rows, first_row)
    if "dt" in cfg.extras and cfg.intervals is not None and rng is not None:
        q = np.asarray(cfg.intervals)
        ex[..., cfg.extras.index("dt")] = np.interp(rng.random((b, n)), np.linspace(0, 1, len(q)), q)
    if "play" in cfg.extras:
        start = None if previous is None else actuator_position(previous, cfg.n_state, cfg.channels, cfg.extras)
        ex[..., cfg.extras.index("play")] = play_offsets(z[..., cfg.n_state], 2.0 * cfg.play_width, start)
    return np.concatenate([z, ex], axis=2).astype(np.float32)


@torch.no_grad()
def rollout(ckpt: Checkpoint, controller: ControllerSpec, init: np.ndarray, steps: int,
            runs: int = 1, seed: int = 0) -> np.ndarray:
    """Simulate ``runs`` runs from each initial window.

    ``init`` is (K, l, |s|+|a|) in physical units; the result is (K*runs, l+steps, |s|+|a|),
    run ``k*runs + r`` starting from window k. Stochastic models draw from a generator seeded
    with ``seed``, so a call repeats exactly.
    """
    cfg = ckpt.config
    k, hist, chans = init.shape
    if hist != cfg.history or chans != cfg.channels:
        raise ValueError(f"initial windows are {hist}x{chans}, the model needs {cfg.history}x{cfg.channels}")
    ns = cfg.n_state
    norm = ckpt.norm
    ctrl = controller.build()
    batch = k * runs
    ctrl.reset(batch)
    gen = torch.Generator().manual_seed(int(seed)) if cfg.stochastic else None
    intervals = np.random.default_rng([int(seed), 1])  # the draws of the 'dt' channel, if the model has one
    out = np.empty((batch, hist + steps, chans))
    out[:, :hist] = np.repeat(init, runs, axis=0)
    window_np = _model_rows(ckpt, out[:, :hist], 0, intervals)
    context = torch.from_numpy(context_of(window_np, ns).astype(np.float32)) if cfg.context else None
    window = torch.from_numpy(window_np)
    model = ckpt.model.eval()
    for t in range(steps):
        x = window.reshape(batch, -1)
        if context is not None:
            x = torch.cat([x, context], dim=1)
        z = model.step(x, gen).numpy().astype(np.float64)
        s = post_process(norm.decode(np.concatenate([z, np.zeros((batch, chans - ns))], axis=1))[:, :ns], ckpt)
        out[:, hist + t, :ns] = s
        out[:, hist + t, ns:] = ctrl(s)
        row = torch.from_numpy(_model_rows(ckpt, out[:, hist + t:hist + t + 1], hist + t, intervals,
                                           window[:, -1:].numpy()))
        window = torch.cat([window[:, 1:], row], dim=1)
    return out


def initial_windows(logs: Sequence[Log], history: int) -> np.ndarray:
    """sigma_0 of each log: its first ``history`` rows, (K, l, |s|+|a|)."""
    return np.stack([lg.values[:history] for lg in logs])


ENGINES = ("auto", "native", "torch")


def choose_engine(ckpt: Checkpoint, controller: ControllerSpec, engine: str = "auto") -> str:
    """``native`` (the C++ engine) or ``torch``. ``auto`` takes native whenever it can run the model;
    asking for ``native`` when it cannot is an error that says why."""
    if engine not in ENGINES:
        raise ValueError(f"unknown engine {engine!r}; choose from {', '.join(ENGINES)}")
    if engine == "torch":
        return engine
    from . import native

    why = native.unsupported(ckpt, controller)
    if why is None:
        return "native"
    if engine == "native":
        raise ValueError(f"the native engine cannot run this: {why}")
    return "torch"


def simulate_logs(ckpt: Checkpoint, controller: ControllerSpec, init_logs: Sequence[Log],
                  steps: int | None = None, runs: int = 1, seed: int = 0, engine: str = "torch") -> list[Log]:
    """Simulate from each log's sigma_0 and return the traces as logs (source ``sim``).

    ``steps`` defaults to each real log's own length minus the window, so real and simulated runs
    cover the same span. Time continues at the initial window's median period. ``engine``: see
    :func:`choose_engine`; the default stays PyTorch because training calls this on a few logs
    many times, where compiling the model for the native engine each time would cost more than
    it saves. Stochastic draws differ between engines (each is seeded, each repeats exactly); the
    engine is recorded in every log's provenance.
    """
    hist = ckpt.config.history
    engine = choose_engine(ckpt, controller, engine)
    if engine == "native":
        from . import native

        compiled = native.load(ckpt)
        roll = lambda init, n, r, s: native.rollout(compiled, controller, init, n, r, s)  # noqa: E731
    else:
        roll = lambda init, n, r, s: rollout(ckpt, controller, init, n, r, s)  # noqa: E731
    by_len: dict[int, list[int]] = {}
    for i, lg in enumerate(init_logs):
        n = steps if steps is not None else len(lg) - hist
        by_len.setdefault(n, []).append(i)
    result: list[Log | None] = [None] * (len(init_logs) * runs)
    for n, idx in by_len.items():
        traj = roll(initial_windows([init_logs[i] for i in idx], hist), n, runs, seed + 7919 * n)
        for j, i in enumerate(idx):
            src = init_logs[i]
            period = float(np.median(np.diff(src.time[:hist]))) if hist > 1 else (src.meta.period_ms or 40.0)
            time = np.concatenate([src.time[:hist], src.time[hist - 1] + period * np.arange(1, n + 1)])
            for r in range(runs):
                tr = traj[j * runs + r]
                meta = LogMeta(schema=ckpt.schema, controller=controller.to_json(), period_ms=period,
                               run_id=f"{src.meta.run_id or src.name}-sim{r}", source="sim",
                               provenance={"init_log": src.name, "model_algorithm": ckpt.record.algorithm,
                                           "seed": seed, "replicate": r, "engine": engine})
                result[i * runs + r] = Log(None, time.copy(), tr[:, :ckpt.config.n_state].copy(),
                                           tr[:, ckpt.config.n_state:].copy(), meta)
    return [lg for lg in result if lg is not None]
