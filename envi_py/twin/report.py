"""How well a twin profile matches the real logs: per controller version, real vs twin distributions of
the goal metrics and oscillation statistics, their distances and the real-vs-real floor.

The floor is the project's one fair reference (:func:`envi_py.verify.fair_reference`): two halves of
the real runs against each other, and a real half against as many twin runs, over the same random
halvings, so the twin is compared with reality at the size reality is compared with itself.
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import numpy as np

from envi_py.logs import Log
from envi_py.metrics import METRIC_NAMES, MetricConfig, driving_metrics, metric_bounds, safety_comfort
from envi_py.verify import fair_reference

from ..atomic import atomic_write_text
from .calibrate import STAT_NAMES, run_stats, targets, twin_color
from .profile import TwinProfile

SPLITS = 20


def fit_summary(
    profile: TwinProfile, logs: list[Log], key: str = "x", cfg: MetricConfig = MetricConfig(), seed: int = 12345
) -> tuple[dict[str, Any], dict[Any, tuple[np.ndarray, np.ndarray]]]:
    """Per version: metric and statistic distributions, distances at matched sizes, floor and their ratios."""
    out: dict[str, Any] = {
        "seed": seed,
        "splits": SPLITS,
        "metric_config": vars(cfg) if hasattr(cfg, "__dict__") else {},
        "versions": {},
    }
    traces = {}
    for i, t in enumerate(targets(logs, key, cfg)):
        value = t.spec.params.get(key)
        n, length = t.color.shape
        if n < 4:
            raise ValueError(f"{key}={value}: the real-vs-real floor needs at least 4 real runs, got {n}")
        pool = twin_color(profile, t.spec, (n // 2) * SPLITS, length, seed + i)
        mr, mt = driving_metrics(t.color, cfg), driving_metrics(pool, cfg)
        low, high = metric_bounds(length - cfg.skip, cfg)
        fl, d, _ = fair_reference(
            mr,
            mt,
            np.maximum(high - low, 1e-12),
            safety_comfort(t.color, cfg),
            safety_comfort(pool, cfg),
            seed + i,
            repetitions=SPLITS,
            permutations=1,
        )
        sr, st = run_stats(t.color[:, cfg.skip :], cfg.centre), run_stats(pool[:, cfg.skip :], cfg.centre)
        ratio = d.w1 / np.maximum(fl.w1, 1e-9)
        out["versions"][str(value)] = {
            "runs_real": int(n),
            "runs_twin": int(pool.shape[0]),
            "metrics": {
                m: {
                    "real_mean": float(mr[:, j].mean()),
                    "real_sd": float(mr[:, j].std()),
                    "twin_mean": float(mt[:, j].mean()),
                    "twin_sd": float(mt[:, j].std()),
                    "w1_twin": float(d.w1[j]),
                    "w1_floor": float(fl.w1[j]),
                    "w1_ratio": float(ratio[j]),
                    "ks_twin": float(d.ks[j]),
                    "ks_floor": float(fl.ks[j]),
                }
                for j, m in enumerate(METRIC_NAMES)
            },
            "stats": {
                s: {"real": float(sr[:, j].mean()), "twin": float(st[:, j].mean())} for j, s in enumerate(STAT_NAMES)
            },
            "acc_twin": d.acc,
            "acc_floor": fl.acc,
            "kld_twin": d.kld,
            "kld_floor": fl.kld,
            "within_2x": int((ratio <= 2).sum()),
        }
        traces[value] = (t.color, pool)
    return out, traces


def to_markdown(summary: dict[str, Any], profile: TwinProfile) -> str:
    lines = [
        "# Twin calibration report",
        "",
        "Twin vs real: W1 of each goal metric (divided by its possible range) between a random half of the",
        f"real runs and as many twin runs, averaged over {summary['splits']} halvings; floor: the same between",
        "two real halves. ratio = twin / floor (1 = as close as reality to itself; aim <= 2).",
        "",
        "## Profile",
        "",
        "```json",
        json.dumps({k: v for k, v in profile.to_json().items() if k != "fit"}, indent=1),
        "```",
        "",
    ]
    for x, v in summary["versions"].items():
        s = v["stats"]
        lines += [
            f"## x = {x}  ({v['runs_real']} real runs, {v['within_2x']}/8 metrics within 2x floor)",
            "",
            f"oscillation period {s['period']['real']:.2f} real / {s['period']['twin']:.2f} twin ticks; "
            f"amplitude {s['amplitude']['real']:.1f} / {s['amplitude']['twin']:.1f}; colour mean "
            f"{s['colour_mean']['real']:.1f} / {s['colour_mean']['twin']:.1f}, sd {s['colour_sd']['real']:.1f} / "
            f"{s['colour_sd']['twin']:.1f}; accuracy twin {v['acc_twin']:.3f} floor {v['acc_floor']:.3f}; "
            f"KLD twin {v['kld_twin']:.2f} floor {v['kld_floor']:.2f}",
            "",
            "| metric | real mean±sd | twin mean±sd | W1 twin | W1 floor | ratio | KS twin | KS floor |",
            "|---|---|---|---|---|---|---|---|",
        ]
        for m, r in v["metrics"].items():
            lines.append(
                f"| {m} | {r['real_mean']:.1f}±{r['real_sd']:.1f} | {r['twin_mean']:.1f}±{r['twin_sd']:.1f} | "
                f"{r['w1_twin']:.4f} | {r['w1_floor']:.4f} | {r['w1_ratio']:.2f} | {r['ks_twin']:.2f} | "
                f"{r['ks_floor']:.2f} |"
            )
        lines.append("")
    return "\n".join(lines)


def plot(traces: dict[Any, tuple[np.ndarray, np.ndarray]], path: Path, show: int = 60) -> None:
    """Per version: two real and two twin colour traces, and the colour histograms."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(
        len(traces), 2, figsize=(12, 2.2 * len(traces)), squeeze=False, gridspec_kw={"width_ratios": [3, 1]}
    )
    for row, (x, (real, twin)) in enumerate(traces.items()):
        ax = axes[row, 0]
        for k in range(2):
            ax.plot(real[k, :show], color="k", lw=1, alpha=0.8, label="real" if k == 0 else None)
            ax.plot(twin[k, :show], color="tab:red", lw=1, alpha=0.8, label="twin" if k == 0 else None)
        ax.axhline(40, color="gray", lw=0.5)
        ax.set_ylim(0, 100)
        ax.set_ylabel(f"x={x}\ncolour")
        ax.legend(loc="upper right", fontsize=7)
        bins = np.arange(0, 101, 4)
        axes[row, 1].hist(real.ravel(), bins, density=True, color="k", alpha=0.5, label="real")
        axes[row, 1].hist(twin.ravel(), bins, density=True, color="tab:red", alpha=0.5, label="twin")
    axes[-1, 0].set_xlabel("tick")
    axes[-1, 1].set_xlabel("colour")
    fig.tight_layout()
    fig.savefig(path, dpi=80)
    plt.close(fig)


