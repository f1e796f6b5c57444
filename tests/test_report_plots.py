"""The report's plots render to PNG figures with what a reader needs: units, versions, fits."""

from __future__ import annotations

import io

import numpy as np

from envi_py.report.plots import (
    TracePair,
    correlation_figure,
    metric_distributions,
    simulated_centre,
    trace_fits,
    trace_overlay,
)
from envi_py.report.stats import residual_correlations


def _size(png: bytes) -> tuple[int, int]:
    import matplotlib.image

    h, w = matplotlib.image.imread(io.BytesIO(png)).shape[:2]
    return w, h


def test_stochastic_traces_are_compared_by_their_median_and_band() -> None:
    rng = np.random.default_rng(0)
    t = np.arange(80)
    real = np.stack([np.sin(t / 5), 2 * np.cos(t / 7)], axis=1)
    sims = real[None] + rng.normal(0, 0.05, size=(9, 80, 2))
    centre, lo, hi = simulated_centre(sims)
    assert lo is not None and hi is not None and (lo <= centre).all() and (centre <= hi).all()
    pair = TracePair("log_1.csv", t * 0.04, real, sims)
    fits = trace_fits([pair], ["a", "b"], skip=10)
    assert [f.channel for f in fits] == ["a", "b"] and all(f.runs == 9 and 90 < f.fit < 100 for f in fits)
    single = trace_fits([TracePair("log_1.csv", t * 0.04, real, real[None])], ["a", "b"], skip=10)
    assert [f.fit for f in single] == [100.0, 100.0]
    fig = trace_overlay([pair], ["a", "b"], {"a": "cm", "b": ""}, "x=30", 10, "traces_x=30")
    assert fig.png.startswith(b"\x89PNG") and "median of 9 runs" in fig.caption and "x=30" in fig.caption
    w, h = _size(fig.png)
    assert w >= 900 and h > 300


def test_correlation_figure_shows_every_residual_against_every_input() -> None:
    rng = np.random.default_rng(2)
    u = rng.normal(size=500)
    curves = {(r, "angle"): residual_correlations(rng.normal(size=500), u) for r in ("color", "distance")}
    fig = correlation_figure(curves, {"color": "%", "angle": "deg"})
    assert fig.png.startswith(b"\x89PNG") and "500 samples" in fig.caption
    w, h = _size(fig.png)
    assert w > h  # two rows of two panels each, wider than tall


def test_metric_distributions_of_five_versions_fit_a_page() -> None:
    rng = np.random.default_rng(3)
    versions = [f"x={x}" for x in (10, 20, 30, 40, 50)]
    real = {v: rng.normal(size=(6, 3)) for v in versions}
    sim = {v: rng.normal(size=(12, 3)) for v in versions}
    fig = metric_distributions(versions, ["g1", "g2", "g3"], real, sim, {"g1": "color [%]"})
    w, h = _size(fig.png)
    assert fig.png.startswith(b"\x89PNG") and w <= 1400 and h > 400  # two panels a row: fits a page
