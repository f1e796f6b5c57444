"""The model-selection score any system can use: how far simulated runs are from real ones.

For each controller version, every goal metric is computed on the real and on the simulated runs
and the two samples are compared by their Wasserstein-1 distance (in the metric's unit), divided by
the metric's scale (the width of its possible range for the signal's declared range, see
:mod:`.library`) so that metrics of different signals and units weigh alike. The score is the mean
over goals and versions: 0 is a perfect match, lower is better. Without declared goals, every
state channel is scored by its mean, standard deviation and largest deviation from the middle of
its range: what a model predicts is the states, and these three see its level, its spread and its
excursions.

Divergence is checked beside it, because a mean of distribution distances hides a minority of
runs that ran away: each such run weighs only 1/R in every metric's sample, yet a verification on
that model would report verdicts on trajectories no real system shows. A run *diverges* when a
state channel stays, for ``sustain`` consecutive scored samples, at a limit of its declared range
(where a simulator clips a runaway prediction) or outside the range the training data showed
(widened by ``margin`` of its width). The same rule is applied to the real runs, since a saturating
sensor (an ultrasonic sensor reading its maximum) legitimately sits at its limit in reality too;
a model is flagged *diverged* when its fraction exceeds the real runs' own fraction by more than
``tolerance`` (allowing for sampling noise), and its score is then ``inf``, so selecting the
lowest score never keeps a diverged model, while ``distance`` still says how close it was.
"""

from __future__ import annotations

import math
from collections.abc import Hashable, Mapping, Sequence
from dataclasses import dataclass, replace

import numpy as np
from scipy import stats

from ..system import Channel, GoalSpec, LogSchema
from .evaluate import Runs, goal_scale, goal_values


@dataclass(frozen=True)
class SelectionScore:
    """The score (inf when diverged), the plain distance, its parts and the divergence check."""

    score: float
    distance: float  # mean normalised W1 over goals and versions, whatever the divergence
    per_goal: dict[str, float]  # mean normalised W1 of each goal over versions
    sim_divergence: float  # fraction of simulated runs that diverged
    real_divergence: float  # the same rule on the real runs
    diverged: bool
    real_runs: int
    sim_runs: int

    def to_json(self) -> dict[str, object]:
        return {
            "score": self.score,
            "distance": self.distance,
            "per_goal": dict(self.per_goal),
            "sim_divergence": self.sim_divergence,
            "real_divergence": self.real_divergence,
            "diverged": self.diverged,
            "real_runs": self.real_runs,
            "sim_runs": self.sim_runs,
        }


def default_goals(schema: LogSchema, observed: Mapping[str, tuple[float, float]]) -> tuple[GoalSpec, ...]:
    """Mean, std and max |x - mid-range| of every state channel (mid of the declared range, or of the
    observed one when the declared range is not finite)."""
    goals = []
    for ch in schema.states:
        low, high = _effective_range(ch, observed)
        mid = (low + high) / 2.0
        goals += [
            GoalSpec(f"mean({ch.name})", "mean", ch.name),
            GoalSpec(f"std({ch.name})", "std", ch.name),
            GoalSpec(f"max_abs_dev({ch.name}, {mid:g})", "max_abs_dev", ch.name, {"setpoint": mid}),
        ]
    return tuple(goals)


def observed_ranges(runs: Sequence[Runs], names: Sequence[str]) -> dict[str, tuple[float, float]]:
    """The smallest and largest value of each named signal over all rows of all ``runs``."""
    out = {}
    for name in names:
        values = [np.asarray(r.signals[name], dtype=np.float64) for r in runs if name in r.signals]
        if not values:
            raise ValueError(f"no runs hold signal {name!r}")
        out[name] = (float(min(v.min() for v in values)), float(max(v.max() for v in values)))
    return out


def selection_score(
    real: Mapping[Hashable, Runs],
    sim: Mapping[Hashable, Runs],
    schema: LogSchema,
    goals: Sequence[GoalSpec] = (),
    observed: Mapping[str, tuple[float, float]] | None = None,
    sustain: int | None = None,
    margin: float = 0.05,
    tolerance: float = 0.05,
    limits: Sequence[Channel] | None = None,
) -> SelectionScore:
    """Score simulated runs against real runs of the same controller versions (keys).

    ``observed``: each state's range in the training data (default: the real runs given);
    ``sustain``: samples a divergence must last (default a tenth of the scored run, at least 2);
    ``limits``: the states with the limits a diverged run rests at (default: the schema's declared
    ranges; :func:`runaway_states` gives the simulator's clamp)."""
    if not real or set(real) != set(sim):
        raise ValueError(
            f"real and simulated runs must cover the same controller versions; real: "
            f"{sorted(map(str, real))}, simulated: {sorted(map(str, sim))}"
        )
    channels = {c.name: c for c in schema.channels + schema.logged}
    state_names = [c.name for c in schema.states]
    observed = dict(observed) if observed is not None else observed_ranges(list(real.values()), state_names)
    missing = [n for n in state_names if n not in observed]
    if missing:
        raise ValueError(f"observed ranges lack state(s) {', '.join(missing)}")
    goals = tuple(goals) or default_goals(schema, observed)
    if len({g.name for g in goals}) != len(goals):
        raise ValueError("two goals share a name; each goal's distance is reported under its name")
    for g in goals:
        if g.signal not in channels:
            raise ValueError(f"goal {g.name!r} reads signal {g.signal!r}, which the schema does not declare")
    ranges = {**observed_ranges(list(real.values()), sorted({g.signal for g in goals})), **observed}
    per_goal: dict[str, list[float]] = {g.name: [] for g in goals}
    for version, real_runs in real.items():
        sim_runs = sim[version]
        if real_runs.period_ms != sim_runs.period_ms or real_runs.skip != sim_runs.skip:
            raise ValueError(f"version {version}: real and simulated runs differ in period or skipped rows")
        for g in goals:
            rv, sv = goal_values(g, real_runs), goal_values(g, sim_runs)
            scale = _scale(g, _effective_range(channels[g.signal], ranges), real_runs, rv)
            per_goal[g.name].append(stats.wasserstein_distance(rv, sv) / scale)
    means = {name: float(np.mean(v)) for name, v in per_goal.items()}
    distance = float(np.mean(list(means.values())))
    states = list(limits) if limits is not None else [channels[n] for n in state_names]
    sim_frac = diverged_fraction(list(sim.values()), states, observed, sustain, margin)
    real_frac = diverged_fraction(list(real.values()), states, observed, sustain, margin)
    diverged = sim_frac > real_frac + tolerance
    return SelectionScore(
        math.inf if diverged else distance,
        distance,
        means,
        sim_frac,
        real_frac,
        diverged,
        sum(r.count for r in real.values()),
        sum(r.count for r in sim.values()),
    )


