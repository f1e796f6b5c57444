"""Goal metrics of a lane-keeping run and the distances between real and simulated runs.

The paper's eight driving-quality metrics look at the colour reading against a band around the
lane centre (the controller threshold, 40). A sample above ``centre + band`` is overshoot, below
``centre - band`` undershoot, inside the band steady state. An *episode* is a maximal run of
consecutive samples in one region; its duration is its number of samples and its amplitude the
largest excursion beyond the band edge it crossed.

Defaults, from the real logs: the band is +-10 colour units (about a seventh of the 70-unit
black/white contrast). It holds the inter-quartile range of the gentlest controller (x=10: colour
quartiles 34..45, 87% of samples in band) while the harshest (x=50) spends only 13% in it, so the
metrics separate the controller versions. The first ``skip`` rows (the initial window sigma_0,
copied from the real log) are not scored: simulation did not produce them.

The verification accuracy normalises each metric by its *possible* range over T scored samples
(documented in :func:`metric_bounds`); the paper notes this is lenient (random scores ~82%), so
per-metric Wasserstein-1 and Kolmogorov-Smirnov distances are reported beside it, against the one
fair real-vs-real floor (:func:`envi_py.verify.fair_reference`).
"""

from __future__ import annotations

import math
import warnings
from dataclasses import dataclass

import numpy as np
from scipy import stats

METRIC_NAMES: tuple[str, ...] = (
    "steady_count",
    "steady_duration",
    "over_count",
    "over_amplitude",
    "over_duration",
    "under_count",
    "under_amplitude",
    "under_duration",
)


@dataclass(frozen=True)
class MetricConfig:
    """Where the lane centre and its band are, which channel is scored, how many rows to skip."""

    centre: float = 40.0
    band: float = 10.0
    skip: int = 10
    channel: int = 0
    low: float = 0.0  # valid range of the scored channel, for the metric bounds
    high: float = 100.0

    @property
    def upper(self) -> float:
        return self.centre + self.band

    @property
    def lower(self) -> float:
        return self.centre - self.band


