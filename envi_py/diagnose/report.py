"""The diagnosis as a person reads it, written through the one report writer (:mod:`envi_py.report`):
the verdict table per version first, the verdict paragraph, then data quality, the model class, the
pictures, the candidate effects, the shrink, the gaps, the residuals, and the provenance last."""

from __future__ import annotations

from functools import partial
from pathlib import Path
from typing import Any, Mapping

import numpy as np

from ..report.document import Figure as ReportFigure
from ..report.document import Provenance, Report, Section, Table, Text
from ..effect_layers import Layer
from ..model import Checkpoint
from ..report.files import Attachment, ReportFiles, write_files
from ..report.plots import correlation_figure, png_bytes, pyplot
from ..report.stats import Correlations
from .cycles import MAX_PERIOD
from .effects import CANDIDATES, MIN_SHARE, WHAT_IF_BAR
from .gap import ratio_text, share_text
from .layers import save_layers
from .run import OTHER_WORLD_RMS, Diagnosis, another_world


def _own_bars() -> str:
    """The candidates whose share bar is not the common one, for the report's legend."""
    bars = {c.name: f"{c.min_share:.0%}" if c.min_share else "no bar" for c in CANDIDATES if c.min_share is not None}
    return ", ".join(f"{bar} for {name}" for name, bar in bars.items())


def residual_map_figure(d: Diagnosis) -> Any:
    """One heat map per state and action: the mean residual over the state's value x the action's.
    A cell with fewer than 5 residuals has no mean: it is hatched grey, never drawn as zero bias."""
    from matplotlib.patches import Rectangle

    plt = pyplot()
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


def _signal(name: str, unit: str) -> str:
    return f"{name} [{unit}]" if unit else name


def horizon_figure(d: Diagnosis) -> Any:
    """Per state, one line per controller version: the windowed gap over the real-vs-real floor
    against the step (log scale; 1 is the floor)."""
    plt = pyplot()
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


def metrics_figure(d: Diagnosis) -> Any:
    """One panel per goal, every controller version side by side: real (grey) and simulated (blue)
    runs, with the version's ratio to the floor under its name."""
    plt = pyplot()
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


def shrink_figure(d: Diagnosis) -> Any:
    """Per goal, the confirmation logs' gap before and after each fix, against the floor's band."""
    plt = pyplot()
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


def _figure(name: str, fig: Any, caption: str) -> ReportFigure:
    return ReportFigure(name, png_bytes(fig, dpi=110), caption)


def _quality_section(d: Diagnosis) -> Section:
    """Data-quality findings, before any effect: where the logs themselves are wrong."""
    if not d.quality:
        return Section(
            "Data quality",
            [
                Text(
                    "No pause in the time stamps, no repeated rows, no frozen or out-of-range reading, no session "
                    "that differs as a block, in the diagnosed or the training logs."
                )
            ],
        )
    blocks: list[Any] = [
        Table(
            ["logs", "finding", "files", "what"],
            [[q["logs"], q["kind"].replace("_", " "), str(len(q["files"])), q["what"]] for q in d.quality],
            numeric=frozenset({2}),
        )
    ]
    pauses = [(q["logs"], w) for q in d.quality if q["kind"] == "pause" for w in q["where"]]
    if pauses:
        blocks.append(
            Table(
                ["logs", "file", "time into the log [s]", "row", "pause [s]"],
                [[which, w["file"], f"{w['time_s']:.2f}", str(w["row"]), f"{w['pause_s']:.1f}"] for which, w in pauses],
                caption="Pauses in the time stamps",
                numeric=frozenset({2, 3, 4}),
            )
        )
    return Section("Data quality", blocks)


def _stage_section(d: Diagnosis) -> list[Section]:
    """The model-class check: per version and goal, simulated against real run-to-run spread."""
    if not d.stage:
        return []
    s = d.stage
    return [
        Section(
            "Model class: simulated against real run-to-run spread",
            [
                Text(
                    "Scatter of the real readings the model cannot predict: "
                    + "; ".join(f"{x['detail']} (p={x['p']:.2g}, {share_text(x['share'])})" for x in s["scatter"])
                    + "."
                ),
                Table(
                    ["controller", "goal", "sd real", "sd simulated", "ratio"],
                    [
                        [
                            r["controller"],
                            r["goal"],
                            f"{r['sd_real']:.3g}{u}",
                            f"{r['sd_sim']:.3g}{u}",
                            f"{r['ratio']:.2f}",
                        ]
                        for r in s["goals"]
                        for u in [f" {r['unit']}" if r["unit"] else ""]
                    ],
                    numeric=frozenset({2, 3, 4}),
                ),
            ],
        )
    ]


