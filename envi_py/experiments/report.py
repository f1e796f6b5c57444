"""Tables and plots of a finished grid: the paper's Tables 5-7 layout plus distances, floor and KLD.

Each cell is the mean over repetitions with a 95% Student-t interval (half-width), e.g.
``98.61 +- 0.21``. Per use case and controller version: accuracy (%) per algorithm and n, mean
normalised W1 and the safety/comfort KLD (and its geometric mean over versions, the authors'
summary), with the FOT-vs-FOT floor of the same test logs as the last row.
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any, Sequence

import numpy as np
from scipy import stats

from ..metrics import METRIC_NAMES

#: The paper's accuracies (%), Tables 5-7, for n = 3, 15, 30 (random: one value for every n).
PAPER = {
    "tovk": {30: {"random": 82.47, "bc": (97.53, 97.27, 97.49), "gail": (96.15, 97.62, 97.83),
                  "bcxgail": (98.69, 99.20, 99.30)}},
    "tmvk": {10: {"random": 69.63, "bc": (95.77, 96.14, 97.17), "gail": (96.16, 98.21, 98.52),
                  "bcxgail": (97.38, 96.95, 97.47)},
             30: {"random": 82.04, "bc": (97.74, 97.91, 98.15), "gail": (96.64, 98.32, 98.59),
                  "bcxgail": (98.78, 99.20, 99.33)},
             50: {"random": 80.96, "bc": (97.80, 97.85, 97.71), "gail": (97.25, 97.92, 98.80),
                  "bcxgail": (98.54, 99.24, 99.34)}},
    "tmvu": {20: {"random": 79.63, "bc": (97.09, 96.62, 96.71), "gail": (97.03, 98.94, 99.21),
                  "bcxgail": (98.44, 97.47, 97.51)},
             40: {"random": 81.60, "bc": (97.79, 98.18, 98.03), "gail": (96.85, 98.18, 98.73),
                  "bcxgail": (98.76, 99.32, 99.53)}},
}


def mean_ci(values: Sequence[float]) -> tuple[float, float]:
    """Mean and the half-width of its 95% t-interval (0 for a single value)."""
    v = np.asarray(values, dtype=float)
    v = v[np.isfinite(v)]
    if len(v) == 0:
        return float("nan"), float("nan")
    if len(v) == 1:
        return float(v[0]), 0.0
    return float(v.mean()), float(stats.t.ppf(0.975, len(v) - 1) * v.std(ddof=1) / np.sqrt(len(v)))


def geometric_mean(values: Sequence[float]) -> float:
    """exp(mean(log v)): the authors' KLD summary over versions and folds (one bad fold does not dominate)."""
    v = np.maximum(np.asarray(values, dtype=float), 1e-12)
    return float(np.exp(np.log(v).mean()))


def _fmt(mc: tuple[float, float], scale: float = 1.0, digits: int = 2) -> str:
    m, h = mc
    return "-" if not np.isfinite(m) else f"{m * scale:.{digits}f} ± {h * scale:.{digits}f}"


def collect(results: Sequence[dict[str, Any]], use_case: str) -> dict[str, Any]:
    """Per version x, algorithm, n: lists over repetitions of acc, mean W1, per-metric W1/KS, KLD; and floors."""
    table: dict[float, dict[str, dict[int, dict[str, list]]]] = {}
    floors: dict[float, dict[str, list]] = {}
    geo: dict[str, dict[int, list]] = {}
    seen: set[tuple] = set()
    for res in results:
        ev = res["evals"].get(use_case)
        if ev is None:
            continue
        geo.setdefault(res["algorithm"], {}).setdefault(res["n"], []).append(ev["kld_geomean"])
        for g in ev["groups"]:
            cell = table.setdefault(g["x"], {}).setdefault(res["algorithm"], {}).setdefault(
                res["n"], {"acc": [], "w1": [], "kld": [], "w1_metric": [], "ks_metric": []})
            s = g["sim_vs_real"]
            cell["acc"].append(s["acc"])
            cell["w1"].append(float(np.mean(list(s["w1"].values()))))
            cell["kld"].append(s["kld"])
            cell["w1_metric"].append([s["w1"][m] for m in METRIC_NAMES])
            cell["ks_metric"].append([s["ks"][m] for m in METRIC_NAMES])
            floor_key = (g["x"], tuple(ev["test_logs"]), res["rep"])
            if g["floor"] is not None and floor_key not in seen:  # one floor per distinct test set
                seen.add(floor_key)
                fl = floors.setdefault(g["x"], {"acc": [], "w1": [], "kld": [], "w1_metric": [], "ks_metric": []})
                f = g["floor"]
                fl["acc"].append(f["acc"])
                fl["w1"].append(float(np.mean(list(f["w1"].values()))))
                fl["kld"].append(f["kld"])
                fl["w1_metric"].append([f["w1"][m] for m in METRIC_NAMES])
                fl["ks_metric"].append([f["ks"][m] for m in METRIC_NAMES])
    return {"table": table, "floor": floors, "kld_geomean": geo}


