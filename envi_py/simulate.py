"""Closed-loop simulation: the controller under test against an environment model.

From an initial window sigma_0 (the first l rows of a real log) the model predicts the next state,
the controller answers with its action, and the window slides; N runs per initial window are
batched into one tensor so a whole verification is one loop over time steps. This PyTorch engine
is the reference; the native runtime implements the same loop and is tested against it.
"""

from __future__ import annotations

from collections.abc import Callable, Iterator, Sequence
from pathlib import Path

import numpy as np
import torch

from .controllers import ControllerSpec, in_range
from .effect_layers import RANDOM_LAYERS, LayerStack, describe, layers_json
from .logs import Log, LogMeta, group_by_controller
from .model import Checkpoint
from .system import LogSchema


def initial_rows(init: np.ndarray, ckpt: Checkpoint) -> tuple[np.ndarray, np.ndarray]:
    """sigma_0's states (K, l, |s|) and actions (K, l, |a|): what a controller is warmed up on."""
    ns = ckpt.config.n_state
    return init[..., :ns], init[..., ns:]


def window_shape(ckpt: Checkpoint, init: np.ndarray) -> tuple[int, int, int]:
    """(K, l, C) of the initial windows ``init``, refused unless l and C are the model's."""
    cfg = ckpt.config
    k, hist, chans = init.shape
    if hist != cfg.history or chans != cfg.channels:
        raise ValueError(f"initial windows are {hist}x{chans}, the model needs {cfg.history}x{cfg.channels}")
    return k, hist, chans


class ModelWindow:
    """The last l rows of a batch of runs as the model reads them (encoded, with the model's context).

    One owner of encoding, stepping and sliding, so every PyTorch rollout (:func:`rollout`, the
    diagnosis's layered one) feeds the model alike; ``intervals`` draws the 'dt' channel, if the
    model has one, in the same order in every rollout."""

    def __init__(self, ckpt: Checkpoint, rows: np.ndarray, intervals: np.random.Generator) -> None:
        self.ckpt, self.intervals = ckpt, intervals
        window = ckpt.encode_rows(rows, 0, intervals)
        context = ckpt.context(window)
        self.context = None if context is None else torch.from_numpy(context)
        self.window = torch.from_numpy(window)

    def next_state(self, gen: torch.Generator | None) -> np.ndarray:
        """The model's next states (N, |s|) from the window (drawn with ``gen`` when it is stochastic)."""
        return self.ckpt.next_state(self.ckpt.model_input(self.window, self.context), gen)

    def push(self, row: np.ndarray, index: int) -> None:
        """Slide the window by one physical row (N, 1, C), row ``index`` of the runs."""
        encoded = self.ckpt.encode_rows(row, index, self.intervals, self.window[:, -1:].numpy())
        self.window = torch.cat([self.window[:, 1:], torch.from_numpy(encoded)], dim=1)