CANDIDATES_TEXT = (
    "Each one-step residual is compared with the residual of the most similar window of another run "
    "(the model's misfit cancels there, an unmodelled effect does not); every candidate is tried on every "
    "state it can act on (on every action for an actuator's play). Holm-corrected p-values; "
    "*share* is the part of those differences' mean square the effect accounts for; "
    "*what-if* is the part of the one-step residual mean square removed by feeding the model its inputs "
    "as the effect would have changed them (no retraining; it sees a misfit the pairs cannot); "
    "significant = p_holm < 0.05 and share >= {min_share:.0%} ({own}) or what-if >= {what_if:.0%}; when the "
    "logs fit significantly and at least {other:g}x worse than the model's own held-out logs (another world), "
    "the share counts beyond the share on those (*held-out*: what the model misses on its own world too); backlash, "
    "a specific memory, is also significant (and named first) when memory leads by its share and backlash "
    "explains something beyond the rows before the window."
)


def _candidates_section(d: Diagnosis) -> Section:
    counted = another_world(d.held_out)  # shares counted beyond the held-out logs'
    return Section(
        "Candidate effects",
        [
            Text(
                CANDIDATES_TEXT.format(min_share=MIN_SHARE, own=_own_bars(), what_if=WHAT_IF_BAR, other=OTHER_WORLD_RMS)
            ),
            Table(
                ["effect", "significant", "p (Holm)", "share", "held-out", "what-if", "evidence"],
                [
                    [
                        f.effect,
                        _yes(f.significant),
                        f"{f.p_holm:.2g}",
                        share_text(f.share),
                        share_text(f.held_out) if counted else "-",
                        share_text(f.what_if),
                        f.detail,
                    ]
                    for f in d.findings
                ],
                numeric=frozenset({2, 3, 4, 5}),
            ),
        ],
    )


def _shrink_cell(a: dict[str, Any]) -> str:
    """A retrained fix's shrink with its bootstrap interval; a fix that leaves the model as it is says so."""
    if a.get("unchanged"):
        return "unchanged: the model already has it"
    ci = a.get("shrink_ci")
    return f"{a['shrink']:+.0%}" + (f" ({ci[0]:+.0%} to {ci[1]:+.0%})" if ci else "")


def _yes(flag: bool) -> str:
    return "yes" if flag else "no"


def _own_cell(own: dict[str, Any] | None) -> str:
    """The model alone on its held-out logs (:func:`~.layers.own_level`), as a ratio to their floor."""
    if not own:
        return "not measured"
    if own["ratio"] is None:
        return f"floor 0 ({own['logs']} logs)"
    return f"{own['ratio']:.2f}x ({own['logs']} logs)"


def _layer_section(d: Diagnosis) -> list[Section]:
    """The leading candidate fitted as a small layer around the learnt model, confirmed elsewhere."""
    if not d.layer:
        return []
    f, c, own = d.layer["fit"], d.layer["confirm"], d.layer.get("own")
    lo, hi = c["shrink_ci"]
    return [
        Section(
            "The effect fitted where the gap is (a layer around the model)",
            [
                Text(
                    f"The leading candidate ({d.layer['candidate']}) as a parametric layer around the learnt model, "
                    f"fitted on the logs that show the gap ({f['criterion']}; the interval is a bootstrap over those "
                    "logs), then the gap measured on the confirmation logs without and with it, and set against the "
                    "model alone on its own held-out logs: a layer adds the effect, not what the model misses on its "
                    "own world. "
                    + (
                        "Saved beside the report as <model>.layers.json."
                        if layer_shown_to_help(d)
                        else "Not saved: it is the identity, or the confirmation logs do not show it shrinking the gap."
                    )
                ),
                Table(
                    [
                        "fitted layer",
                        "gap before",
                        "gap after",
                        "floor",
                        "shrink (95%)",
                        "within 1.5x the floor",
                        "model alone on its held-out logs (x their floor)",
                        "within 1.5x of that (or the floor)",
                    ],
                    [
                        [
                            f["short"],
                            f"{c['before']:.4f}",
                            f"{c['after']:.4f}",
                            f"{c['floor']:.4f}",
                            f"{c['shrink']:+.0%} ({lo:+.0%} to {hi:+.0%})",
                            _yes(c["within_1.5_floor"]),
                            _own_cell(own),
                            "-" if not own or own["within_1.5_own"] is None else _yes(own["within_1.5_own"]),
                        ]
                    ],
                    numeric=frozenset({1, 2, 3, 4}),
                ),
                *([] if f["identifiable"] else [Text(f"The fitted value is a guess: {f['text']}.")]),
            ],
        )
    ]


