"""The plots a control engineer expects, rendered to PNG report figures (matplotlib Agg, imported lazily).

Every plot names its signals with their units and its controller versions in titles or legends, and
stays readable for five versions: one colour per data source (real black, simulated blue), versions
side by side on a shared axis rather than stacked in one tangle.
"""

from __future__ import annotations

import io
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np

from .document import Figure
from .stats import Correlations, fit_percent
from .training import MEMBER_ERROR

REAL, SIM = "black", "tab:blue"


def pyplot() -> Any:
    """matplotlib.pyplot on the Agg backend, imported on first use (never at command-line start-up)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def png_bytes(fig: Any, dpi: int = 100) -> bytes:
    """A finished matplotlib figure as PNG bytes (the figure is closed): what a report :class:`Figure` holds."""
    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=dpi)
    pyplot().close(fig)
    return buf.getvalue()


def signal_label(name: str, unit: str = "") -> str:
    return f"{name} [{unit}]" if unit else name


@dataclass(frozen=True)
class TracePair:
    """One real log and the simulated runs started from its initial window: (T, c) arrays of its
    state channels, ``sims`` (R, T, c); ``time_s`` (T,) seconds from the log's start."""

    name: str
    time_s: np.ndarray
    real: np.ndarray
    sims: np.ndarray


@dataclass(frozen=True)
class Fit:
    log: str
    channel: str
    fit: float  # percent; of the simulated median when there are several runs
    runs: int


def simulated_centre(sims: np.ndarray) -> tuple[np.ndarray, np.ndarray | None, np.ndarray | None]:
    """The simulated trace to compare: the run itself, or for several runs of a stochastic model the
    pointwise median with its 5-95 % band."""
    if sims.shape[0] == 1:
        return sims[0], None, None
    lo, med, hi = np.percentile(sims, [5, 50, 95], axis=0)
    return med, lo, hi


def trace_fits(pairs: Sequence[TracePair], channels: Sequence[str], skip: int) -> list[Fit]:
    """MATLAB ``compare``'s fit per log and channel over the rows after the initial window (the
    window is copied from the real log, so it would flatter the fit)."""
    out = []
    for p in pairs:
        centre, _, _ = simulated_centre(p.sims)
        t = min(len(p.real), centre.shape[0])
        for j, ch in enumerate(channels):
            out.append(Fit(p.name, ch, fit_percent(p.real[skip:t, j], centre[skip:t, j]), int(p.sims.shape[0])))
    return out


def trace_overlay(
    pairs: Sequence[TracePair],
    channels: Sequence[str],
    units: Mapping[str, str],
    version: str,
    skip: int,
    name: str,
) -> Figure:
    """One column per real log, one row per state channel: the real trace, the simulated one (or the
    median and 5-95 % band of several runs) from the same initial window, the window shaded, and the
    fit in each panel's title."""
    plt = pyplot()
    fits = {(f.log, f.channel): f.fit for f in trace_fits(pairs, channels, skip)}
    rows, cols = len(channels), len(pairs)
    fig, axes = plt.subplots(rows, cols, figsize=(max(10.0, 4.0 * cols), 2.8 * rows + 0.7), squeeze=False)
    runs = int(pairs[0].sims.shape[0]) if pairs else 0
    for j_log, p in enumerate(pairs):
        centre, lo, hi = simulated_centre(p.sims)
        t = min(len(p.real), centre.shape[0])
        x = p.time_s[:t]
        for j, ch in enumerate(channels):
            ax = axes[j, j_log]
            if skip > 0:
                ax.axvspan(x[0], x[min(skip, t) - 1], color="0.92", lw=0)
            if lo is not None and hi is not None:
                ax.fill_between(x, lo[:t, j], hi[:t, j], color=SIM, alpha=0.2, lw=0, label="simulated 5-95 %")
            ax.plot(x, p.real[:t, j], color=REAL, lw=1.2, label="real")
            ax.plot(x, centre[:t, j], color=SIM, lw=1.2, label="simulated median" if lo is not None else "simulated")
            fit = fits[(p.name, ch)]
            ax.set_title(f"{p.name}: fit {fit:.1f} %" if np.isfinite(fit) else f"{p.name}: fit -", fontsize=9)
            if j_log == 0:
                ax.set_ylabel(signal_label(ch, units.get(ch, "")), fontsize=9)
            ax.tick_params(labelsize=8)
            if j == rows - 1:
                ax.set_xlabel("time [s]", fontsize=8)
    axes[0, 0].legend(fontsize=7, loc="best")
    what = f"median of {runs} runs" if runs > 1 else "one run"
    fig.suptitle(f"{version}: real vs simulated ({what}) from the same initial window (shaded)", fontsize=10)
    fig.tight_layout()
    return Figure(
        name,
        png_bytes(fig),
        f"Version {version}: real (black) and simulated ({what}, blue{', 5-95 % band' if runs > 1 else ''}) "
        "traces from each real log's initial window (shaded, copied from the log); fit as MATLAB's compare.",
    )