def write_report(
    profile: TwinProfile,
    logs: list[Log],
    out_dir: Path,
    key: str = "x",
    cfg: MetricConfig = MetricConfig(),
    seed: int = 12345,
) -> dict[str, Any]:
    """Write report.md, report.json and traces.png; return the summary."""
    out_dir.mkdir(parents=True, exist_ok=True)
    summary, traces = fit_summary(profile, logs, key, cfg, seed)
    atomic_write_text(out_dir / "report.json", json.dumps(summary, indent=1) + "\n")
    atomic_write_text(out_dir / "report.md", to_markdown(summary, profile) + "\n")
    plot(traces, out_dir / "traces.png")
    return summary


def headline(summary: dict[str, Any]) -> dict[str, dict[str, float]]:
    """The compact figure stored in the profile and re-checked by the tests."""
    return {
        x: {
            "median_w1_ratio": float(np.median([m["w1_ratio"] for m in v["metrics"].values()])),
            "within_2x": v["within_2x"],
            "period_twin": v["stats"]["period"]["twin"],
            "amplitude_twin": v["stats"]["amplitude"]["twin"],
        }
        for x, v in summary["versions"].items()
    }


def write_calibration(
    profile: TwinProfile, logs: list[Log], out_dir: Path, key: str = "x", cfg: MetricConfig = MetricConfig()
) -> tuple[TwinProfile, dict[str, Any]]:
    """Report on a fitted profile and save it as ``profile.json`` with its headline fit attached."""
    summary = write_report(profile, logs, out_dir, key, cfg)
    fitted = profile.replace(fit={"seed": summary["seed"], "key": key, "headline": headline(summary)})
    fitted.save(out_dir / "profile.json")
    return fitted, summary