def summarise(results: Sequence[dict[str, Any]], use_cases: Sequence[str]) -> dict[str, Any]:
    """JSON-able means and intervals of every cell."""
    out: dict[str, Any] = {}
    for uc in use_cases:
        c = collect(results, uc)
        versions = {}
        for x, algos in sorted(c["table"].items()):
            versions[f"{x:g}"] = {
                "cells": {a: {str(n): {k: mean_ci(v) for k, v in cell.items() if k in ("acc", "w1", "kld")}
                              | {"w1_metric": np.mean(cell["w1_metric"], axis=0).tolist(),
                                 "ks_metric": np.mean(cell["ks_metric"], axis=0).tolist(), "reps": len(cell["acc"])}
                              for n, cell in sorted(ns.items())} for a, ns in algos.items()},
                "floor": {k: (mean_ci(v) if k in ("acc", "w1", "kld") else np.mean(v, axis=0).tolist())
                          for k, v in c["floor"].get(x, {}).items()}}
        out[uc] = {"versions": versions,
                   "kld_geomean": {a: {str(n): mean_ci(v) for n, v in sorted(ns.items())}
                                   for a, ns in c["kld_geomean"].items()},
                   "kld_geomean_pooled": {a: {str(n): geometric_mean(v) for n, v in sorted(ns.items())}
                                          for a, ns in c["kld_geomean"].items()}}
    return out


def to_markdown(summary: dict[str, Any], meta: dict[str, Any]) -> str:
    lines = [f"# ENVI experiments: {', '.join(u.upper() for u in summary)}", "",
             f"Protocol {meta['protocol']}, algorithms {', '.join(meta['algorithms'])}, n = "
             f"{', '.join(map(str, meta['ns']))} training logs per version, {meta['reps']} repetitions, seed "
             f"{meta['seed']}, epochs {meta['epochs']}. Cells: mean ± half-width of the 95% t-interval over "
             "repetitions. acc: the paper's verification accuracy (%). W1: mean over the eight metrics of the "
             "normalised Wasserstein-1 distance. KLD: Gaussian KL of (safety, comfort), real || sim. Floor: the "
             "same between two halves of the real test logs (FOT vs FOT).", ""]
    for uc, s in summary.items():
        for x, v in s["versions"].items():
            algos = [a for a in meta["algorithms"] if a in v["cells"]]
            ns = sorted({int(n) for a in algos for n in v["cells"][a]})
            for key, label, scale in (("acc", "accuracy (%)", 100.0), ("w1", "mean normalised W1", 1.0),
                                      ("kld", "safety/comfort KLD", 1.0)):
                lines += [f"## {uc.upper()}, x={x}: {label}", "",
                          "| algorithm | " + " | ".join(f"n={n}" for n in ns) + " |",
                          "|---|" + "---:|" * len(ns)]
                for a in algos:
                    cells = [_fmt(tuple(v["cells"][a][str(n)][key]), scale, 2 if key == "acc" else 4)
                             if str(n) in v["cells"][a] else "-" for n in ns]
                    lines.append(f"| {a} | " + " | ".join(cells) + " |")
                if v["floor"]:
                    lines.append("| FOT vs FOT floor | " + " | ".join([_fmt(tuple(v["floor"][key]), scale,
                                                                             2 if key == "acc" else 4)] * len(ns)) + " |")
                paper = PAPER.get(uc, {}).get(int(float(x)))
                if key == "acc" and paper and ns == [3, 15, 30]:
                    for a, p in paper.items():
                        vals = [p] * 3 if isinstance(p, float) else p
                        lines.append(f"| paper: {a} | " + " | ".join(f"{q:.2f}" for q in vals) + " |")
                lines.append("")
            best_n = str(max(ns))
            lines += [f"## {uc.upper()}, x={x}: per-metric W1 / KS at n={best_n}", "",
                      "| metric | " + " | ".join(f"{a} W1 / KS" for a in algos) + " | floor W1 / KS |",
                      "|---|" + "---:|" * (len(algos) + 1)]
            for j, m in enumerate(METRIC_NAMES):
                cells = [f"{v['cells'][a][best_n]['w1_metric'][j]:.4f} / {v['cells'][a][best_n]['ks_metric'][j]:.3f}"
                         if best_n in v["cells"][a] else "-" for a in algos]
                fl = (f"{v['floor']['w1_metric'][j]:.4f} / {v['floor']['ks_metric'][j]:.3f}" if v["floor"] else "-")
                lines.append(f"| {m} | " + " | ".join(cells) + f" | {fl} |")
            lines.append("")
        g = s["kld_geomean"]
        ns = sorted({int(n) for a in g for n in g[a]})
        pooled = s["kld_geomean_pooled"]
        lines += [f"## {uc.upper()}: geometric-mean KLD over versions (the authors' summary)", "",
                  "Per repetition the geometric mean over controller versions; cells give its mean ± 95% "
                  "interval over repetitions and, in brackets, the geometric mean over all repetitions (the "
                  "authors' figure: BCxGAIL 0.80 at n=20, about 6.5 at n=3, FOT-vs-FOT about 0.62).", "",
                  "| algorithm | " + " | ".join(f"n={n}" for n in ns) + " |", "|---|" + "---:|" * len(ns)]
        for a in [a for a in meta["algorithms"] if a in g]:
            cells = g[a]
            lines.append(f"| {a} | " + " | ".join(f"{_fmt(tuple(cells[str(n)]), 1.0, 3)} [{pooled[a][str(n)]:.3f}]"
                                                   if str(n) in cells else "-" for n in ns) + " |")
        lines.append("")
    lines += ["Logs of every training (training, validation, test) are listed per job in `results.json`.", ""]
    return "\n".join(lines)


