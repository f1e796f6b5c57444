"""Tables and plots of a finished grid: the paper's Tables 5-7 layout plus distances, floor and KLD.

Each cell is the mean over repetitions with a 95% Student-t interval (half-width), e.g.
``98.61 +- 0.21``. Per use case and controller version (by its label, ``x=30`` or
``kp_steer=0.8,kp_speed=18``): accuracy (%) per algorithm and n, mean normalised W1 over the
system's goals, per-goal W1 and KS, and for the lane-keeping preset the safety/comfort KLD (and its
geometric mean over versions, the authors' summary), with the FOT-vs-FOT floor of the same test
logs as the last row. The paper's published accuracies are shown beside the paper's x versions.
"""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np
from scipy import stats

from ..goals.presets import LANE_KEEPING_SIGNAL
from ..report.document import Provenance, Report, Section, Table, Text
from ..report.files import strict, write_files
from ..report.markdown import to_markdown as render_markdown
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
    runs: dict[str, dict[str, set[int]]] = {}
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
            seen_runs = runs.setdefault(label, {"real": set(), "sim": set()})
            seen_runs["real"].add(int(g["n_real"]))
            seen_runs["sim"].add(int(g["n_sim"]))
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
        "runs": {k: {side: sorted(n) for side, n in v.items()} for k, v in runs.items()},
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
                "runs": c["runs"][label],
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


