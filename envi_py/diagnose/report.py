"""The diagnosis as a person reads it: a verdict paragraph, then pictures, then the tables."""

from __future__ import annotations

import json
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
from matplotlib.figure import Figure  # noqa: E402
from matplotlib.patches import Rectangle  # noqa: E402
import numpy as np  # noqa: E402

from .effects import CANDIDATES, MIN_SHARE, WHAT_IF_BAR  # noqa: E402
from .gap import ratio_text, share_text  # noqa: E402
from .run import Diagnosis  # noqa: E402


def _own_bars() -> str:
    """The candidates whose share bar is not the common one, for the report's legend."""
    return ", ".join(f"{c.min_share:.0%} for {c.name}" for c in CANDIDATES if c.min_share is not None)


def residual_map_figure(d: Diagnosis) -> Figure:
    """One heat map per state and action: the mean residual over the state's value x the action's.
    A cell with fewer than 5 residuals has no mean: it is hatched grey, never drawn as zero bias."""
    maps = [(ch, m) for ch in d.residual_map for m in ch["by_action"]]
    fig, axes = plt.subplots(len(maps), 1, figsize=(7, 3.2 * len(maps)), squeeze=False)
    cmap = plt.get_cmap("RdBu_r").with_extremes(bad=(0.0, 0.0, 0.0, 0.0))  # NaN cells show the hatching
    for ax, (ch, m) in zip(axes.ravel(), maps):
        mean = np.array(m["mean"], dtype=float)
        lim = np.nanmax(np.abs(mean)) if np.isfinite(mean).any() else 1.0
        ax.add_patch(
            Rectangle(
                (-0.5, -0.5), mean.shape[1], mean.shape[0], facecolor="0.85", hatch="///", edgecolor="0.5", zorder=0
            )
        )
        im = ax.imshow(np.ma.masked_invalid(mean), aspect="auto", cmap=cmap, vmin=-lim, vmax=lim, zorder=1)
        edges = m["state_edges"]
        ax.set_xticks(
            range(len(edges) - 1),
            [f"{edges[i]:.3g}-{edges[i + 1]:.3g}" for i in range(len(edges) - 1)],
            rotation=30,
            fontsize=7,
        )
        ax.set_yticks(range(len(m["actions"])), m["actions"])
        ax.set_xlabel(f"{_signal(ch['signal'], ch['unit'])} (last reading of the window)")
        ax.set_ylabel(m["action_signal"])
        ax.set_title(f"mean one-step error of {ch['signal']} (real - predicted); hatched: < 5 residuals", fontsize=9)
        fig.colorbar(im, ax=ax, label=ch["unit"] or None)
    fig.tight_layout()
    return fig


def _save(fig: Figure, path: Path) -> None:
    fig.savefig(path, dpi=110)
    plt.close(fig)


def _signal(name: str, unit: str) -> str:
    return f"{name} [{unit}]" if unit else name


def horizon_figure(d: Diagnosis) -> Figure:
    """Per state, one line per controller version: the windowed gap over the real-vs-real floor
    against the step (log scale; 1 is the floor)."""
    signals = list(dict.fromkeys(h["signal"] for h in d.horizon))
    fig, axes = plt.subplots(len(signals), 1, figsize=(7, 3.4 * len(signals)), squeeze=False)
    for ax, sig in zip(axes.ravel(), signals):
        rows = [h for h in d.horizon if h["signal"] == sig]
        for h in rows:
            ratio = np.array(h["ratio"], dtype=float)
            shown = np.where(np.isfinite(ratio), ratio, np.nan)
            ax.plot(h["step"], shown, label=f"{h['controller']} (window {h['width']} rows)")
        ax.axhline(1.0, color="k", linestyle="--", linewidth=1, label="real-vs-real floor")
        ax.set_yscale("log")
        ax.set_xlabel("step (end of the window)")
        ax.set_ylabel("W1 sim / W1 real-vs-real")
        ax.set_title(f"gap of {sig} readings over one oscillation period, against the horizon", fontsize=9)
        ax.legend(fontsize=7, ncol=2)
    fig.tight_layout()
    return fig