def _effective_range(ch: Channel, observed: Mapping[str, tuple[float, float]]) -> tuple[float, float]:
    if math.isfinite(ch.low) and math.isfinite(ch.high):
        return ch.low, ch.high
    if ch.name not in observed:
        raise ValueError(f"signal {ch.name!r} declares no finite range and none was observed")
    return observed[ch.name]


def _scale(goal: GoalSpec, signal_range: tuple[float, float], runs: Runs, real_values: np.ndarray) -> float:
    """The goal's scale from its signal's range (declared, else observed); for a metric with no
    derivable scale (a user's), the spread of its real values; 1 if that is zero too."""
    scale = goal_scale(goal, *signal_range, runs.scored_length, runs.period_ms)
    if scale is None or not scale > 0:
        scale = float(np.ptp(real_values))
    return scale if scale > 0 else 1.0


def _longest_stretch(mask: np.ndarray) -> np.ndarray:
    """Per row of ``mask`` (R, T), the length of its longest run of consecutive True."""
    counts = np.cumsum(mask, axis=1)
    reset = np.maximum.accumulate(np.where(~mask, counts, 0), axis=1)
    return (counts - reset).max(axis=1)


def runaway_states(
    states: Sequence[Channel], clamp: Sequence[tuple[float, float]], limit_readings: Sequence[tuple[int, float]]
) -> list[Channel]:
    """The states with the limits a run that left reality sits at, for :func:`diverged_fraction`: the
    range the simulator clamps to (a model whose distance collapses rests there, inside the observed
    range), and each saturating sensor's limit reading taken out (``limit_readings``: state index and
    reading): that is what the sensor says with nothing in range, and real runs hold it too (the car
    twin's far starts hold 255 for most of a run, 15-17 % of real runs for a tenth of it or more).
    Measured in benchmarks/fidelity_car.py: this rule fires on 0 of 1,600 real car runs and on every
    run of a model collapsed onto its 12 cm clamp, which the declared-range rule never flagged."""
    out = [replace(ch, low=lo, high=hi) for ch, (lo, hi) in zip(states, clamp)]
    for i, reading in limit_readings:
        ch = out[i]
        out[i] = replace(ch, high=math.inf) if reading >= ch.high else replace(ch, low=-math.inf)
    return out


def diverged_runs(
    runs: Runs,
    channels: Sequence[Channel],
    observed: Mapping[str, tuple[float, float]],
    sustain: int | None,
    margin: float,
) -> np.ndarray:
    """Per run (R,), whether some channel sits at a limit of its range or outside its observed range
    (widened by ``margin`` of its width) for ``sustain`` consecutive scored samples (by default a
    tenth of the scored run). A channel with infinite limits is judged on its observed range alone."""
    need = sustain if sustain is not None else max(2, math.ceil(0.1 * runs.scored_length))
    bad = np.zeros(runs.count, dtype=bool)
    for ch in channels:
        x = runs.scored(ch.name)
        lo, hi = observed[ch.name]
        widen = margin * (hi - lo)
        flag = (x < lo - widen) | (x > hi + widen)
        if math.isfinite(ch.low):  # at the limit reading (Channel.reads: within half a step) or beyond it
            flag |= (x < ch.low) | ch.reads(x, ch.low)
        if math.isfinite(ch.high):
            flag |= (x > ch.high) | ch.reads(x, ch.high)
        bad |= _longest_stretch(flag) >= need
    return bad


def diverged_fraction(
    runs: Sequence[Runs],
    states: Sequence[Channel],
    observed: Mapping[str, tuple[float, float]],
    sustain: int | None,
    margin: float,
) -> float:
    """Fraction of runs in which some state diverged (:func:`diverged_runs`), over all ``runs``."""
    diverged = sum(int(diverged_runs(r, states, observed, sustain, margin).sum()) for r in runs)
    return diverged / sum(r.count for r in runs)
