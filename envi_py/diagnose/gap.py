"""Where the closed-loop gap lies: by goal, by horizon, by region of state x action, by controller
version, and where simulated windows leave the region the training data covers.

The goals are the system's (:func:`envi_py.verify.goals_for` through :class:`envi_py.verify.Scoring`:
the paper's eight metrics for the lane-keeping preset, the declared goals otherwise, default goals
on every state for a system declaring none). Every gap is measured against the project's one fair
floor (:func:`envi_py.verify.fair_reference`, :func:`envi_py.verdicts.fair_floor`): a real half
against as many simulated runs beside a real half against the other, m = n_real // 2 runs per side,
with the permutation test of "simulated runs are exchangeable with real ones".
"""

from __future__ import annotations

from typing import Any, Sequence

import numpy as np
from scipy import stats

from ..goals.evaluate import goal_unit
from ..logs import Log
from ..model import Checkpoint
from ..verdicts import fair_floor, w1_normalised
from ..verify import Scoring, fair_reference
from .effects import holm, n_eff
from .residuals import Residuals, ResidualSet

#: Repetitions and relabellings of the fair floor, as :func:`envi_py.verify.fair_reference` uses.
REPETITIONS, PERMUTATIONS = 10, 99
#: Relabellings of the per-version test on the mean over the goals (:func:`gap_test`): its smallest
#: p-value is 1/200, so a gap in one of up to ten versions can still be significant after Holm.
VERSION_PERMUTATIONS = 199
#: A goal's gap is beyond the floor when its permutation test gives p <= LEVEL.
LEVEL = 0.05
#: Real runs of each controller version the fair floor needs: one real half against the other.
MIN_RUNS = 2


def ratio_text(ratio: float) -> str:
    """A ratio to a real-vs-real floor as every section prints it: one number per concept."""
    if ratio == float("inf"):
        return "floor 0: any difference is a gap"
    return f"{ratio:.1f}x"


def share_text(share: float) -> str:
    """A share as every section prints it (whole percent, one decimal below 10%)."""
    return f"{share:.1%}" if abs(share) < 0.1 else f"{share:.0%}"


def floor_ratio(value: float, floor: float) -> float:
    """``value`` over a real-vs-real floor. A floor of exactly 0 (the real runs never differ in this
    goal) makes any gap infinite and no gap 0, rather than a huge number from a tiny divisor."""
    if floor > 0:
        return value / floor
    return 0.0 if value == 0 else float("inf")


def gap_rank(row: dict[str, Any]) -> tuple[bool, float, float]:
    """Goals beyond the floor by their permutation test first, each group by its ratio to the floor,
    largest first: a large ratio resting on a few runs that chance explains does not lead."""
    return (not row["beyond_floor"], -row["ratio"], row["p"])


def cut_logs(logs: Sequence[Log], t: int) -> list[Log]:
    """The first ``t`` rows of each log: real and simulated runs are scored over the same span."""
    return [
        lg if len(lg) == t else Log(lg.path, lg.time[:t], lg.states[:t], lg.actions[:t], lg.meta, lg.logged[:t])
        for lg in logs
    ]


def _bootstrap_ci(mr: np.ndarray, ms: np.ndarray, scale: float, rng: np.random.Generator, boot: int) -> list[float]:
    """95% interval of the all-runs normalised W1, runs resampled on both sides."""
    bs = [
        stats.wasserstein_distance(mr[rng.integers(0, len(mr), len(mr))], ms[rng.integers(0, len(ms), len(ms))]) / scale
        for _ in range(boot)
    ]
    return [float(np.percentile(bs, 2.5)), float(np.percentile(bs, 97.5))]