def _shrink_section(d: Diagnosis) -> list[Section]:
    if not d.shrink:
        return []
    s = d.shrink
    b = s["before"]
    rows = [["as trained", f"{b['mean_w1']:.4f}", f"{b['inside_floor']}/{b['n_goals']}", "-"]]
    rows += [
        [
            f"+ {a['effect']}: {a.get('train_options') or a['fix']}",
            f"{a['mean_w1']:.4f}",
            f"{a['inside_floor']}/{a['n_goals']}",
            _shrink_cell(a),
        ]
        for a in s["after"]
    ]
    return [
        Section(
            "How far the gap shrinks (confirmation logs)",
            [
                _figure(
                    "shrink",
                    shrink_figure(d),
                    "Goal gaps on the confirmation logs (normalised W1 at matched sizes), before and after each "
                    "retrained fix, against the real-vs-real floor and its 95 % range.",
                ),
                Table(
                    ["model", "mean normalised W1 (matched)", f"goals within the floor (p > {b['level']:g})", "shrink"],
                    rows,
                    numeric=frozenset({1, 2, 3}),
                ),
                Text(f"Real-vs-real floor: {b['mean_floor']:.4f}."),
            ],
        )
    ]


GAPS_TEXT = (
    "Per goal: W1 between a real half and as many simulated runs (matched), over the goal's scale; the fair "
    "floor between the two real halves (m = n_real // 2 runs per side, 10 random splits); their ratio and the "
    "range the ratio takes when simulated runs are exchangeable with real ones (95%); the permutation test's "
    "p-value (all real runs against as many simulated); and the W1 of all simulated against all real runs with "
    "a bootstrap 95% interval. Ranked: goals beyond the floor (p <= 0.05) first, each group by its ratio, "
    "largest first."
)


def _gaps_section(d: Diagnosis) -> Section:
    blocks: list[Any] = [Text(GAPS_TEXT)]
    for g in d.gaps:
        blocks.append(
            Table(
                [
                    "goal",
                    "unit",
                    "W1 sim (matched)",
                    "floor",
                    "ratio",
                    "ratio if sim were real",
                    "p",
                    "W1 all runs (95%)",
                ],
                [
                    [
                        x["goal"],
                        x["unit"] or "-",
                        f"{x['w1']:.4f}",
                        f"{x['floor']:.4f}",
                        ratio_text(x["ratio"]),
                        f"{x['ratio_null_band'][0]:.2f}..{x['ratio_null_band'][1]:.2f}",
                        f"{x['p']:.2g}",
                        f"{x['w1_all']:.4f} ({x['ci'][0]:.4f}..{x['ci'][1]:.4f})",
                    ]
                    for x in g["gaps"]
                ],
                caption=f"{g['controller']}: {g['n_real']} real runs, {g['n_sim']} simulated, {g['per_side']} per side",
                numeric=frozenset({2, 3, 4, 5, 6, 7}),
            )
        )
    blocks.extend(_cycles_table(d))
    blocks.append(
        _figure(
            "horizon",
            horizon_figure(d),
            "Gap of each state's readings over one oscillation period of the real runs (phase-blind), over the "
            "real-vs-real floor, against the step: 1 is the floor.",
        )
    )
    return Section("Where the gap lies", blocks)