@torch.no_grad()
def rollout(
    ckpt: Checkpoint,
    controller: ControllerSpec,
    init: np.ndarray,
    steps: int,
    runs: int = 1,
    seed: int = 0,
    mean: bool = False,
) -> np.ndarray:
    """Simulate ``runs`` runs from each initial window.

    ``init`` is (K, l, |s|+|a|) in physical units; the result is (K*runs, l+steps, |s|+|a|),
    run ``k*runs + r`` starting from window k. The controller is reset and warmed up on sigma_0
    (so a PID's memory matches the real one's at row l), then answers every simulated state.
    Stochastic models draw from a generator seeded with ``seed``, so a call repeats exactly;
    ``mean`` simulates a stochastic model by its mean instead (no draws, limit events where likelier
    than not): one deterministic trajectory per window, what the model expects rather than what it samples.
    The checkpoint's effect layers (:mod:`envi_py.effect_layers`) act at every step, their draws
    seeded apart from the model's. A seed ensemble's runs are shared out among its members
    (:func:`ensemble_rollout`).
    """
    if ckpt.members:
        members = [ckpt.member(m) for m in range(ckpt.size)]
        return ensemble_rollout(
            [lambda i, n, r, s, m=m: rollout(m, controller, i, n, r, s, mean) for m in members], init, steps, runs, seed
        )
    cfg = ckpt.config
    k, hist, chans = window_shape(ckpt, init)
    if steps < 0:
        raise ValueError(f"steps must not be negative, got {steps}")
    if mean and cfg.kind == "random":
        raise ValueError("the random baseline has no mean to simulate; simulate it without --mean")
    ns = cfg.n_state
    ctrl = controller.build(ns, cfg.n_action, ckpt.period_ms)
    actions = ckpt.schema.actions
    batch = k * runs
    out = np.empty((batch, hist + steps, chans))
    out[:, :hist] = np.repeat(init, runs, axis=0)
    ctrl.reset(batch)
    ctrl.warmup(*initial_rows(out[:, :hist], ckpt))
    gen = torch.Generator().manual_seed(int(seed)) if cfg.stochastic and not mean else None
    intervals = np.random.default_rng([int(seed), 1])  # the draws of the 'dt' channel, if the model has one
    # effect layers: the log holds what the controller saw and said, the model's window what it sees
    layers = LayerStack(ckpt.layers, out[:, :hist, ns:], steps, np.random.default_rng([int(seed), 2]))
    view = out.copy() if ckpt.layers else out
    window = ModelWindow(ckpt, view[:, :hist], intervals)
    for t in range(steps):
        s = window.next_state(gen)
        seen = sensor_reading(ckpt, layers.states(s)) if layers.state_layers else s
        out[:, hist + t, :ns] = seen
        out[:, hist + t, ns:] = in_range(ctrl(seen), actions, controller)
        if view is not out:
            view[:, hist + t, :ns], view[:, hist + t, ns:] = s, layers.commands(out[:, hist + t, ns:])
        window.push(view[:, hist + t : hist + t + 1], hist + t)
    return out


def draws_at_random(ckpt: Checkpoint, mean: bool = False) -> bool:
    """Whether two runs from one initial window can differ: a sampled head, a seed ensemble (each run
    drawn by one member), a noise or per-run gain layer, or intervals drawn for a 'dt' channel."""
    return (
        (ckpt.config.stochastic and not mean)
        or ckpt.size > 1
        or any(layer.kind in RANDOM_LAYERS for layer in ckpt.layers)
        or ("dt" in ckpt.config.extras and ckpt.config.intervals is not None)
    )


def sensor_reading(ckpt: Checkpoint, seen: np.ndarray) -> np.ndarray:
    """What a sensor reports of the layered states ``seen`` (B, |s|): within each state's declared
    range and at its resolution, as the model's own states are (a noise layer of sd 50 once wrote
    colour readings of -113 and 188, which every later command refused as a log). A layer that
    drives a state to a non-finite value is a ValueError naming the state."""
    bad = ~np.isfinite(seen).all(axis=0)
    if bad.any():
        name = ckpt.schema.states[int(np.argmax(bad))].name
        raise ValueError(f"the effect layers {describe(ckpt.layers)} drive state {name!r} to a non-finite value")
    low = np.array([c.low for c in ckpt.schema.states])
    high = np.array([c.high for c in ckpt.schema.states])
    seen = np.clip(seen, low, high)
    if ckpt.config.round_to is not None:
        res = np.asarray(ckpt.config.round_to)
        seen = np.round(seen / res) * res
    return seen


#: (initial windows (K, l, C), steps, runs per window, seed) -> runs (K*runs, l+steps, C): one
#: engine's rollout of one model
Roll = Callable[[np.ndarray, int, int, int], np.ndarray]


_MASK = (1 << 64) - 1


def _splitmix64(state: int) -> tuple[int, int]:
    """SplitMix64's next (state, value), as ``cpp/include/envi/ensemble.hpp`` computes it."""
    state = (state + 0x9E3779B97F4A7C15) & _MASK
    z = ((state ^ (state >> 30)) * 0xBF58476D1CE4E5B9) & _MASK
    z = ((z ^ (z >> 27)) * 0x94D049BB133111EB) & _MASK
    return state, z ^ (z >> 31)