def goal_gaps(
    scoring: Scoring, real: Sequence[Log], sim: Sequence[Log], seed: int = 0, boot: int = 200
) -> dict[str, Any]:
    """The gap of one controller version on every goal, ranked by :func:`gap_rank`.

    Per goal: the matched W1 (a real half against m simulated runs) over the fair floor (a real half
    against the other), both from :func:`~envi_py.verify.fair_reference` (the figures ``envi verify``
    reports), the permutation test's p-value on that goal (:func:`~envi_py.verdicts.fair_floor`, its
    null band of the ratio), and the W1 of all simulated runs against all real runs with a bootstrap
    95% interval (``boot`` resamplings; none when 0). Needs :data:`MIN_RUNS` real runs and as many simulated ones."""
    if len(real) < MIN_RUNS:
        raise ValueError(
            f"the fair floor needs at least {MIN_RUNS} real runs of each controller version, got {len(real)}"
        )
    rr, sr = scoring.runs(real), scoring.runs(sim)
    mr, ms, scale = scoring.table(rr), scoring.table(sr), scoring.scales(rr)
    floor, matched, tests = fair_reference(mr, ms, scale, None, None, seed, REPETITIONS, VERSION_PERMUTATIONS)
    rng = np.random.default_rng(seed)
    units = {c.name: c.unit for c in scoring.schema.channels}
    rows = []
    for j, goal in enumerate(scoring.goals):
        test = fair_floor(mr[:, j], ms[:, j], w1_normalised(scale[j]), REPETITIONS, PERMUTATIONS, LEVEL, seed)
        w1, fl = float(matched.w1[j]), float(floor.w1[j])
        rows.append(
            {
                "goal": goal.name,
                "signal": goal.signal,
                "unit": goal_unit(goal, units.get(goal.signal, "")),
                "scale": float(scale[j]),
                "w1": w1,
                "floor": fl,
                "ratio": floor_ratio(w1, fl),
                "ratio_null_band": [float(v) for v in test.ratio_null_band],
                "p": test.p_value,
                "beyond_floor": not test.within_floor,
                "w1_all": float(stats.wasserstein_distance(mr[:, j], ms[:, j]) / scale[j]),
                "ci": _bootstrap_ci(mr[:, j], ms[:, j], float(scale[j]), rng, boot) if boot else None,
                "real": mr[:, j].tolist(),
                "sim": ms[:, j].tolist(),
            }
        )
    rows.sort(key=gap_rank)
    return {
        "gaps": rows,
        "n_real": int(mr.shape[0]),
        "n_sim": int(ms.shape[0]),
        "per_side": int(tests["per_side"]),
        "mean_w1": float(np.mean(matched.w1)),
        "mean_floor": float(np.mean(floor.w1)),
        "goals_test": tests["goals_w1"],
    }


def _w1_column(a: np.ndarray, b: np.ndarray) -> float:
    return float(stats.wasserstein_distance(a.ravel(), b.ravel()))