def _cycles_table(d: Diagnosis) -> list[Table]:
    """Per version, how many runs settle into an exact repeating cycle, real and simulated
    (:mod:`.cycles`); none for a diagnosis without the check."""
    c = d.cycles
    if not c:
        return []
    return [
        Table(
            ["controller", "real runs", "settled, real", "settled, simulated", "periods (rows)"],
            [
                [
                    v["controller"],
                    str(v["runs"]),
                    str(v["real_settled"]),
                    str(v["sim_settled"]),
                    ", ".join(map(str, v["sim_periods"])) or "-",
                ]
                for v in c["versions"]
            ],
            caption=(
                f"Runs whose last half repeats exactly with a period of 1-{MAX_PERIOD} rows (one simulated run per "
                f"real log's initial window): {c['sim_settled']} of {c['runs']} simulated against "
                f"{c['real_settled']} of {c['runs']} real, Fisher exact p={c['p']:.2g}"
                + (" (more than the real ones)" if c["significant"] else "")
            ),
            numeric=frozenset({1, 2, 3}),
        )
    ]


def _correlation_figure(d: Diagnosis) -> list[ReportFigure]:
    if not d.correlation:
        return []
    curves = {
        (c["state"], c["action"]): Correlations(
            np.asarray(c["lags"]),
            np.asarray(c["auto"]),
            np.asarray(c["cross_lags"]),
            np.asarray(c["cross"]),
            float(c["band"]),
            int(c["n"]),
        )
        for c in d.correlation
    }
    return [correlation_figure(curves, {c["state"]: c["unit"] for c in d.correlation}, name="residual_correlation")]


def _residuals_section(d: Diagnosis) -> Section:
    units = {c["signal"]: c["unit"] for c in d.residual_map}
    blocks: list[Any] = [
        Text(
            f"{share_text(d.misfit)} of the residual mean square (in units of each state's range) is a smooth "
            "function of the window (misfit where similar windows were seen)."
        ),
        Table(
            ["state", "unit", "range", "RMSE", "RMSE / range", "misfit share"],
            [
                [
                    c["signal"],
                    c["unit"] or "-",
                    f"{c['scale']:.4g}",
                    f"{c['rmse']:.3g}",
                    f"{c['rmse_of_range']:.2%}",
                    share_text(d.misfit_by_signal.get(c["signal"], float("nan"))),
                ]
                for c in d.residual_map
            ],
            numeric=frozenset({2, 3, 4, 5}),
        ),
        _figure(
            "residual_map",
            residual_map_figure(d),
            "Mean one-step error (real - predicted) by the state's last reading and the action's last command; "
            "hatched cells hold fewer than 5 residuals.",
        ),
        *_correlation_figure(d),
    ]
    for c in d.residual_map:
        cells = [
            f"{m['action_signal']} {x['action']}, {c['signal']} {x['state'][0]:.3g}-{x['state'][1]:.3g}: "
            f"{x['bias']:+.3g}"
            for m in c["by_action"]
            for x in m["significant"][:6]
        ]
        blocks.append(
            Text(
                f"{_signal(c['signal'], c['unit'])}: cells with significant bias (Bonferroni): "
                + (", ".join(cells) or "none")
                + ". By phase of the run (bias, RMS): "
                + ", ".join(
                    f"rows {p['rows'][0]:.0f}-{p['rows'][1]:.0f}: {p['bias']:+.3g}, {p['rms']:.3g}"
                    for p in c["by_phase"]
                )
                + "."
            )
        )
    blocks.append(
        Text(
            "Logs with the largest one-step residuals (RMS over each state's range, the RMS of each state, and the "
            "mean square over the median log's): "
            + ", ".join(
                f"{r['log']} {r['rms_of_range']:.2%} ("
                + ", ".join(f"{k} {v:.3g}{' ' + units[k] if units.get(k) else ''}" for k, v in r["rms"].items())
                + f"; {r['ratio']:.1f}x)"
                for r in d.runs[:5]
            )
            + "."
        )
    )
    return Section("One-step residuals by state", blocks)


def _verdict_table(d: Diagnosis) -> Table:
    """One row per controller version: the closed-loop gap over the goals against the fair floor."""
    held = {v["controller"]: v for v in d.gap_test.get("versions", [])}
    return Table(
        [
            "controller",
            "mean W1 (matched)",
            "mean floor",
            "p",
            "p (Holm)",
            "goals beyond the floor",
            "worst goal (ratio)",
        ],
        [
            [
                v["controller"],
                f"{v['mean_w1']:.4f}",
                f"{v['mean_floor']:.4f}",
                f"{v['p']:.2g}",
                f"{held[v['controller']]['p_holm']:.2g}" if v["controller"] in held else "-",
                str(v["beyond_floor"]),
                f"{v['worst_goal']} ({ratio_text(v['worst_ratio'])})",
            ]
            for v in d.versions
        ],
        numeric=frozenset({1, 2, 3, 4, 5}),
    )


