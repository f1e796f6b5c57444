"""Where the closed-loop gap lies: by goal metric, by horizon, by region of state x action, by
controller version, and where simulated windows leave the region the training data covers."""

from __future__ import annotations

from typing import Any, Sequence

import numpy as np
from scipy import stats

from ..metrics import METRIC_NAMES, MetricConfig, driving_metrics, metric_bounds
from .effects import n_eff
from .residuals import Residuals


def _w1_metrics(mr: np.ndarray, ms: np.ndarray, span: np.ndarray) -> np.ndarray:
    return np.array([stats.wasserstein_distance(mr[:, j], ms[:, j]) for j in range(mr.shape[1])]) / span


def floor_ratio(value: float, floor: float) -> float:
    """``value`` over a real-vs-real floor. A floor of exactly 0 (the real runs never differ in this
    metric) makes any gap infinite and no gap 0, rather than a huge number from a tiny divisor."""
    if floor > 0:
        return value / floor
    return 0.0 if value == 0 else float("inf")


def metric_gaps(
    real: np.ndarray, sim: np.ndarray, cfg: MetricConfig, boot: int = 200, seed: int = 0
) -> list[dict[str, Any]]:
    """Per metric: normalised W1 with a bootstrap 95% interval (runs resampled on both sides), the
    real-vs-real floor (random halves), and their ratio; ranked by the ratio, largest first."""
    rng = np.random.default_rng(seed)
    mr, ms = driving_metrics(real, cfg), driving_metrics(sim, cfg)
    lo, hi = metric_bounds(real.shape[1] - cfg.skip, cfg)
    span = hi - lo
    w1 = _w1_metrics(mr, ms, span)
    bs = np.array(
        [
            _w1_metrics(mr[rng.integers(0, len(mr), len(mr))], ms[rng.integers(0, len(ms), len(ms))], span)
            for _ in range(boot)
        ]
    )
    halves = []
    for _ in range(50):
        p = rng.permutation(len(mr))
        halves.append(_w1_metrics(mr[p[: len(p) // 2]], mr[p[len(p) // 2 :]], span))
    fl = np.mean(halves, axis=0)
    rows = [
        {
            "metric": m,
            "w1": float(w1[j]),
            "ci": [float(np.percentile(bs[:, j], 2.5)), float(np.percentile(bs[:, j], 97.5))],
            "floor": float(fl[j]),
            "ratio": floor_ratio(float(w1[j]), float(fl[j])),
            "real": mr[:, j].tolist(),
            "sim": ms[:, j].tolist(),
        }
        for j, m in enumerate(METRIC_NAMES)
    ]
    return sorted(rows, key=lambda r: -r["ratio"])


def horizon_gap(real: np.ndarray, sim: np.ndarray, skip: int, seed: int = 0) -> dict[str, Any]:
    """How the gap grows with the horizon: per step the W1 between real and simulated states, the
    same between halves of the real runs, the share of simulated runs outside the real 5-95% band,
    and per simulated run the first step it leaves that band for 3 consecutive steps."""
    rng = np.random.default_rng(seed)
    t = min(real.shape[1], sim.shape[1])
    steps = np.arange(skip, t)
    w1 = np.array([stats.wasserstein_distance(real[:, k], sim[:, k]) for k in steps])
    p = rng.permutation(len(real))
    a, b = real[p[: len(p) // 2]], real[p[len(p) // 2 :]]
    fl = np.array([stats.wasserstein_distance(a[:, k], b[:, k]) for k in steps])
    lo, hi = np.percentile(real[:, steps], 5, axis=0), np.percentile(real[:, steps], 95, axis=0)
    outside = (sim[:, steps] < lo) | (sim[:, steps] > hi)
    exits = []
    for row in outside:
        run3 = np.convolve(row.astype(int), np.ones(3, int), mode="valid") == 3
        exits.append(int(np.argmax(run3)) if run3.any() else len(steps))
    return {
        "step": steps.tolist(),
        "w1": w1.tolist(),
        "floor": fl.tolist(),
        "outside_band": outside.mean(axis=0).tolist(),
        "median_exit_step": float(np.median(exits)),
        "never_exit_share": float(np.mean(np.array(exits) == len(steps))),
    }


def residual_map(res: Residuals, state_bins: int = 8, alpha: float = 0.05) -> dict[str, Any]:
    """Mean one-step residual over state x action cells, and over the phase of the run, with the
    cells whose bias is significant (t-test on the effective sample size, Bonferroni over cells)."""
    edges = np.quantile(res.state, np.linspace(0, 1, state_bins + 1))
    edges[-1] += 1e-9
    actions = np.unique(res.action)
    if len(actions) > 8:
        aedges = np.quantile(res.action, np.linspace(0, 1, 9))
        aedges[-1] += 1e-9
        a_idx = np.clip(np.searchsorted(aedges, res.action, side="right") - 1, 0, 7)
        a_labels = [f"{aedges[i]:.3g}..{aedges[i + 1]:.3g}" for i in range(8)]
    else:
        a_idx = np.searchsorted(actions, res.action)
        a_labels = [f"{a:g}" for a in actions]
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
    phase_edges = np.quantile(res.row, np.linspace(0, 1, 6))
    ph = np.clip(np.searchsorted(phase_edges, res.row, side="right") - 1, 0, 4)
    phase = [
        {
            "rows": [float(phase_edges[k]), float(phase_edges[k + 1])],
            "bias": float(res.r[ph == k].mean()),
            "sd": float(res.r[ph == k].std()),
            "rms": float(np.sqrt(np.mean(res.r[ph == k] ** 2))),
        }
        for k in range(5)
        if np.any(ph == k)
    ]
    return {
        "state_edges": edges.tolist(),
        "actions": a_labels,
        "mean": mean.tolist(),
        "count": count.tolist(),
        "significant": sorted(significant, key=lambda c: -abs(c["bias"])),
        "by_phase": phase,
        "rmse": float(np.sqrt(np.mean(res.r**2))),
    }


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


def windows_of(traces: np.ndarray, norm_encode: Any, history: int, skip: int) -> np.ndarray:
    """Flattened normalised windows (N, l*C) of simulated physical traces (R, T, C) after ``skip``."""
    z = norm_encode(traces)
    out = [z[:, t - history : t].reshape(len(z), -1) for t in range(max(history, skip), z.shape[1])]
    return np.concatenate(out, axis=0) if out else np.zeros((0, history * z.shape[2]))


def by_version(groups: Sequence[tuple[str, np.ndarray, np.ndarray]], cfg: MetricConfig) -> list[dict[str, Any]]:
    """Mean normalised W1 and its ratio to the floor for each controller version."""
    out = []
    for label, real, sim in groups:
        gaps = metric_gaps(real, sim, cfg, boot=50)
        out.append(
            {
                "controller": label,
                "mean_w1": float(np.mean([g["w1"] for g in gaps])),
                "mean_floor": float(np.mean([g["floor"] for g in gaps])),
                "worst_metric": gaps[0]["metric"],
                "worst_ratio": gaps[0]["ratio"],
            }
        )
    return out


def by_run(res: Residuals, names: Sequence[str]) -> list[dict[str, Any]]:
    """Per log: one-step residual RMS and its ratio to the median log's, largest first. A gap that
    lives in some runs only (a worn battery, a slippery patch) shows as a few logs far above 1."""
    ms = res.ms_by_run(len(names))
    med = float(np.nanmedian(ms)) or 1e-12
    rows = [
        {"log": names[i], "rms": float(np.sqrt(ms[i])), "ratio": float(ms[i] / med)}
        for i in range(len(names))
        if np.isfinite(ms[i])
    ]
    return sorted(rows, key=lambda r: -r["ratio"])