def oscillation_rows(real: np.ndarray, low: int = 3) -> int:
    """The real runs' dominant period in rows: the first peak of their mean autocorrelation after it
    turns negative (``low`` rows at least, a third of the run at most; a third of the run when the
    readings do not oscillate). Pooling readings over one period makes a window's distribution blind
    to phase: two runs of one oscillation at different phases then look alike, as they should."""
    x = real - real.mean(axis=1, keepdims=True)
    t = x.shape[1]
    cap = max(low, t // 3)
    denom = np.sum(x * x, axis=1)
    ok = denom > 0
    if not ok.any():
        return cap
    ac = np.array([np.mean(np.sum(x[ok, : t - k] * x[ok, k:], axis=1) / denom[ok]) for k in range(cap + 1)])
    negative = np.flatnonzero(ac < 0)
    if not len(negative):
        return cap
    return int(np.clip(negative[0] + int(np.argmax(ac[negative[0] :])), low, cap))


def horizon_gap(real: np.ndarray, sim: np.ndarray, skip: int, seed: int = 0) -> dict[str, Any]:
    """How the gap of one state grows with the horizon, blind to phase: at each step, the readings of
    the last ``width`` rows (one oscillation period of the real runs, :func:`oscillation_rows`) pooled
    per run, the W1 of a real half against as many simulated runs over the W1 of the two real halves
    (the fair floor's design, :func:`~envi_py.verdicts.fair_floor`, 10 random splits). Per-step W1 of
    single readings measures the phase spread of an oscillating robot instead (large for two real
    runs alike but for their phase). ``real`` and ``sim`` are (runs, steps)."""
    t = min(real.shape[1], sim.shape[1])
    width = min(oscillation_rows(real[:, skip:t]), t - skip)
    ends = np.arange(skip + width, t + 1)
    per_step = [
        fair_floor(real[:, e - width : e], sim[:, e - width : e], _w1_column, REPETITIONS, 1, LEVEL, seed) for e in ends
    ]
    ratio = np.array([floor_ratio(f.sim, f.floor) for f in per_step])
    above = ratio > 1.0
    # the first window from which the windowed gap stays above the floor to the end of the run
    stays = int(np.flatnonzero(~above)[-1] + 1) if (~above).any() else 0
    return {
        "step": (ends - 1).tolist(),
        "width": width,
        "w1": [f.sim for f in per_step],
        "floor": [f.floor for f in per_step],
        "ratio": ratio.tolist(),
        "per_side": real.shape[0] // 2,
        "median_ratio": float(np.median(ratio)),
        "above_share": float(above.mean()),
        "above_from_step": int(ends[stays] - 1) if stays < len(ends) else None,
    }


def _action_cells(action: np.ndarray) -> tuple[np.ndarray, list[str]]:
    """Each residual's action cell: the action's values when it takes at most 8, else 8 quantile bins."""
    actions = np.unique(action)
    if len(actions) > 8:
        edges = np.quantile(action, np.linspace(0, 1, 9))
        edges[-1] += 1e-9
        return np.clip(np.searchsorted(edges, action, side="right") - 1, 0, 7), [
            f"{edges[i]:.3g}..{edges[i + 1]:.3g}" for i in range(8)
        ]
    return np.searchsorted(actions, action), [f"{a:g}" for a in actions]


def state_action_map(res: Residuals, state_bins: int = 8, alpha: float = 0.05) -> dict[str, Any]:
    """Mean one-step residual of one state over its own value x one action's value, with the cells
    whose bias is significant (t-test on the effective sample size, Bonferroni over cells)."""
    edges = np.quantile(res.state, np.linspace(0, 1, state_bins + 1))
    edges[-1] += 1e-9
    a_idx, a_labels = _action_cells(res.action)
    s_idx = np.clip(np.searchsorted(edges, res.state, side="right") - 1, 0, state_bins - 1)
    ratio = n_eff(res) / len(res)
    cells = len(a_labels) * state_bins
    mean = np.full((len(a_labels), state_bins), np.nan)
    count = np.zeros_like(mean)
    significant = []
    for i in range(len(a_labels)):
        for j in range(state_bins):
            r = res.r[(a_idx == i) & (s_idx == j)]
            count[i, j] = len(r)
            if len(r) < 5:
                continue
            mean[i, j] = r.mean()
            ne = max(2.0, len(r) * ratio)
            tstat = r.mean() / (r.std(ddof=1) / np.sqrt(ne) + 1e-12)
            p = 2 * stats.t.sf(abs(tstat), ne - 1)
            if p * cells < alpha:
                significant.append(
                    {
                        "action": a_labels[i],
                        "state": [float(edges[j]), float(edges[j + 1])],
                        "bias": float(r.mean()),
                        "sd": float(r.std()),
                        "n": int(len(r)),
                        "p_bonferroni": float(min(1.0, p * cells)),
                    }
                )
    return {
        "action_signal": res.action_name,
        "state_edges": edges.tolist(),
        "actions": a_labels,
        "mean": mean.tolist(),
        "count": count.tolist(),
        "significant": sorted(significant, key=lambda c: -abs(c["bias"])),
    }


def residual_map(res: ResidualSet, state_bins: int = 8, alpha: float = 0.05) -> list[dict[str, Any]]:
    """Per state channel: its one-step RMSE (physical, and over the channel's range), its mean
    residual over its own value x each action's value (:func:`state_action_map`) and over the phase
    of the run."""
    out = []
    for k, s in enumerate(res.states):
        phase_edges = np.quantile(s.row, np.linspace(0, 1, 6))
        ph = np.clip(np.searchsorted(phase_edges, s.row, side="right") - 1, 0, 4)
        phase = [
            {
                "rows": [float(phase_edges[i]), float(phase_edges[i + 1])],
                "bias": float(s.r[ph == i].mean()),
                "sd": float(s.r[ph == i].std()),
                "rms": float(np.sqrt(np.mean(s.r[ph == i] ** 2))),
            }
            for i in range(5)
            if np.any(ph == i)
        ]
        rmse = float(np.sqrt(np.mean(s.r**2)))
        out.append(
            {
                "signal": s.name,
                "unit": s.unit,
                "scale": s.scale,
                "rmse": rmse,
                "rmse_of_range": rmse / s.scale,
                "by_action": [state_action_map(res.view(k, j), state_bins, alpha) for j in range(len(res.actions))],
                "by_phase": phase,
            }
        )
    return out


def coverage(train_windows: np.ndarray, sim_windows: np.ndarray, seed: int = 0, sample: int = 2000) -> dict[str, Any]:
    """Share of simulated windows farther from every training window than 95% of training windows
    are from their nearest neighbour (normalised units): where the model extrapolates."""
    rng = np.random.default_rng(seed)
    tr = train_windows[rng.choice(len(train_windows), min(sample, len(train_windows)), replace=False)]
    sm = sim_windows[rng.choice(len(sim_windows), min(sample, len(sim_windows)), replace=False)]

    def nn(a: np.ndarray, b: np.ndarray, exclude_self: bool) -> np.ndarray:
        d = ((a[:, None, :] - b[None, :, :]) ** 2).sum(-1)
        if exclude_self:
            np.fill_diagonal(d, np.inf)
        return np.sqrt(d.min(axis=1))

    ref = nn(tr, tr, True)
    threshold = float(np.percentile(ref, 95))
    dist = nn(sm, tr, False)
    return {
        "threshold": threshold,
        "outside_share": float(np.mean(dist > threshold)),
        "median_distance": float(np.median(dist)),
        "train_median_distance": float(np.median(ref)),
    }


def model_windows(ckpt: Checkpoint, logs: Sequence[Log]) -> np.ndarray:
    """The model's input windows of ``logs`` (N, l*W), normalised: what :func:`coverage` compares."""
    return np.concatenate(ckpt.dataset(logs).X)[:, : ckpt.config.history * ckpt.config.row_width]


def windows_of(traces: np.ndarray, norm_encode: Any, history: int, skip: int) -> np.ndarray:
    """Flattened normalised windows (N, l*C) of simulated physical traces (R, T, C) after ``skip``."""
    z = norm_encode(traces)
    out = [z[:, t - history : t].reshape(len(z), -1) for t in range(max(history, skip), z.shape[1])]
    return np.concatenate(out, axis=0) if out else np.zeros((0, history * z.shape[2]))


def by_version(gaps: Sequence[dict[str, Any]]) -> list[dict[str, Any]]:
    """Per controller version: mean matched W1 over the goals, mean floor, the permutation test on
    that mean, and the worst goal."""
    return [
        {
            "controller": g["controller"],
            "mean_w1": g["mean_w1"],
            "mean_floor": g["mean_floor"],
            "p": g["goals_test"]["p_value"],
            "per_side": g["per_side"],
            "worst_goal": g["gaps"][0]["goal"],
            "worst_ratio": g["gaps"][0]["ratio"],
            "beyond_floor": sum(r["beyond_floor"] for r in g["gaps"]),
        }
        for g in gaps
    ]


def by_run(res: ResidualSet, names: Sequence[str]) -> list[dict[str, Any]]:
    """Per log: one-step residual RMS over the channels' ranges (and per channel, physical units),
    and its mean square over the median log's, largest first. A gap that lives in some runs only
    (a worn battery, a slippery patch) shows as a few logs far above 1."""
    ms = res.ms_by_run(len(names))
    per = {s.name: s.ms_by_run(len(names)) for s in res.states}
    med = float(np.nanmedian(ms)) or 1e-12
    rows = [
        {
            "log": names[i],
            "rms_of_range": float(np.sqrt(ms[i])),
            "rms": {k: float(np.sqrt(v[i])) for k, v in per.items()},
            "ratio": float(ms[i] / med),
        }
        for i in range(len(names))
        if np.isfinite(ms[i])
    ]
    return sorted(rows, key=lambda r: -r["ratio"])


def gap_test(gaps: Sequence[dict[str, Any]], level: float = LEVEL) -> dict[str, Any]:
    """Is there a closed-loop gap at all? Per controller version, the permutation test of "simulated
    runs are exchangeable with real ones" on the mean normalised W1 over the goals (the fair floor's
    test, :func:`~envi_py.verify.fair_reference`), Holm-corrected over the versions: a negative
    control then shows a gap in at most ``level`` of data sets, however many versions and goals.
    (The per-goal p-values rank the goals; taken together, eight goals of five versions at 5% each
    would find a gap in most negative controls.)"""
    p = [g["goals_test"]["p_value"] for g in gaps]
    adj = holm(p)
    return {
        "significant": bool(np.any(adj <= level)),
        "level": level,
        "versions": [
            {"controller": g["controller"], "p": float(q), "p_holm": float(a)} for g, q, a in zip(gaps, p, adj)
        ],
    }