def plot(summary: dict[str, Any], results: Sequence[dict[str, Any]], out: Path) -> list[Path]:
    """Accuracy vs n per algorithm (paper Figures 6-8) and real vs simulated traces."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    paths = []
    for uc, s in summary.items():
        vs = list(s["versions"].items())
        fig, axes = plt.subplots(1, len(vs), figsize=(5 * len(vs), 4), squeeze=False)
        for ax, (x, v) in zip(axes[0], vs):
            for a, cells in v["cells"].items():
                ns = sorted(int(n) for n in cells)
                m = np.array([cells[str(n)]["acc"][0] for n in ns]) * 100
                h = np.array([cells[str(n)]["acc"][1] for n in ns]) * 100
                ax.errorbar(ns, m, yerr=h, marker="o", capsize=3, label=a)
            if v["floor"]:
                ax.axhline(v["floor"]["acc"][0] * 100, color="k", ls="--", lw=1, label="FOT vs FOT")
            ax.set_title(f"{uc.upper()} x={x}")
            ax.set_xlabel("training logs per version")
            ax.set_ylabel("verification accuracy (%)")
            ax.legend(fontsize=8)
        fig.tight_layout()
        p = out / f"accuracy_{uc}.png"
        fig.savefig(p, dpi=100)
        plt.close(fig)
        paths.append(p)
        # traces: first repetition, largest n, each algorithm
        top = max(r["n"] for r in results)
        chosen = [r for r in results if r["rep"] == 0 and r["n"] == top and uc in r["evals"]]
        if not chosen:
            continue
        groups = chosen[0]["evals"][uc]["groups"]
        fig, axes = plt.subplots(len(groups), len(chosen) + 1, figsize=(3.2 * (len(chosen) + 1), 2.4 * len(groups)),
                                 squeeze=False)
        for gi, g in enumerate(groups):
            axes[gi, 0].set_ylabel(f"x={g['x']:g}: colour")
            for tr in g["traces"]["real"]:
                axes[gi, 0].plot(tr, lw=1)
            axes[gi, 0].set_title("real (FOT)" if gi == 0 else "")
            for ai, r in enumerate(chosen, start=1):
                for tr in r["evals"][uc]["groups"][gi]["traces"]["sim"]:
                    axes[gi, ai].plot(tr, lw=1)
                axes[gi, ai].set_title(r["algorithm"] if gi == 0 else "")
            for ax in axes[gi]:
                ax.set_ylim(0, 100)
                ax.axhspan(30, 50, color="0.9")
        fig.suptitle(f"{uc.upper()}: real vs simulated colour traces (same initial windows, n={top}, rep 0)")
        fig.tight_layout()
        p = out / f"traces_{uc}.png"
        fig.savefig(p, dpi=90)
        plt.close(fig)
        paths.append(p)
    return paths


def write_report(results: Sequence[dict[str, Any]], meta: dict[str, Any], out: Path) -> Path:
    """``report.md``, ``results.json`` (every job, its logs and numbers) and the PNGs in ``out``."""
    out.mkdir(parents=True, exist_ok=True)
    summary = summarise(results, meta["use_cases"])
    (out / "results.json").write_text(json.dumps({"meta": meta, "summary": summary, "jobs": list(results)}, indent=1))
    md = out / "report.md"
    md.write_text(to_markdown(summary, meta))
    plot(summary, results, out)
    return md