def _episodes(mask: np.ndarray, excursion: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Per row of ``mask`` (R, T): episode count, total duration and summed per-episode max excursion."""
    r, t = mask.shape
    starts = mask & ~np.concatenate([np.zeros((r, 1), bool), mask[:, :-1]], axis=1)
    count = starts.sum(axis=1)
    duration = mask.sum(axis=1)
    ep_id = np.cumsum(starts.ravel()) - 1  # global episode index of each sample
    flat_mask = mask.ravel()
    n_ep = int(count.sum())
    ep_max = np.zeros(n_ep)
    np.maximum.at(ep_max, ep_id[flat_mask], excursion.ravel()[flat_mask])
    ep_run = np.repeat(np.arange(r), count)
    amp = np.zeros(r)
    np.add.at(amp, ep_run, ep_max)
    return count.astype(float), duration.astype(float), amp


def driving_metrics(traces: np.ndarray, cfg: MetricConfig = MetricConfig()) -> np.ndarray:
    """The eight metrics of each run. ``traces`` is (R, T) of the scored channel -> (R, 8)."""
    c = np.atleast_2d(np.asarray(traces, dtype=np.float64))[:, cfg.skip :]
    if c.shape[1] == 0:
        raise ValueError(f"runs of {c.shape[1] + cfg.skip} rows leave nothing to score after skipping {cfg.skip}")
    over, under = c > cfg.upper, c < cfg.lower
    steady = ~(over | under)
    sc, sd, _ = _episodes(steady, np.zeros_like(c))
    oc, od, oa = _episodes(over, c - cfg.upper)
    uc, ud, ua = _episodes(under, cfg.lower - c)
    return np.stack([sc, sd, oc, oa, od, uc, ua, ud], axis=1)


def metric_bounds(scored: int, cfg: MetricConfig = MetricConfig()) -> tuple[np.ndarray, np.ndarray]:
    """The possible minimum and maximum of each metric over ``scored`` samples.

    Counts: at most ceil(T/2) episodes of one region (they must alternate with another region).
    Durations: at most T. Summed amplitudes: at most ceil(T/2) episodes each reaching the range
    limit (100 - upper above, lower - 0 below). Minimum 0 for every metric.
    """
    half = math.ceil(scored / 2)
    hi = np.array(
        [half, scored, half, half * (cfg.high - cfg.upper), scored, half, half * (cfg.lower - cfg.low), scored],
        dtype=np.float64,
    )
    return np.zeros(len(METRIC_NAMES)), hi


def accuracy(real: np.ndarray, sim: np.ndarray, scored: int, cfg: MetricConfig = MetricConfig()) -> float:
    """The paper's acc = 1 - mean_phi |psi_real - psi_sim| / (max_phi - min_phi); psi is the run mean."""
    lo, hi = metric_bounds(scored, cfg)
    diff = np.abs(real.mean(axis=0) - sim.mean(axis=0)) / (hi - lo)
    return float(1.0 - diff.mean())


def safety_comfort(traces: np.ndarray, cfg: MetricConfig = MetricConfig()) -> np.ndarray:
    """The authors' later pair per run: safety = max |c - centre|, comfort = max |third difference of c|."""
    c = np.atleast_2d(np.asarray(traces, dtype=np.float64))[:, cfg.skip :]
    safety = np.abs(c - cfg.centre).max(axis=1)
    d3 = np.diff(c, n=3, axis=1)
    comfort = np.abs(d3).max(axis=1) if d3.shape[1] else np.zeros(c.shape[0])
    return np.stack([safety, comfort], axis=1)


def gaussian_kld(p: np.ndarray, q: np.ndarray, ridge: float = 1e-3) -> float:
    """KL(N_p || N_q) between Gaussian fits of two samples (rows = runs).

    ``ridge`` (in squared units) is added to both covariances: a deterministic model can produce a
    sample with zero spread in one coordinate, whose Gaussian fit is singular. NaN when either
    sample has fewer than two runs (no spread to fit), said without numpy's warnings.
    """
    if len(p) < 2 or len(q) < 2:
        return float("nan")
    k = p.shape[1]
    mp, mq = p.mean(axis=0), q.mean(axis=0)
    sp = np.atleast_2d(np.cov(p, rowvar=False)) + ridge * np.eye(k)
    sq = np.atleast_2d(np.cov(q, rowvar=False)) + ridge * np.eye(k)
    sq_inv = np.linalg.inv(sq)
    d = mq - mp
    _, logdet_p = np.linalg.slogdet(sp)
    _, logdet_q = np.linalg.slogdet(sq)
    return float(0.5 * (np.trace(sq_inv @ sp) + d @ sq_inv @ d - k + logdet_q - logdet_p))


@dataclass
class Distances:
    """Per-metric distances between two samples of runs."""

    w1: np.ndarray  # Wasserstein-1, divided by the metric's possible range
    ks: np.ndarray  # two-sample Kolmogorov-Smirnov statistic
    ks_p: np.ndarray  # its p-value
    acc: float
    kld: float  # safety/comfort Gaussian KL divergence, real || sim


def distances(real_traces: np.ndarray, sim_traces: np.ndarray, cfg: MetricConfig = MetricConfig()) -> Distances:
    """All distances between real and simulated runs of the scored channel (R, T) each."""
    scored = real_traces.shape[1] - cfg.skip
    mr, ms = driving_metrics(real_traces, cfg), driving_metrics(sim_traces, cfg)
    lo, hi = metric_bounds(scored, cfg)
    w1 = np.array([stats.wasserstein_distance(mr[:, j], ms[:, j]) for j in range(mr.shape[1])]) / (hi - lo)
    with warnings.catch_warnings():  # with ties scipy falls back from the exact to the asymptotic p-value
        warnings.simplefilter("ignore", RuntimeWarning)
        ks = [stats.ks_2samp(mr[:, j], ms[:, j]) for j in range(mr.shape[1])]
    kld = gaussian_kld(safety_comfort(real_traces, cfg), safety_comfort(sim_traces, cfg))
    return Distances(
        w1, np.array([k.statistic for k in ks]), np.array([k.pvalue for k in ks]), accuracy(mr, ms, scored, cfg), kld
    )