def correlation_figure(
    curves: Mapping[tuple[str, str], Correlations], units: Mapping[str, str] | None = None, name: str = "residuals"
) -> Figure:
    """MATLAB ``resid``: per residual channel its auto-correlation, and per (residual, input) pair
    the cross-correlation, each with the 99 % band of a white residual independent of the input."""
    plt = pyplot()
    units = units or {}
    residuals = list(dict.fromkeys(r for r, _ in curves))
    inputs = list(dict.fromkeys(u for _, u in curves))
    fig, axes = plt.subplots(
        len(residuals), 1 + len(inputs), figsize=(4.2 * (1 + len(inputs)), 2.6 * len(residuals) + 0.5), squeeze=False
    )
    for i, r in enumerate(residuals):
        first = curves[(r, inputs[0])]
        ax = axes[i, 0]
        ax.axhspan(-first.band, first.band, color="0.88", lw=0, label="99 % band")
        ax.stem(first.lags, first.auto, basefmt=" ", markerfmt=".")
        ax.set_title(f"auto-correlation of {signal_label(r, units.get(r, ''))} residual", fontsize=9)
        ax.set_xlabel("lag [steps]", fontsize=8)
        ax.legend(fontsize=7)
        for j, u in enumerate(inputs, start=1):
            c = curves.get((r, u))
            ax = axes[i, j]
            if c is None:
                ax.set_visible(False)
                continue
            ax.axhspan(-c.band, c.band, color="0.88", lw=0)
            ax.stem(c.cross_lags, c.cross, basefmt=" ", markerfmt=".")
            ax.set_title(f"residual {r} × input {signal_label(u, units.get(u, ''))}", fontsize=9)
            ax.set_xlabel("lag [steps] (positive: input leads)", fontsize=8)
    n = next(iter(curves.values())).n
    fig.suptitle(f"residual analysis (N = {n} samples, band ±2.58/√N)", fontsize=10)
    fig.tight_layout()
    return Figure(
        name,
        png_bytes(fig),
        f"Residual auto-correlation and residual–input cross-correlation over {n} samples, as MATLAB's resid. "
        "Bars outside the grey 99 % band (±2.58/√N) mean the residual still holds dynamics the model missed "
        "(left) or a dependence on the input it did not capture (right).",
    )


