"""Tables and plots of a finished grid: the paper's Tables 5-7 layout plus distances, floor and KLD.

Each cell is the mean over repetitions with a 95% Student-t interval (half-width), e.g.
``98.61 +- 0.21``. Per use case and controller version (by its label, ``x=30`` or
``kp_steer=0.8,kp_speed=18``): accuracy (%) per algorithm and n, mean normalised W1 over the
system's goals, per-goal W1 and KS, and for the lane-keeping preset the safety/comfort KLD (and its
geometric mean over versions, the authors' summary), with the FOT-vs-FOT floor of the same test
logs as the last row. The paper's published accuracies are shown beside the paper's x versions.
"""

from __future__ import annotations

import json
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np
from scipy import stats

from ..goals.presets import LANE_KEEPING_SIGNAL
from .versions import parse_label

#: The paper's accuracies (%), Tables 5-7, for n = 3, 15, 30 (random: one value for every n).
PAPER = {
    "tovk": {
        30: {
            "random": 82.47,
            "bc": (97.53, 97.27, 97.49),
            "gail": (96.15, 97.62, 97.83),
            "bcxgail": (98.69, 99.20, 99.30),
        }
    },
    "tmvk": {
        10: {
            "random": 69.63,
            "bc": (95.77, 96.14, 97.17),
            "gail": (96.16, 98.21, 98.52),
            "bcxgail": (97.38, 96.95, 97.47),
        },
        30: {
            "random": 82.04,
            "bc": (97.74, 97.91, 98.15),
            "gail": (96.64, 98.32, 98.59),
            "bcxgail": (98.78, 99.20, 99.33),
        },
        50: {
            "random": 80.96,
            "bc": (97.80, 97.85, 97.71),
            "gail": (97.25, 97.92, 98.80),
            "bcxgail": (98.54, 99.24, 99.34),
        },
    },
    "tmvu": {
        20: {
            "random": 79.63,
            "bc": (97.09, 96.62, 96.71),
            "gail": (97.03, 98.94, 99.21),
            "bcxgail": (98.44, 97.47, 97.51),
        },
        40: {
            "random": 81.60,
            "bc": (97.79, 98.18, 98.03),
            "gail": (96.85, 98.18, 98.73),
            "bcxgail": (98.76, 99.32, 99.53),
        },
    },
}


NONE = (float("nan"), float("nan"))  # a figure a cell does not have


def mean_ci(values: Sequence[float]) -> tuple[float, float]:
    """Mean and the half-width of its 95% t-interval (NaN for a single value: no interval)."""
    v = np.asarray(values, dtype=float)
    v = v[np.isfinite(v)]
    if len(v) == 0:
        return float("nan"), float("nan")
    if len(v) == 1:
        return float(v[0]), float("nan")
    return float(v.mean()), float(stats.t.ppf(0.975, len(v) - 1) * v.std(ddof=1) / np.sqrt(len(v)))


def geometric_mean(values: Sequence[float]) -> float:
    """exp(mean(log v)): the authors' KLD summary over versions and folds (one bad fold does not dominate)."""
    v = np.maximum(np.asarray(values, dtype=float), 1e-12)
    return float(np.exp(np.log(v).mean()))


def paper_accuracy(use_case: str, label: str) -> dict[str, Any] | None:
    """The paper's published accuracies for a version, when it is one of the paper's x versions."""
    params = parse_label(label)
    if list(params) != ["x"]:
        return None
    try:
        x = float(params["x"])
    except ValueError:
        return None
    return PAPER.get(use_case, {}).get(int(x)) if x.is_integer() else None


def _number(v: float | None) -> float:
    return float("nan") if v is None else float(v)


def _fmt(mc: tuple[float, float], scale: float = 1.0, digits: int = 2) -> str:
    m, h = (float("nan") if x is None else x for x in mc)
    if not np.isfinite(m):
        return "-"
    mean = f"{m * scale:.{digits}f}"
    return f"{mean} ± {h * scale:.{digits}f}" if np.isfinite(h) else f"{mean} (one rep.)"