def members_of_runs(members: int, batch: int, seed: int) -> np.ndarray:
    """Which member simulates each of ``batch`` runs: each member an equal share (to within one run),
    in a seeded random order. Balanced rather than drawn independently, so 10 runs of 3 members are
    never all of one; random so that which run a member gets does not follow the window order. A
    Fisher-Yates shuffle of ``g mod members`` driven by SplitMix64, the very draws of ``envi_sim``'s
    twin (``cpp/include/envi/ensemble.hpp``), so both give each run to the same member."""
    pick = np.arange(batch) % members
    state = int(seed) & _MASK
    for i in range(batch - 1, 0, -1):
        state, value = _splitmix64(state)
        j = value % (i + 1)
        pick[i], pick[j] = pick[j], pick[i]
    return pick


def ensemble_rollout(rolls: Sequence[Roll], init: np.ndarray, steps: int, runs: int, seed: int) -> np.ndarray:
    """:func:`rollout`'s contract for a seed ensemble, ``rolls`` being each member's: run
    ``k*runs + r`` from window k is simulated by the member :func:`members_of_runs` picks, each
    member's runs together in one call with their own seed. Any engine's rollout fits, so the PyTorch
    and native engines split runs alike."""
    batch = len(init) * runs
    if batch == 0:  # no run to share out: an empty batch behaves as a single model's does
        return rolls[0](init, steps, runs, seed)
    pick = members_of_runs(len(rolls), batch, seed)
    out: np.ndarray | None = None
    for m, roll in enumerate(rolls):
        idx = np.flatnonzero(pick == m)
        if not len(idx):
            continue
        part = roll(np.ascontiguousarray(init[idx // runs]), steps, 1, int(seed) + 15485863 * (m + 1))
        if out is None:
            out = np.empty((batch, *part.shape[1:]))
        out[idx] = part
    assert out is not None  # batch >= 1: some member ran
    return out


def initial_windows(logs: Sequence[Log], history: int) -> np.ndarray:
    """sigma_0 of each log: its first ``history`` rows, (K, l, |s|+|a|)."""
    return np.stack([lg.values[:history] for lg in logs])


ENGINES = ("auto", "native", "torch")


def choose_engine(ckpt: Checkpoint, controller: ControllerSpec, engine: str = "auto", mean: bool = False) -> str:
    """``native`` (the C++ engine) or ``torch``. ``auto`` takes native whenever it can run the model
    (in ``mean`` mode too); asking for ``native`` when it cannot is an error that says why."""
    if engine not in ENGINES:
        raise ValueError(f"unknown engine {engine!r}; choose from {', '.join(ENGINES)}")
    if engine == "torch":
        return engine
    from . import native

    why = native.unsupported(ckpt, controller, mean)
    if why is None:
        return "native"
    if engine == "native":
        raise ValueError(f"the native engine cannot run this: {why}")
    return "torch"


#: Simulated runs held in memory at once when streaming: the replicates of a call are simulated in
#: chunks of about this many runs, so memory does not grow with ``runs``.
CHUNK_RUNS = 20_000


def iter_simulate(
    ckpt: Checkpoint,
    controller: ControllerSpec,
    init_logs: Sequence[Log],
    steps: int | None = None,
    runs: int = 1,
    seed: int = 0,
    engine: str = "torch",
    mean: bool = False,
) -> Iterator[tuple[int, int, Log]]:
    """Simulate from each log's sigma_0, yielding ``(initial log index, replicate, log)`` chunk by
    chunk (source ``sim``).

    ``steps`` defaults to each real log's own length minus the window, so real and simulated runs
    cover the same span. Time continues at the initial window's median period. ``engine``: see
    :func:`choose_engine`. Stochastic draws differ between engines (each is seeded, each repeats
    exactly); the engine is recorded in every log's provenance. Replicates are simulated in chunks
    of about :data:`CHUNK_RUNS` runs, each chunk with its own seed, so a million runs stream
    through flat memory and the same call always gives the same runs. Run ids are ``<initial log's
    file stem>-sim<r>`` (its run id for a log in memory), so versions whose logs share run numbers
    do not collide. ``mean``: see :func:`rollout` (recorded in the provenance).
    """
    hist = ckpt.config.history
    engine = choose_engine(ckpt, controller, engine, mean)
    roll: Roll
    if engine == "native":
        from . import native

        compiled = [native.load(native.mean_model(m) if mean else m) for m in map(ckpt.member, range(ckpt.size))]
        rolls: list[Roll] = [lambda init, n, r, s, c=c: native.rollout(c, controller, init, n, r, s) for c in compiled]
        roll = rolls[0] if len(rolls) == 1 else lambda init, n, r, s: ensemble_rollout(rolls, init, n, r, s)
    else:
        roll = lambda init, n, r, s: rollout(ckpt, controller, init, n, r, s, mean)  # noqa: E731
    by_len: dict[int, list[int]] = {}
    for i, lg in enumerate(init_logs):
        n = steps if steps is not None else len(lg) - hist
        if n == 0 and steps is None:  # once a 'simulated' log of sigma_0 alone, exit 0
            raise ValueError(
                f"{lg.path or lg.name}: {len(lg)} rows, the model's window alone: no row is left to "
                "simulate; give --steps, or a longer log"
            )
        by_len.setdefault(n, []).append(i)
    ns = ckpt.config.n_state
    schema = LogSchema(ckpt.schema.states, ckpt.schema.actions)
    for n, idx in by_len.items():
        init = initial_windows([init_logs[i] for i in idx], hist)
        chunk = max(1, CHUNK_RUNS // len(idx))
        for r0 in range(0, runs, chunk):
            count = min(chunk, runs - r0)
            traj = roll(init, n, count, seed + 7919 * n + 104729 * r0)
            for j, i in enumerate(idx):
                src = init_logs[i]
                period = (
                    float(np.median(np.diff(src.time[:hist]))) if hist > 1 else (src.meta.period_ms or ckpt.period_ms)
                )
                time = np.concatenate([src.time[:hist], src.time[hist - 1] + period * np.arange(1, n + 1)])
                stem = Path(src.path).stem if src.path else src.meta.run_id
                for k in range(count):
                    r = r0 + k
                    tr = traj[j * count + k]
                    meta = LogMeta(
                        schema=schema,
                        controller=controller.to_json(),
                        period_ms=period,
                        run_id=f"{stem}-sim{r}",
                        source="sim",
                        provenance={
                            "init_log": src.name,
                            "model_algorithm": ckpt.record.algorithm,
                            "seed": seed,
                            "replicate": r,
                            "engine": engine,
                            **({"members": ckpt.size} if ckpt.members else {}),
                            **({"mean": True} if mean else {}),
                            **({"layers": layers_json(ckpt.layers)} if ckpt.layers else {}),
                        },
                    )
                    yield i, r, Log(None, time.copy(), tr[:, :ns].copy(), tr[:, ns:].copy(), meta)
            del traj


def simulate_logs(
    ckpt: Checkpoint,
    controller: ControllerSpec,
    init_logs: Sequence[Log],
    steps: int | None = None,
    runs: int = 1,
    seed: int = 0,
    engine: str = "torch",
    mean: bool = False,
) -> list[Log]:
    """:func:`iter_simulate` collected in order (initial log, then replicate). The default engine
    stays PyTorch because training calls this on a few logs many times, where compiling the model
    for the native engine each time would cost more than it saves."""
    result: list[Log | None] = [None] * (len(init_logs) * runs)
    for i, r, lg in iter_simulate(ckpt, controller, init_logs, steps, runs, seed, engine, mean):
        result[i * runs + r] = lg
    return [lg for lg in result if lg is not None]


def simulate_versions(
    ckpt: Checkpoint,
    init_logs: Sequence[Log],
    runs: int = 1,
    seed: int = 0,
    engine: str = "torch",
    steps: int | None = None,
    controller: ControllerSpec | None = None,
    mean: bool = False,
) -> list[Log]:
    """Each log's own controller version simulated from its sigma_0 (or every log under
    ``controller`` when given): the one loop over versions every command uses."""
    return [
        lg
        for group in versions_to_simulate(init_logs, controller)
        for lg in simulate_logs(ckpt, group[0], group[1], steps, runs, seed, engine, mean)
    ]


def versions_to_simulate(
    init_logs: Sequence[Log], controller: ControllerSpec | None = None
) -> list[tuple[ControllerSpec, list[Log]]]:
    """(controller, initial logs) pairs: each log's own version, or all logs under ``controller``."""
    if controller is not None:
        return [(controller, list(init_logs))]
    return list(group_by_controller(init_logs).items())