def metric_distributions(
    versions: Sequence[str],
    goals: Sequence[str],
    real: Mapping[str, np.ndarray],
    sim: Mapping[str, np.ndarray],
    goal_signals: Mapping[str, str],
    name: str = "metric_distributions",
) -> Figure:
    """One panel per goal metric; in each, every version side by side with a real (grey) and a
    simulated (blue) box, the number of runs in the tick label. ``real``/``sim``: version -> (R, G)."""
    plt = pyplot()
    cols = min(2, len(goals))
    rows = -(-len(goals) // cols)
    width = max(5.0, 1.0 * len(versions) + 1.0)
    fig, axes = plt.subplots(rows, cols, figsize=(width * cols, 3.1 * rows + 0.6), squeeze=False)
    pos = np.arange(len(versions), dtype=float)
    for k, (ax, goal) in enumerate(zip(axes.flat, goals)):
        r = [real[v][:, k] for v in versions]
        s = [sim[v][:, k] for v in versions]
        b1 = ax.boxplot(r, positions=pos - 0.2, widths=0.35, patch_artist=True, showfliers=True)
        b2 = ax.boxplot(s, positions=pos + 0.2, widths=0.35, patch_artist=True, showfliers=True)
        for b, colour in ((b1, "0.75"), (b2, "#9ec5e8")):
            for patch in b["boxes"]:
                patch.set_facecolor(colour)
            for med in b["medians"]:
                med.set_color("black")
        ax.set_xticks(pos, [f"{v}\n({len(real[v])} real, {len(sim[v])} sim)" for v in versions], fontsize=8)
        ax.set_title(f"{goal}\n(of {goal_signals.get(goal, '?')})", fontsize=9)
        ax.tick_params(axis="y", labelsize=8)
        if k == 0:
            ax.legend([b1["boxes"][0], b2["boxes"][0]], ["real", "simulated"], fontsize=7)
    for ax in list(axes.flat)[len(goals) :]:
        ax.set_visible(False)
    fig.suptitle("goal metrics per run, every controller version: real vs simulated", fontsize=10)
    fig.tight_layout()
    return Figure(
        name,
        png_bytes(fig),
        "Distribution of every goal metric over runs, per controller version: real (grey) beside simulated "
        "(blue); boxes span the quartiles, whiskers 1.5 IQR, the line is the median. Run counts in the labels.",
    )


def training_curves(rows: Sequence[Mapping[str, float]], title: str, name: str = "training_curves") -> Figure:
    """Each recorded training series against the epoch: the closed-loop validation error (the model
    selection's criterion, the selected epoch marked) and, when the algorithm records them, losses."""
    plt = pyplot()
    keys = [k for k in (rows[0].keys() if rows else []) if k not in ("epoch", "selected", "diverged")]
    series = {k: np.array([float(r.get(k, np.nan)) for r in rows]) for k in keys}
    series = {k: v for k, v in series.items() if np.isfinite(v).any()}
    epochs = np.array([float(r["epoch"]) for r in rows])
    members = [k for k in series if k.startswith(MEMBER_ERROR)]  # a seed ensemble's further members
    panels = [k for k in series if k == "val_error"] + [k for k in series if k != "val_error" and k not in members]
    cols = 1 if len(panels) <= 2 else 2
    rows_n = max(1, -(-len(panels) // cols))
    fig, axes = plt.subplots(
        rows_n, cols, figsize=(6.0 * cols, 2.3 * rows_n + 0.7), squeeze=False, sharex=True, layout="constrained"
    )
    for ax, k in zip(axes.flat, panels):
        ok = np.isfinite(series[k])
        member0 = "member 0" if k == "val_error" and members else None
        ax.plot(epochs[ok], series[k][ok], marker="." if k == "val_error" else None, lw=1.2, label=member0)
        ax.set_ylabel(k, fontsize=8)
        ax.tick_params(labelsize=7)
        if k == "val_error":
            ax.set_ylabel("closed-loop error\n(mean normalised W1)", fontsize=8)
            for m in members:
                ok = np.isfinite(series[m])
                ax.plot(epochs[ok], series[m][ok], lw=0.9, alpha=0.6, label=f"member {m.removeprefix(MEMBER_ERROR)}")
            chosen = [r["epoch"] for r in rows if r.get("selected")]
            bad = [(r["epoch"], r["val_error"]) for r in rows if r.get("diverged") and np.isfinite(r["val_error"])]
            if bad:
                ax.plot(*zip(*bad), "x", color="tab:red", ms=7, label="diverged in closed loop")
            if chosen:
                ax.axvline(
                    chosen[0],
                    color="tab:green",
                    ls="--",
                    lw=1,
                    label=f"selected epoch {chosen[0]:g}" + (" (member 0)" if members else ""),
                )
            if chosen or bad or members:
                ax.legend(fontsize=7)
    for ax in list(axes.flat)[len(panels) :]:
        ax.set_visible(False)
    for ax in axes.flat:
        ax.tick_params(labelbottom=True)  # a panel above an empty cell keeps its epochs
        ax.set_xlabel("epoch", fontsize=8)
    if not panels:
        axes[0, 0].text(0.5, 0.5, "no curve recorded (no validation logs)", ha="center", va="center")
    fig.suptitle(title, fontsize=10)
    return Figure(
        name,
        png_bytes(fig),
        f"Training curves of {title}. Closed-loop error: the validation logs' controllers simulated from their "
        "initial windows, the mean over the goal metrics of the Wasserstein-1 distance to the real runs over each "
        "metric's scale (the model selection's criterion); the checkpoint keeps the selected epoch. Losses appear "
        "when the algorithm records them (GAIL, BCxGAIL).",
    )


def requirement_intervals(rows: Sequence[Any], name: str = "requirements") -> Figure:
    """Per requirement, every version's estimated probability of meeting it: the simulation's point
    and interval and the real system's interval, against the required probability."""
    plt = pyplot()
    reqs = list(dict.fromkeys(r.requirement for r in rows))
    per = max(len([r for r in rows if r.requirement == q]) for q in reqs)
    fig, axes = plt.subplots(len(reqs), 1, figsize=(10, (0.45 * per + 1.1) * len(reqs) + 0.4), squeeze=False)
    for ax, req in zip(axes[:, 0], reqs):
        mine = [r for r in rows if r.requirement == req]
        y = np.arange(len(mine), dtype=float)
        for i, r in enumerate(mine):
            s, q = r.simulation, r.real_system
            ax.plot(q["interval"], [y[i] + 0.15] * 2, color=REAL, lw=4, marker="|", ms=10, solid_capstyle="butt")
            ax.plot(s["interval"], [y[i] - 0.15] * 2, color=SIM, lw=2, marker="|", ms=8)
            if s["runs"]:
                ax.plot([s["successes"] / s["runs"]], [y[i] - 0.15], "o", color=SIM, ms=4)
        ax.axvline(mine[0].p_required, color="tab:red", ls="--", lw=1)
        ax.set_yticks(y, [f"{r.version} ({r.verdict})" for r in mine], fontsize=8)
        ax.set_xlim(-0.02, 1.02)
        ax.set_ylim(len(mine) - 0.5, -0.5)
        ax.set_title(f"{req}: {mine[0].expr} (required {mine[0].p_required:g})", fontsize=9)
        ax.tick_params(axis="x", labelsize=8)
    handles = [
        plt.Line2D([], [], color=REAL, lw=4, label="real system (verdict's basis)"),
        plt.Line2D([], [], color=SIM, lw=2, marker="o", ms=4, label="simulation: estimate and interval"),
        plt.Line2D([], [], color="tab:red", ls="--", lw=1, label="required probability"),
    ]
    fig.legend(handles=handles, loc="upper center", ncol=3, fontsize=8, frameon=False)
    axes[-1, 0].set_xlabel("probability of meeting the requirement", fontsize=8)
    fig.tight_layout(rect=(0, 0, 1, 1 - 0.35 / fig.get_figheight()))
    return Figure(
        name,
        png_bytes(fig),
        "Per requirement and version: the interval for the real system (black, the verdict's basis) and the "
        "simulation's estimate and interval (blue), against the required probability (red).",
    )


def accuracy_vs_n(use_case: str, versions: Mapping[str, Any], name: str) -> Figure:
    """Verification accuracy against the number of training logs, per algorithm (mean and 95 %
    interval over repetitions) and version, with the FOT-vs-FOT floor (paper Figures 6-8)."""
    plt = pyplot()
    vs = list(versions.items())
    cols = min(3, max(len(vs), 1))
    rows = -(-max(len(vs), 1) // cols)
    fig, axes = plt.subplots(rows, cols, figsize=(4.6 * cols, 3.6 * rows + 0.4), squeeze=False)
    for ax, (label, v) in zip(axes.flat, vs):
        for a, cells in v["cells"].items():
            ns = sorted(int(n) for n in cells)
            m = np.array([_num(cells[str(n)]["acc"][0]) for n in ns]) * 100
            h = np.nan_to_num(np.array([_num(cells[str(n)]["acc"][1]) for n in ns]) * 100)  # no bar for one rep.
            ax.errorbar(ns, m, yerr=h, marker="o", capsize=3, label=a)
        if v["floor"]:
            ax.axhline(_num(v["floor"]["acc"][0]) * 100, color="k", ls="--", lw=1, label="FOT vs FOT")
        ax.set_title(f"{use_case.upper()} {label}", fontsize=9)
        ax.set_xlabel("training logs per version", fontsize=8)
        ax.set_ylabel("verification accuracy [%]", fontsize=8)
        ax.tick_params(labelsize=8)
        ax.legend(fontsize=7)
    for ax in list(axes.flat)[len(vs) :]:
        ax.set_visible(False)
    fig.tight_layout()
    return Figure(
        name,
        png_bytes(fig),
        f"{use_case.upper()}: verification accuracy against training logs per version, per algorithm and version "
        "(mean and 95 % interval over repetitions); dashed: the accuracy between two halves of the real test logs.",
    )


def _num(v: Any) -> float:
    return float("nan") if v is None else float(v)


def algorithm_traces(
    title: str,
    panels: Sequence[tuple[str, str, Sequence[Sequence[float]], Mapping[str, Sequence[Sequence[float]]]]],
    units: Mapping[str, str],
    skip: int,
    name: str,
    bands: Mapping[str, tuple[float, float]] | None = None,
) -> Figure:
    """One row per (version, state channel), one column per kept real log: the real trace (black) and
    each algorithm's simulated run from the same initial window (one colour each), with the fit of each
    in the legend. ``panels``: (version, channel, real traces, {algorithm: simulated traces}); ``bands``:
    a shaded target band per channel (the lane-keeping steady band)."""
    plt = pyplot()
    n_logs = max((len(p[2]) for p in panels), default=1)
    fig, axes = plt.subplots(
        len(panels), n_logs, figsize=(max(10.0, 4.0 * n_logs), 2.7 * len(panels) + 0.7), squeeze=False
    )
    colours = plt.rcParams["axes.prop_cycle"].by_key()["color"]
    for i, (version, ch, real, sims) in enumerate(panels):
        for k in range(n_logs):
            ax = axes[i, k]
            if k >= len(real):
                ax.set_visible(False)
                continue
            y = np.asarray(real[k], dtype=float)
            ax.axvspan(0, max(skip - 1, 0), color="0.92", lw=0)
            if bands and ch in bands:
                ax.axhspan(*bands[ch], color="tab:green", alpha=0.08, lw=0)
            ax.plot(y, color=REAL, lw=1.4, label="real")
            for c, (algo, runs) in enumerate(sims.items()):
                if k < len(runs):
                    s = np.asarray(runs[k], dtype=float)
                    t = min(len(y), len(s))
                    f = fit_percent(y[skip:t], s[skip:t]) if t > skip + 1 else float("nan")
                    fit = f"{f:.0f} %" if np.isfinite(f) else "-"
                    ax.plot(s[:t], color=colours[c % len(colours)], lw=1, label=f"{algo} (fit {fit})")
            ax.set_title(f"{version}, real log {k + 1}", fontsize=9)
            if k == 0:
                ax.set_ylabel(signal_label(ch, units.get(ch, "")), fontsize=9)
            if i == len(panels) - 1:
                ax.set_xlabel("step", fontsize=8)
            ax.tick_params(labelsize=8)
            ax.legend(fontsize=6, loc="best")
    fig.suptitle(title, fontsize=10)
    fig.tight_layout()
    return Figure(
        name,
        png_bytes(fig),
        f"{title}. Each algorithm's simulated run starts from the real log's initial window (shaded); the legend "
        "gives each run's fit after the window, as MATLAB's compare (100 = identical, 0 = the real mean).",
    )
