"""The diagnosis as a person reads it: a verdict paragraph, then pictures, then the tables."""

from __future__ import annotations

import json
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402

from ..metrics import METRIC_NAMES  # noqa: E402
from .effects import CANDIDATES, MIN_SHARE, WHAT_IF_BAR  # noqa: E402
from .run import Diagnosis  # noqa: E402


def _own_bars() -> str:
    """The candidates whose share bar is not the common one, for the report's legend."""
    return ", ".join(f"{c.min_share:.0%} for {c.name}" for c in CANDIDATES if c.min_share is not None)


def _residual_map_png(d: Diagnosis, path: Path) -> None:
    rm = d.residual_map
    mean = np.array(rm["mean"], dtype=float)
    fig, ax = plt.subplots(figsize=(7, 3.2))
    lim = np.nanmax(np.abs(mean)) if np.isfinite(mean).any() else 1.0
    im = ax.imshow(mean, aspect="auto", cmap="RdBu_r", vmin=-lim, vmax=lim)
    edges = rm["state_edges"]
    ax.set_xticks(
        range(len(edges) - 1),
        [f"{edges[i]:.0f}-{edges[i + 1]:.0f}" for i in range(len(edges) - 1)],
        rotation=30,
        fontsize=7,
    )
    ax.set_yticks(range(len(rm["actions"])), rm["actions"])
    ax.set_xlabel("state (last reading of the window)")
    ax.set_ylabel("action")
    ax.set_title("mean one-step residual (real - predicted)")
    fig.colorbar(im, ax=ax)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def _horizon_png(d: Diagnosis, path: Path) -> None:
    fig, ax = plt.subplots(figsize=(7, 3.2))
    for h in d.horizon:
        ax.plot(h["step"], h["w1"], label=f"{h['controller']} sim vs real")
        ax.plot(h["step"], h["floor"], "--", alpha=0.6, label=f"{h['controller']} real vs real")
    ax.set_xlabel("step")
    ax.set_ylabel("W1 of the state at this step")
    ax.set_title("gap vs horizon")
    ax.legend(fontsize=7)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def _metrics_png(d: Diagnosis, path: Path) -> None:
    g = d.gaps[0]
    by_name = {x["metric"]: x for x in g["gaps"]}
    fig, axes = plt.subplots(2, 4, figsize=(11, 4.5))
    for ax, name in zip(axes.ravel(), METRIC_NAMES):
        x = by_name[name]
        ax.boxplot([x["real"], x["sim"]], tick_labels=["real", "sim"])
        ax.set_title(f"{name}\nW1/floor {x['ratio']:.1f}", fontsize=8)
    fig.suptitle(f"metric distributions, {g['controller']}")
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def _shrink_png(d: Diagnosis, path: Path) -> None:
    s = d.shrink
    assert s is not None
    labels = list(METRIC_NAMES)
    x = np.arange(len(labels))
    width = 0.8 / (1 + len(s["after"]))
    fig, ax = plt.subplots(figsize=(9, 3.5))
    series = [("before", s["before"])] + [(f"+{a['effect']}", a) for a in s["after"]]
    for i, (name, summ) in enumerate(series):
        vals = [summ["metrics"][m]["w1"] for m in labels]
        lo = [summ["metrics"][m]["w1"] - summ["metrics"][m]["ci"][0] for m in labels]
        hi = [summ["metrics"][m]["ci"][1] - summ["metrics"][m]["w1"] for m in labels]
        ax.bar(x + i * width, vals, width, yerr=[np.maximum(lo, 0), np.maximum(hi, 0)], label=name, capsize=2)
    ax.plot(
        x + width * len(series) / 2 - width / 2,
        [s["before"]["metrics"][m]["floor"] for m in labels],
        "k_",
        markersize=18,
        label="real-vs-real floor",
    )
    ax.set_xticks(x + width * (len(series) - 1) / 2, labels, rotation=25, fontsize=7)
    ax.set_ylabel("normalised W1 (confirmation logs)")
    ax.legend(fontsize=7)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def write_diagnosis(d: Diagnosis, out: Path) -> Path:
    """``diagnosis.md``, ``diagnosis.json`` and the PNGs they show, in ``out``."""
    out.mkdir(parents=True, exist_ok=True)
    _residual_map_png(d, out / "residual_map.png")
    _horizon_png(d, out / "horizon.png")
    _metrics_png(d, out / "metrics.png")
    lines = [
        "# Sim-to-real diagnosis",
        "",
        d.verdict(),
        "",
        "![metric distributions](metrics.png)",
        "",
        "![gap vs horizon](horizon.png)",
        "",
        "![residual map](residual_map.png)",
        "",
        "## Candidate effects",
        "",
        "Each one-step residual is compared with the residual of the most similar window of another run "
        "(the model's misfit cancels there, an unmodelled effect does not). Holm-corrected p-values; "
        "*share* is the part of those differences' mean square the effect accounts for; "
        "*what-if* is the part of the one-step residual mean square removed by feeding the model its inputs "
        "as the effect would have changed them (no retraining; it sees a misfit the pairs cannot); "
        f"significant = p_holm < 0.05 and share >= {MIN_SHARE:.0%} ({_own_bars()}) or what-if >= "
        f"{WHAT_IF_BAR:.0%}; backlash, a specific memory, is also significant "
        "(and named first) when memory leads by its share and backlash explains something beyond the rows "
        "before the window.",
        "",
        "| effect | significant | p (Holm) | share | what-if | evidence |",
        "|---|---|---:|---:|---:|---|",
    ]
    for f in d.findings:
        lines.append(
            f"| {f.effect} | {'**yes**' if f.significant else 'no'} | {f.p_holm:.2g} | {f.share:.1%} | "
            f"{f.what_if:.1%} | {f.detail} |"
        )
    if d.shrink:
        _shrink_png(d, out / "shrink.png")
        s = d.shrink
        lines += [
            "",
            "## How far the gap shrinks (confirmation logs)",
            "",
            "![before and after](shrink.png)",
            "",
            "| model | mean normalised W1 | metrics within 1.5x floor | shrink |",
            "|---|---:|---:|---:|",
            f"| as trained | {s['before']['mean_w1']:.4f} | {s['before']['inside_floor']}/8 | - |",
        ]
        for a in s["after"]:
            lines.append(
                f"| + {a['effect']} {a['fix']} | {a['mean_w1']:.4f} | {a['inside_floor']}/8 | {a['shrink']:+.0%} |"
            )
        lines.append(f"\nReal-vs-real floor: {s['before']['mean_floor']:.4f}.")
    lines += ["", "## Where the gap lies", ""]
    for g in d.gaps:
        lines += [
            f"### {g['controller']}",
            "",
            "| metric | W1 | 95% interval | floor | ratio |",
            "|---|---:|---:|---:|---:|",
        ]
        lines += [
            f"| {x['metric']} | {x['w1']:.4f} | {x['ci'][0]:.4f}..{x['ci'][1]:.4f} | {x['floor']:.4f} | "
            f"{x['ratio']:.1f} |"
            for x in g["gaps"]
        ]
        lines.append("")
    lines += [
        "Per controller version:",
        "",
        "| controller | mean W1 | mean floor | worst metric (ratio) |",
        "|---|---:|---:|---|",
    ]
    lines += [
        f"| {v['controller']} | {v['mean_w1']:.4f} | {v['mean_floor']:.4f} | {v['worst_metric']} "
        f"({v['worst_ratio']:.1f}) |"
        for v in d.versions
    ]
    rm = d.residual_map
    lines += [
        "",
        f"One-step RMSE {rm['rmse']:.3g}; {d.misfit:.0%} of its mean square is a smooth function of the "
        f"window (misfit where similar windows were seen). Cells with significant bias (Bonferroni): "
        + (
            ", ".join(
                f"action {c['action']}, state {c['state'][0]:.0f}-{c['state'][1]:.0f}: {c['bias']:+.2f}"
                for c in rm["significant"][:6]
            )
            or "none"
        )
        + ".",
        "",
        "Logs with the largest one-step residuals (RMS, and mean square over the median log's): "
        + ", ".join(f"{r['log']} {r['rms']:.3g} ({r['ratio']:.1f}x)" for r in d.runs[:5])
        + ".",
        "",
        "By phase of the run (bias, RMS): "
        + ", ".join(
            f"rows {p['rows'][0]:.0f}-{p['rows'][1]:.0f}: {p['bias']:+.2f}, {p['rms']:.2f}" for p in rm["by_phase"]
        )
        + ".",
        "",
        f"Coverage: {d.coverage['outside_share']:.1%} of simulated windows are farther from the training "
        f"windows than 95% of training windows are from each other.",
        "",
        "Logs used to choose the effect: " + ", ".join(d.choose_logs),
        "",
        "Confirmation logs: " + ", ".join(d.confirm_logs),
    ]
    md = out / "diagnosis.md"
    md.write_text("\n".join(lines) + "\n")
    (out / "diagnosis.json").write_text(json.dumps(d.to_json(), indent=1, default=float))
    return md