def runs_text(runs: dict[str, list[int]] | None) -> str:
    """What each figure of a version rests on: its real test runs and the simulated runs against them;
    the floor compares two halves of the real runs (``n`` counts training logs, not these)."""
    if not runs:
        return "Runs per figure: not recorded (a journal of an earlier envi)."
    real = "/".join(map(str, runs["real"]))
    half = "/".join(str(n // 2) for n in runs["real"])
    return (
        f"Each figure compares {real} real test runs of this version with {'/'.join(map(str, runs['sim']))} "
        f"simulated runs (mean ± 95 % interval over repetitions); the FOT vs FOT floor compares two halves "
        f"of {half} real runs each. n is the number of training logs per version."
    )


def _version_sections(uc: str, label: str, v: dict[str, Any], algorithms: Sequence[str]) -> list[Section]:
    """Per figure (accuracy, W1, KLD) a table algorithm x n with the floor row and, for the paper's
    versions, the paper's accuracies; then the per-goal W1 / KS at the largest n."""
    algos = [a for a in algorithms if a in v["cells"]]
    ns = sorted({int(n) for a in algos for n in v["cells"][a]})
    sections: list[Section] = []
    figures = [("acc", "accuracy (%)", 100.0), ("w1", "mean normalised W1", 1.0)]
    if _has_kld(v):
        figures.append(("kld", "safety/comfort KLD", 1.0))
    numeric = frozenset(range(1, len(ns) + 1))
    for key, title, scale in figures:
        digits = 2 if key == "acc" else 4
        rows = [
            [a]
            + [
                _fmt(tuple(v["cells"][a][str(n)].get(key, NONE)), scale, digits) if str(n) in v["cells"][a] else "-"
                for n in ns
            ]
            for a in algos
        ]
        if v["floor"]:
            rows.append(["FOT vs FOT floor"] + [_fmt(tuple(v["floor"].get(key, NONE)), scale, digits)] * len(ns))
        paper = paper_accuracy(uc, label)
        if key == "acc" and paper and ns == [3, 15, 30]:
            for a, p in paper.items():
                vals = [p] * 3 if isinstance(p, float) else p
                rows.append([f"paper: {a}"] + [f"{q:.2f}" for q in vals])
        table = Table(["algorithm"] + [f"n={n}" for n in ns], rows, numeric=numeric)
        sections.append(Section(f"{uc.upper()}, {label}: {title}", [Text(runs_text(v.get("runs"))), table]))
    best_n = str(max(ns))
    rows = []
    for j, m in enumerate(v["goals"]):
        cells = [
            f"{v['cells'][a][best_n]['w1_goal'][j]:.4f} / {v['cells'][a][best_n]['ks_goal'][j]:.3f}"
            if best_n in v["cells"][a]
            else "-"
            for a in algos
        ]
        fl = f"{v['floor']['w1_goal'][j]:.4f} / {v['floor']['ks_goal'][j]:.3f}" if v["floor"] else "-"
        rows.append([m, *cells, fl])
    table = Table(
        ["goal"] + [f"{a} W1 / KS" for a in algos] + ["floor W1 / KS"],
        rows,
        numeric=frozenset(range(1, len(algos) + 2)),
    )
    sections.append(Section(f"{uc.upper()}, {label}: per-goal W1 / KS at n={best_n}", [table]))
    return sections


def _geomean_section(uc: str, s: dict[str, Any], algorithms: Sequence[str]) -> list[Section]:
    g = s["kld_geomean"]
    if not g:
        return []
    ns = sorted({int(n) for a in g for n in g[a]})
    pooled = s["kld_geomean_pooled"]
    rows = [
        [a] + [f"{_fmt(tuple(g[a][str(n)]), 1.0, 3)} [{pooled[a][str(n)]:.3f}]" if str(n) in g[a] else "-" for n in ns]
        for a in algorithms
        if a in g
    ]
    text = Text(
        "Per repetition the geometric mean over controller versions; cells give its mean ± 95% "
        "interval over repetitions and, in brackets, the geometric mean over all repetitions (the "
        "authors' figure: BCxGAIL 0.80 at n=20, about 6.5 at n=3, FOT-vs-FOT about 0.62)."
    )
    table = Table(["algorithm"] + [f"n={n}" for n in ns], rows, numeric=frozenset(range(1, len(ns) + 1)))
    return [Section(f"{uc.upper()}: geometric-mean KLD over versions (the authors' summary)", [text, table])]


def _verdict(summary: dict[str, Any], meta: dict[str, Any]) -> Table:
    """The answer first: per use case and version, each algorithm's accuracy at the largest n beside
    the FOT-vs-FOT floor of the same test logs."""
    algos = list(meta["algorithms"])
    rows = []
    for uc, s in summary.items():
        for label, v in s["versions"].items():
            ns = sorted({int(n) for a in v["cells"] for n in v["cells"][a]})
            top = str(ns[-1]) if ns else ""
            cells = [
                _fmt(tuple(v["cells"][a][top]["acc"]), 100.0, 2) if a in v["cells"] and top in v["cells"][a] else "-"
                for a in algos
            ]
            floor = _fmt(tuple(v["floor"]["acc"]), 100.0, 2) if v["floor"] else "-"
            rows.append([uc.upper(), label, top or "-", *cells, floor])
    cols = ["use case", "version", "n"] + [f"{a} acc (%)" for a in algos] + ["FOT vs FOT floor (%)"]
    return Table(cols, rows, numeric=frozenset(range(2, len(cols))))


def _intro(meta: dict[str, Any]) -> list[Text]:
    out = [
        Text(
            f"System {meta.get('system', '?')}. Protocol {meta['protocol']}, algorithms "
            f"{', '.join(meta['algorithms'])}, n = {', '.join(map(str, meta['ns']))} training logs per version, "
            f"{meta['reps']} repetitions, seed {meta['seed']}, epochs {meta['epochs']}. Cells: mean ± half-width "
            "of the 95% t-interval over repetitions. acc: the paper's verification accuracy (%) over the "
            "system's goals. W1: mean over the goals of the normalised Wasserstein-1 distance. KLD (lane "
            "keeping only): Gaussian KL of (safety, comfort), real || sim. Floor: the same between two "
            "halves of the real test logs (FOT vs FOT)."
        )
    ]
    for uc, plan in meta.get("versions", {}).items():
        out.append(Text(f"{uc.upper()}: trains on {'; '.join(plan['train'])}; verifies {'; '.join(plan['eval'])}"))
    return out


def experiment_report(
    summary: dict[str, Any], results: Sequence[dict[str, Any]], meta: dict[str, Any], figures: bool = True
) -> Report:
    """The grid's report: the verdict table, the reading guide, per use case the accuracy figure and
    the trace overlays, the tables per version, provenance last."""
    sections: list[Section] = []
    for uc, s in summary.items():
        if figures:
            sections += _figures(uc, s, results, meta)
        for label, v in s["versions"].items():
            sections += _version_sections(uc, label, v, meta["algorithms"])
        sections += _geomean_section(uc, s, meta["algorithms"])
    sections.append(
        Section(
            "Logs", [Text("Logs of every training (training, validation, test) are listed per job in `results.json`.")]
        )
    )
    title = f"ENVI experiments: {', '.join(u.upper() for u in summary)}"
    data = strict({"meta": meta, "summary": summary, "jobs": list(results)})
    return Report(
        title, _verdict(summary, meta), Provenance.collect(system=meta.get("system")), _intro(meta), sections, data
    )


def to_markdown(summary: dict[str, Any], meta: dict[str, Any]) -> str:
    """The report's tables as Markdown (no figures)."""
    return render_markdown(experiment_report(summary, [], meta, figures=False))


def _units(meta: dict[str, Any]) -> dict[str, str]:
    """Each signal's unit: the grid's ``units`` when it records them, else the shipped system's."""
    if meta.get("units"):
        return dict(meta["units"])
    try:
        from ..system import load_system

        return {c.name: c.unit for c in load_system(str(meta.get("system"))).schema.channels}
    except (ValueError, OSError):
        return {}


def _figures(uc: str, s: dict[str, Any], results: Sequence[dict[str, Any]], meta: dict[str, Any]) -> list[Section]:
    """Accuracy vs n (paper Figures 6-8) and real vs simulated traces of every state channel, each
    algorithm's run from the same initial window as the real log (first repetition, largest n)."""
    from ..report.plots import accuracy_vs_n, algorithm_traces

    blocks: list[Any] = [accuracy_vs_n(uc, s["versions"], f"accuracy_{uc}")]
    mine = [r for r in results if uc in r["evals"]]
    if mine:
        top = max(r["n"] for r in mine)
        chosen = [r for r in mine if r["rep"] == 0 and r["n"] == top]
        groups = chosen[0]["evals"][uc]["groups"]
        panels = [
            (
                g["version"],
                ch,
                g["traces"]["real"][ch],
                {r["algorithm"]: r["evals"][uc]["groups"][gi]["traces"]["sim"].get(ch, []) for r in chosen},
            )
            for gi, g in enumerate(groups)
            for ch in g["traces"]["real"]
        ]
        if panels:
            skip = int(meta.get("train_kwargs", {}).get("history", 10))
            title = f"{uc.upper()}: real vs simulated state traces (same initial windows, n={top}, rep 0)"
            band = meta.get("lane_band")
            bands = {LANE_KEEPING_SIGNAL: (float(band[0]), float(band[1]))} if band else None
            blocks.append(algorithm_traces(title, panels, _units(meta), skip, f"traces_{uc}", bands))
    return [Section(f"{uc.upper()}: figures", blocks)]


def write_report(results: Sequence[dict[str, Any]], meta: dict[str, Any], out: Path) -> Path:
    """``report.md``, ``report.html``, ``results.json`` (every job, its logs and numbers; the report's
    JSON) and the figures in ``report_figures/`` in ``out``; returns the Markdown path."""
    out.mkdir(parents=True, exist_ok=True)
    summary = summarise(results, meta["use_cases"])
    report = experiment_report(summary, results, meta)
    files = write_files(report, out, "report")
    files.json.replace(out / "results.json")
    return files.markdown