def _ratio_short(ratio: float) -> str:
    return "floor 0" if ratio == float("inf") else f"{ratio:.1f}x"


def metrics_figure(d: Diagnosis) -> Figure:
    """One panel per goal, every controller version side by side: real (grey) and simulated (blue)
    runs, with the version's ratio to the floor under its name."""
    goals = [r["goal"] for r in d.gaps[0]["gaps"]]
    cols = 2 if len(d.gaps) > 2 else min(4, len(goals))
    nrows = -(-len(goals) // cols)
    width = max(2.8, 0.9 * len(d.gaps) + 1.0)
    fig, axes = plt.subplots(nrows, cols, figsize=(width * cols, 2.6 * nrows), squeeze=False)
    for ax in axes.ravel()[len(goals) :]:
        ax.axis("off")
    for ax, goal in zip(axes.ravel(), goals):
        rows = [next(r for r in g["gaps"] if r["goal"] == goal) for g in d.gaps]
        data = [v for r in rows for v in (r["real"], r["sim"])]
        pos = [3 * i + k for i in range(len(rows)) for k in (0, 1)]
        box = ax.boxplot(data, positions=pos, widths=0.8, patch_artist=True)
        for k, patch in enumerate(box["boxes"]):
            patch.set_facecolor("0.8" if k % 2 == 0 else "tab:blue")
        ax.set_xticks(
            [3 * i + 0.5 for i in range(len(rows))],
            [f"{g['controller']}\n{_ratio_short(r['ratio'])}" for g, r in zip(d.gaps, rows)],
            fontsize=7,
        )
        ax.set_title(_signal(goal, rows[0]["unit"]), fontsize=8)
    fig.suptitle("goal distributions per version: real (grey) and simulated (blue); under each: W1 / floor")
    fig.tight_layout()
    return fig


def shrink_figure(d: Diagnosis) -> Figure:
    s = d.shrink
    assert s is not None
    labels = list(s["before"]["goals"])
    x = np.arange(len(labels))
    width = 0.8 / (1 + len(s["after"]))
    fig, ax = plt.subplots(figsize=(max(6, 1.1 * len(labels)), 3.5))
    series = [("before", s["before"])] + [(f"+{a['effect']}", a) for a in s["after"]]
    for i, (name, summ) in enumerate(series):
        ax.bar(x + i * width, [summ["goals"][m]["w1"] for m in labels], width, label=name)
    before = s["before"]["goals"]
    floor = np.array([before[m]["floor"] for m in labels])
    low, high = np.array([before[m]["floor_band"] for m in labels]).T
    ax.errorbar(
        x + width * len(series) / 2 - width / 2,
        floor,
        yerr=[np.maximum(floor - low, 0), np.maximum(high - floor, 0)],
        fmt="k_",
        markersize=18,
        capsize=3,
        label="real-vs-real floor (95% range of sim if it were real)",
    )
    ax.set_xticks(x + width * (len(series) - 1) / 2, labels, rotation=25, fontsize=7)
    ax.set_ylabel("normalised W1 (matched sizes)")
    ax.set_title("goal gaps on the confirmation logs, before and after each fix")
    ax.legend(fontsize=7)
    fig.tight_layout()
    return fig


def _quality_lines(d: Diagnosis) -> list[str]:
    """Data-quality findings, before any effect: where the logs themselves are wrong."""
    lines = ["", "## Data quality", ""]
    if not d.quality:
        return lines + [
            "No pause in the time stamps, no repeated rows, no frozen or out-of-range reading, no session that "
            "differs as a block, in the diagnosed or the training logs."
        ]
    lines += ["| logs | finding | files | what |", "|---|---|---:|---|"]
    for q in d.quality:
        lines.append(f"| {q['logs']} | {q['kind'].replace('_', ' ')} | {len(q['files'])} | {q['what']} |")
    pauses = [(q["logs"], w) for q in d.quality if q["kind"] == "pause" for w in q["where"]]
    if pauses:
        lines += ["", "Pauses (file, time into the log, file row, length):", ""]
        lines += [
            f"- {which}: {w['file']} at {w['time_s']:.2f} s (row {w['row']}): {w['pause_s']:.1f} s"
            for which, w in pauses
        ]
    return lines


def _stage_lines(d: Diagnosis) -> list[str]:
    """The model-class check: per version and goal, simulated against real run-to-run spread."""
    if not d.stage:
        return []
    s = d.stage
    lines = [
        "",
        "## Model class: simulated against real run-to-run spread",
        "",
        "Scatter of the real readings the model cannot predict: "
        + "; ".join(f"{x['detail']} (p={x['p']:.2g}, {share_text(x['share'])})" for x in s["scatter"])
        + ".",
        "",
        "| controller | goal | sd real | sd simulated | ratio |",
        "|---|---|---:|---:|---:|",
    ]
    lines += [
        f"| {r['controller']} | {r['goal']} | {r['sd_real']:.3g}{unit} | {r['sd_sim']:.3g}{unit} | {r['ratio']:.2f} |"
        for r in s["goals"]
        for unit in [f" {r['unit']}" if r["unit"] else ""]
    ]
    return lines


def _gap_lines(d: Diagnosis) -> list[str]:
    lines = ["", "## Where the gap lies", ""]
    lines.append(
        "Per goal: W1 between a real half and as many simulated runs (matched), over the goal's scale; the fair "
        "floor between the two real halves (m = n_real // 2 runs per side, 10 random splits); their ratio and the "
        "range the ratio takes when simulated runs are exchangeable with real ones (95%); the permutation test's "
        "p-value (99 relabellings, all real runs against as many simulated); and the W1 of all simulated against "
        "all real runs with a bootstrap 95% interval. Ranked: goals beyond the floor (p <= 0.05) first, each group by "
        "its ratio, largest first."
    )
    lines.append("")
    for g in d.gaps:
        lines += [
            f"### {g['controller']} ({g['n_real']} real runs, {g['n_sim']} simulated, {g['per_side']} per side)",
            "",
            "| goal | unit | W1 sim (matched) | floor | ratio | ratio if sim were real | p | W1 all runs (95%) |",
            "|---|---|---:|---:|---:|---:|---:|---:|",
        ]
        lines += [
            f"| {x['goal']} | {x['unit'] or '-'} | {x['w1']:.4f} | {x['floor']:.4f} | {ratio_text(x['ratio'])} | "
            f"{x['ratio_null_band'][0]:.2f}..{x['ratio_null_band'][1]:.2f} | {x['p']:.2g} | "
            f"{x['w1_all']:.4f} ({x['ci'][0]:.4f}..{x['ci'][1]:.4f}) |"
            for x in g["gaps"]
        ]
        lines.append("")
    lines += [
        "Per controller version (mean over the goals; p: permutation test on that mean):",
        "",
        "| controller | mean W1 (matched) | mean floor | p | goals beyond the floor | worst goal (ratio) |",
        "|---|---:|---:|---:|---:|---|",
    ]
    lines += [
        f"| {v['controller']} | {v['mean_w1']:.4f} | {v['mean_floor']:.4f} | {v['p']:.2g} | {v['beyond_floor']} | "
        f"{v['worst_goal']} ({ratio_text(v['worst_ratio'])}) |"
        for v in d.versions
    ]
    return lines


def _residual_lines(d: Diagnosis) -> list[str]:
    lines = [
        "",
        "## One-step residuals by state",
        "",
        f"{share_text(d.misfit)} of the residual mean square (in units of each state's range) is a smooth function of "
        "the window (misfit where similar windows were seen).",
        "",
        "| state | unit | range | RMSE | RMSE / range | misfit share |",
        "|---|---|---:|---:|---:|---:|",
    ]
    lines += [
        f"| {c['signal']} | {c['unit'] or '-'} | {c['scale']:.4g} | {c['rmse']:.3g} | {c['rmse_of_range']:.2%} | "
        f"{share_text(d.misfit_by_signal.get(c['signal'], float('nan')))} |"
        for c in d.residual_map
    ]
    for c in d.residual_map:
        cells = [
            f"{m['action_signal']} {x['action']}, {c['signal']} {x['state'][0]:.3g}-{x['state'][1]:.3g}: "
            f"{x['bias']:+.3g}"
            for m in c["by_action"]
            for x in m["significant"][:6]
        ]
        lines += [
            "",
            f"### {_signal(c['signal'], c['unit'])}",
            "",
            "Cells with significant bias (Bonferroni): " + (", ".join(cells) or "none") + ".",
            "",
            "By phase of the run (bias, RMS): "
            + ", ".join(
                f"rows {p['rows'][0]:.0f}-{p['rows'][1]:.0f}: {p['bias']:+.3g}, {p['rms']:.3g}" for p in c["by_phase"]
            )
            + ".",
        ]
    units = {c["signal"]: c["unit"] for c in d.residual_map}
    lines += [
        "",
        "Logs with the largest one-step residuals (RMS over each state's range, the RMS of each state, and the "
        "mean square over the median log's): "
        + ", ".join(
            f"{r['log']} {r['rms_of_range']:.2%} ("
            + ", ".join(f"{k} {v:.3g}{' ' + units[k] if units.get(k) else ''}" for k, v in r["rms"].items())
            + f"; {r['ratio']:.1f}x)"
            for r in d.runs[:5]
        )
        + ".",
    ]
    return lines


def write_diagnosis(d: Diagnosis, out: Path) -> Path:
    """``diagnosis.md``, ``diagnosis.json`` and the PNGs they show, in ``out``."""
    out.mkdir(parents=True, exist_ok=True)
    _save(residual_map_figure(d), out / "residual_map.png")
    _save(horizon_figure(d), out / "horizon.png")
    _save(metrics_figure(d), out / "metrics.png")
    lines = [
        "# Sim-to-real diagnosis" + (f": {d.system}" if d.system else ""),
        "",
        d.verdict(),
        *_quality_lines(d),
        *_stage_lines(d),
        "",
        "![goal distributions](metrics.png)",
        "",
        "![gap vs horizon](horizon.png)",
        "",
        "![residual map](residual_map.png)",
        "",
        "## Candidate effects",
        "",
        "Each one-step residual is compared with the residual of the most similar window of another run "
        "(the model's misfit cancels there, an unmodelled effect does not); every candidate is tried on every "
        "state it can act on (on every action for an actuator's play). Holm-corrected p-values; "
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
            f"| {f.effect} | {'**yes**' if f.significant else 'no'} | {f.p_holm:.2g} | {share_text(f.share)} | "
            f"{share_text(f.what_if)} | {f.detail} |"
        )
    if d.shrink:
        _save(shrink_figure(d), out / "shrink.png")
        s = d.shrink
        b = s["before"]
        lines += [
            "",
            "## How far the gap shrinks (confirmation logs)",
            "",
            "![before and after](shrink.png)",
            "",
            f"| model | mean normalised W1 (matched) | goals within the floor (p > {b['level']:g}) | shrink |",
            "|---|---:|---:|---:|",
            f"| as trained | {b['mean_w1']:.4f} | {b['inside_floor']}/{b['n_goals']} | - |",
        ]
        for a in s["after"]:
            lines.append(
                f"| + {a['effect']} {a['fix']} | {a['mean_w1']:.4f} | {a['inside_floor']}/{a['n_goals']} | "
                f"{a['shrink']:+.0%} |"
            )
        lines.append(f"\nReal-vs-real floor: {b['mean_floor']:.4f}.")
    lines += _gap_lines(d)
    lines += _residual_lines(d)
    lines += [
        "",
        f"Coverage: {share_text(d.coverage['outside_share'])} of simulated windows are farther from the training "
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