def strict_json(obj: Any) -> Any:
    """``obj`` with every non-finite number as None: results.json stays standard JSON (no NaN)."""
    if isinstance(obj, float):
        return obj if np.isfinite(obj) else None
    if isinstance(obj, dict):
        return {k: strict_json(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [strict_json(v) for v in obj]
    return obj


def _cell() -> dict[str, list]:
    return {"acc": [], "w1": [], "kld": [], "w1_goal": [], "ks_goal": []}


def _add(cell: dict[str, list], d: dict[str, Any], goals: Sequence[str]) -> None:
    cell["acc"].append(d["acc"])
    cell["w1"].append(float(np.mean([d["w1"][m] for m in goals])))
    cell["kld"].append(_number(d["kld"]))
    cell["w1_goal"].append([d["w1"][m] for m in goals])
    cell["ks_goal"].append([d["ks"][m] for m in goals])


def collect(results: Sequence[dict[str, Any]], use_case: str) -> dict[str, Any]:
    """Per version label, algorithm, n: lists over repetitions of acc, mean W1, per-goal W1/KS, KLD;
    the floors; each version's goal names; and the versions in the order the grid chose them."""
    table: dict[str, dict[str, dict[int, dict[str, list]]]] = {}
    floors: dict[str, dict[str, list]] = {}
    goals: dict[str, list[str]] = {}
    geo: dict[str, dict[int, list]] = {}
    order: list[str] = []
    seen: set[tuple] = set()
    for res in results:
        ev = res["evals"].get(use_case)
        if ev is None:
            continue
        order += [v for v in res.get("versions", {}).get(use_case, []) if v not in order]
        if ev["kld_geomean"] is not None:
            geo.setdefault(res["algorithm"], {}).setdefault(res["n"], []).append(ev["kld_geomean"])
        for g in ev["groups"]:
            label = g["version"]
            names = goals.setdefault(label, list(g["goals"]))
            if names != list(g["goals"]):
                raise ValueError(
                    f"{use_case}, {label}: jobs scored different goals ({', '.join(names)} vs "
                    f"{', '.join(g['goals'])}); were they run with different system descriptions?"
                )
            cell = table.setdefault(label, {}).setdefault(res["algorithm"], {}).setdefault(res["n"], _cell())
            _add(cell, g["sim_vs_real"], names)
            floor_key = (label, tuple(ev["test_logs"]), res["rep"])
            if g["floor"] is not None and floor_key not in seen:  # one floor per distinct test set
                seen.add(floor_key)
                _add(floors.setdefault(label, _cell()), g["floor"], names)
    order += [v for v in table if v not in order]
    return {
        "table": table,
        "floor": floors,
        "goals": goals,
        "kld_geomean": geo,
        "order": [v for v in order if v in table],
    }


def _summary_cell(cell: dict[str, list]) -> dict[str, Any]:
    """Mean ± interval of acc, W1 and (where defined) KLD; mean per-goal W1 and KS. A KLD no
    repetition has (every system but lane keeping) is left out rather than written as NaN."""
    out: dict[str, Any] = {k: mean_ci(cell[k]) for k in ("acc", "w1")}
    if np.isfinite(cell["kld"]).any():
        out["kld"] = mean_ci(cell["kld"])
    return out | {
        "w1_goal": np.mean(cell["w1_goal"], axis=0).tolist(),
        "ks_goal": np.mean(cell["ks_goal"], axis=0).tolist(),
    }


def summarise(results: Sequence[dict[str, Any]], use_cases: Sequence[str]) -> dict[str, Any]:
    """JSON-able means and intervals of every cell, versions keyed by their labels."""
    out: dict[str, Any] = {}
    for uc in use_cases:
        c = collect(results, uc)
        versions = {}
        for label in c["order"]:
            versions[label] = {
                "goals": c["goals"][label],
                "cells": {
                    a: {str(n): _summary_cell(cell) | {"reps": len(cell["acc"])} for n, cell in sorted(ns.items())}
                    for a, ns in c["table"][label].items()
                },
                "floor": _summary_cell(c["floor"][label]) if label in c["floor"] else {},
            }
        out[uc] = {
            "versions": versions,
            "kld_geomean": {
                a: {str(n): mean_ci(v) for n, v in sorted(ns.items())} for a, ns in c["kld_geomean"].items()
            },
            "kld_geomean_pooled": {
                a: {str(n): geometric_mean(v) for n, v in sorted(ns.items())} for a, ns in c["kld_geomean"].items()
            },
        }
    return out


def _has_kld(v: dict[str, Any]) -> bool:
    """Whether a version has a KLD anywhere (the lane-keeping preset's safety/comfort pair)."""
    return any("kld" in cell for ns in v["cells"].values() for cell in ns.values()) or "kld" in v["floor"]


def _version_tables(uc: str, label: str, v: dict[str, Any], algorithms: Sequence[str]) -> list[str]:
    algos = [a for a in algorithms if a in v["cells"]]
    ns = sorted({int(n) for a in algos for n in v["cells"][a]})
    lines: list[str] = []
    figures = [("acc", "accuracy (%)", 100.0), ("w1", "mean normalised W1", 1.0)]
    if _has_kld(v):
        figures.append(("kld", "safety/comfort KLD", 1.0))
    for key, title, scale in figures:
        digits = 2 if key == "acc" else 4
        lines += [
            f"## {uc.upper()}, {label}: {title}",
            "",
            "| algorithm | " + " | ".join(f"n={n}" for n in ns) + " |",
            "|---|" + "---:|" * len(ns),
        ]
        for a in algos:
            cells = [
                _fmt(tuple(v["cells"][a][str(n)].get(key, NONE)), scale, digits) if str(n) in v["cells"][a] else "-"
                for n in ns
            ]
            lines.append(f"| {a} | " + " | ".join(cells) + " |")
        if v["floor"]:
            lines.append(
                "| FOT vs FOT floor | "
                + " | ".join([_fmt(tuple(v["floor"].get(key, NONE)), scale, digits)] * len(ns))
                + " |"
            )
        paper = paper_accuracy(uc, label)
        if key == "acc" and paper and ns == [3, 15, 30]:
            for a, p in paper.items():
                vals = [p] * 3 if isinstance(p, float) else p
                lines.append(f"| paper: {a} | " + " | ".join(f"{q:.2f}" for q in vals) + " |")
        lines.append("")
    best_n = str(max(ns))
    lines += [
        f"## {uc.upper()}, {label}: per-goal W1 / KS at n={best_n}",
        "",
        "| goal | " + " | ".join(f"{a} W1 / KS" for a in algos) + " | floor W1 / KS |",
        "|---|" + "---:|" * (len(algos) + 1),
    ]
    for j, m in enumerate(v["goals"]):
        cells = [
            f"{v['cells'][a][best_n]['w1_goal'][j]:.4f} / {v['cells'][a][best_n]['ks_goal'][j]:.3f}"
            if best_n in v["cells"][a]
            else "-"
            for a in algos
        ]
        fl = f"{v['floor']['w1_goal'][j]:.4f} / {v['floor']['ks_goal'][j]:.3f}" if v["floor"] else "-"
        lines.append(f"| {m} | " + " | ".join(cells) + f" | {fl} |")
    lines.append("")
    return lines


def _geomean_table(uc: str, s: dict[str, Any], algorithms: Sequence[str]) -> list[str]:
    g = s["kld_geomean"]
    if not g:
        return []
    ns = sorted({int(n) for a in g for n in g[a]})
    pooled = s["kld_geomean_pooled"]
    lines = [
        f"## {uc.upper()}: geometric-mean KLD over versions (the authors' summary)",
        "",
        (
            "Per repetition the geometric mean over controller versions; cells give its mean ± 95% "
            "interval over repetitions and, in brackets, the geometric mean over all repetitions (the "
            "authors' figure: BCxGAIL 0.80 at n=20, about 6.5 at n=3, FOT-vs-FOT about 0.62)."
        ),
        "",
        "| algorithm | " + " | ".join(f"n={n}" for n in ns) + " |",
        "|---|" + "---:|" * len(ns),
    ]
    for a in [a for a in algorithms if a in g]:
        cells = g[a]
        lines.append(
            f"| {a} | "
            + " | ".join(
                f"{_fmt(tuple(cells[str(n)]), 1.0, 3)} [{pooled[a][str(n)]:.3f}]" if str(n) in cells else "-"
                for n in ns
            )
            + " |"
        )
    lines.append("")
    return lines


def to_markdown(summary: dict[str, Any], meta: dict[str, Any]) -> str:
    lines = [
        f"# ENVI experiments: {', '.join(u.upper() for u in summary)}",
        "",
        (
            f"System {meta.get('system', '?')}. Protocol {meta['protocol']}, algorithms "
            f"{', '.join(meta['algorithms'])}, n = {', '.join(map(str, meta['ns']))} training logs per version, "
            f"{meta['reps']} repetitions, seed {meta['seed']}, epochs {meta['epochs']}. Cells: mean ± half-width "
            "of the 95% t-interval over repetitions. acc: the paper's verification accuracy (%) over the "
            "system's goals. W1: mean over the goals of the normalised Wasserstein-1 distance. KLD (lane "
            "keeping only): Gaussian KL of (safety, comfort), real || sim. Floor: the same between two "
            "halves of the real test logs (FOT vs FOT)."
        ),
        "",
    ]
    for uc, plan in meta.get("versions", {}).items():
        lines.append(f"- {uc.upper()}: trains on {'; '.join(plan['train'])}; verifies {'; '.join(plan['eval'])}")
    lines.append("")
    for uc, s in summary.items():
        for label, v in s["versions"].items():
            lines += _version_tables(uc, label, v, meta["algorithms"])
        lines += _geomean_table(uc, s, meta["algorithms"])
    lines += ["Logs of every training (training, validation, test) are listed per job in `results.json`.", ""]
    return "\n".join(lines)


def _grid(n: int, cols: int = 3) -> tuple[int, int]:
    c = min(cols, max(n, 1))
    return -(-max(n, 1) // c), c


def plot(
    summary: dict[str, Any],
    results: Sequence[dict[str, Any]],
    out: Path,
    ranges: dict[str, list[float] | None] | None = None,
    band: tuple[float, float] | None = None,
) -> list[Path]:
    """Accuracy vs n per algorithm and version (paper Figures 6-8), and real vs simulated traces of
    every state channel. ``ranges``: each state's plotted range (its valid range when finite);
    ``band``: the lane-keeping steady band (given for that preset only), shaded on its signal."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    ranges = ranges or {}
    paths = []
    for uc, s in summary.items():
        vs = list(s["versions"].items())
        rows, cols = _grid(len(vs))
        fig, axes = plt.subplots(rows, cols, figsize=(5 * cols, 4 * rows), squeeze=False)
        for ax, (label, v) in zip(axes.flat, vs):
            for a, cells in v["cells"].items():
                ns = sorted(int(n) for n in cells)
                m = np.array([cells[str(n)]["acc"][0] for n in ns]) * 100
                h = np.nan_to_num(np.array([cells[str(n)]["acc"][1] for n in ns]) * 100)  # no bar for one rep.
                ax.errorbar(ns, m, yerr=h, marker="o", capsize=3, label=a)
            if v["floor"]:
                ax.axhline(v["floor"]["acc"][0] * 100, color="k", ls="--", lw=1, label="FOT vs FOT")
            ax.set_title(f"{uc.upper()} {label}", fontsize=9)
            ax.set_xlabel("training logs per version")
            ax.set_ylabel("verification accuracy (%)")
            ax.legend(fontsize=8)
        for ax in list(axes.flat)[len(vs) :]:
            ax.set_visible(False)
        fig.tight_layout()
        p = out / f"accuracy_{uc}.png"
        fig.savefig(p, dpi=100)
        plt.close(fig)
        paths.append(p)
        p = _plot_traces(plt, uc, results, out, ranges, band)
        if p is not None:
            paths.append(p)
    return paths


def _plot_traces(
    plt: Any,
    uc: str,
    results: Sequence[dict[str, Any]],
    out: Path,
    ranges: dict[str, list[float] | None],
    band: tuple[float, float] | None,
) -> Path | None:
    """One row per (version, state channel): real traces, then each algorithm's simulated ones
    (first repetition, largest n)."""
    mine = [r for r in results if uc in r["evals"]]
    if not mine:
        return None
    top = max(r["n"] for r in mine)
    chosen = [r for r in mine if r["rep"] == 0 and r["n"] == top]
    groups = chosen[0]["evals"][uc]["groups"]
    rows = [(gi, ch) for gi, g in enumerate(groups) for ch in g["traces"]["real"]]
    # shared axes and a fixed layout: tick placement dominates the cost of a figure with many panels
    fig, axes = plt.subplots(
        len(rows),
        len(chosen) + 1,
        figsize=(3.2 * (len(chosen) + 1), 2.4 * len(rows)),
        squeeze=False,
        sharex=True,
        sharey="row",
    )
    fig.subplots_adjust(left=0.12, right=0.98, bottom=0.04, top=1 - 0.5 / len(rows), hspace=0.25, wspace=0.08)
    for ri, (gi, ch) in enumerate(rows):
        axes[ri, 0].set_ylabel(f"{groups[gi]['version']}\n{ch}", fontsize=8)
        for tr in groups[gi]["traces"]["real"][ch]:
            axes[ri, 0].plot(tr, lw=1)
        axes[ri, 0].set_title("real (FOT)" if ri == 0 else "")
        for ai, r in enumerate(chosen, start=1):
            for tr in r["evals"][uc]["groups"][gi]["traces"]["sim"].get(ch, []):
                axes[ri, ai].plot(tr, lw=1)
            axes[ri, ai].set_title(r["algorithm"] if ri == 0 else "")
        for ax in axes[ri]:
            if ranges.get(ch):
                ax.set_ylim(*ranges[ch])
            if band is not None and ch == LANE_KEEPING_SIGNAL:
                ax.axhspan(*band, color="0.9")
    fig.suptitle(f"{uc.upper()}: real vs simulated state traces (same initial windows, n={top}, rep 0)")
    p = out / f"traces_{uc}.png"
    fig.savefig(p, dpi=90)
    plt.close(fig)
    return p


def write_report(results: Sequence[dict[str, Any]], meta: dict[str, Any], out: Path) -> Path:
    """``report.md``, ``results.json`` (every job, its logs and numbers) and the PNGs in ``out``."""
    out.mkdir(parents=True, exist_ok=True)
    summary = summarise(results, meta["use_cases"])
    (out / "results.json").write_text(
        json.dumps(strict_json({"meta": meta, "summary": summary, "jobs": list(results)}), indent=1, allow_nan=False)
    )
    md = out / "report.md"
    md.write_text(to_markdown(summary, meta))
    band = meta.get("lane_band")
    plot(summary, results, out, meta.get("state_ranges"), tuple(band) if band else None)
    return md