def kept_model_name(model: Path, effect: str) -> str:
    """The file a model retrained with ``effect`` (or the Gaussian refit, ``refit``) is kept under,
    beside the diagnosis: ``<model>+<effect>.pt``."""
    return f"{model.stem}+{effect.replace(' ', '_')}.pt"


def _save_model(ckpt: Checkpoint, name: str, folder: Path) -> Path:
    return ckpt.save(folder / name)


def layer_shown_to_help(d: Diagnosis) -> bool:
    """Whether the fitted layer is worth saving and suggesting: not the identity (a delay of 0 ticks),
    and the confirmation logs' shrink interval lies above 0."""
    if not d.layer:
        return False
    return not Layer.from_json(d.layer["fit"]["layer"]).identity and d.layer["confirm"]["shrink_ci"][0] > 0


def _outputs(d: Diagnosis, model: Path, kept: Mapping[str, Checkpoint]) -> list[Attachment]:
    """What the diagnosis writes besides the report: the retrained models and the fitted layer
    (``<model>.layers.json``). They go with the report, so a new diagnosis replaces the earlier
    one's as a whole (:func:`~envi_py.report.files.write_files`)."""
    out: list[Attachment] = [partial(_save_model, ckpt, kept_model_name(model, e)) for e, ckpt in kept.items()]
    if layer_shown_to_help(d):
        fit = d.layer["fit"]
        out.append(lambda folder: save_layers(folder / model.name, [fit]))
    return out


def write_diagnosis(
    d: Diagnosis, out: Path, model: Path | None = None, kept: Mapping[str, Checkpoint] | None = None
) -> ReportFiles:
    """``diagnosis.md``, ``diagnosis.html``, ``diagnosis.json`` and ``diagnosis_figures/`` in ``out``;
    ``model``: the diagnosed checkpoint, named and hashed in the provenance. With ``model``, the
    ``kept`` models (by effect, :func:`kept_model_name`) and the fitted layer go beside the report,
    named after it; without it there is nothing to name them after."""
    if kept and model is None:
        raise ValueError("the kept models are named after the diagnosed model: pass its path")
    for effect, ckpt in (kept or {}).items():  # named where it would land, not in the staging folder
        ckpt.check_finite(str(out / kept_model_name(model, effect)))  # type: ignore[arg-type]
    sections = [
        _quality_section(d),
        *_stage_section(d),
        Section(
            "Goal distributions",
            [
                _figure(
                    "metrics",
                    metrics_figure(d),
                    "Goal distributions of every version: real (grey) and simulated (blue) runs; under each "
                    "version its W1 over the real-vs-real floor.",
                )
            ],
        ),
        _candidates_section(d),
        *_shrink_section(d),
        *_layer_section(d),
        _gaps_section(d),
        _residuals_section(d),
        Section(
            "Training-data coverage and logs",
            [
                Text(
                    f"Coverage: {share_text(d.coverage['outside_share'])} of simulated windows"
                    + (
                        f" and {share_text(d.coverage['diagnosed_outside_share'])} of the diagnosed logs' own windows"
                        if np.isfinite(d.coverage.get("diagnosed_outside_share", float("nan")))
                        else ""
                    )
                    + " are farther from the training windows than 95% of training windows are from each other."
                ),
                Text("Logs used to choose the effect: " + ", ".join(d.choose_logs)),
                Text("Confirmation logs: " + ", ".join(d.confirm_logs)),
            ],
        ),
    ]
    report = Report(
        "Sim-to-real diagnosis" + (f": {d.system}" if d.system else ""),
        _verdict_table(d),
        Provenance.collect(model=model, system=d.system or None),
        [Text(d.verdict())],
        sections,
        d.to_json(),
    )
    outputs = _outputs(d, model, kept or {}) if model else []
    return write_files(report, out, "diagnosis", outputs, protect=[model] if model else [])
