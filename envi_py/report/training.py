"""Training curves of a finished model: a CSV, a report page and, on request, TensorBoard scalars.

What is read (read-only) is what the trainers store: every algorithm's closed-loop validation error
per evaluated epoch and the selected epoch (``record.selection``: ``curve``, ``best_epoch``,
``diverged_epochs``); GAIL and BCxGAIL also write per-epoch losses to a ``curves.csv`` when asked for
a curves folder (:func:`envi_py.train.gail.write_curves`), merged here when present. BC stores no
per-epoch loss, so its page shows the validation curve only.
"""

from __future__ import annotations

import csv
import io
import math
from collections.abc import Sequence
from pathlib import Path
from typing import Any

from ..atomic import atomic_write_text
from .document import Provenance, Report, Section, Table, Text
from .files import ReportFiles, write_files

TENSORBOARD_HINT = "pip install 'envi[tensorboard]'"


#: the column prefix of a seed ensemble's further members' validation errors (member 0's is ``val_error``)
MEMBER_ERROR = "val_error_member"


def curve_rows(selection: dict[str, Any], losses: Sequence[dict[str, Any]] = ()) -> list[dict[str, float]]:
    """One row per epoch that has a number: ``epoch``, ``val_error`` (closed-loop mean normalised W1,
    NaN where not evaluated), ``selected`` (1 at the kept epoch), ``diverged`` (1 where the simulated
    runs left the real runs' range), and any loss columns of ``losses``. A seed ensemble's selection
    (``members``) adds ``val_error_member<k>`` for members 1.. : each member is selected on its own
    curve, and a member that stopped early or diverged must show, not only member 0."""
    rows: dict[int, dict[str, float]] = {}
    for r in losses:
        e = int(float(r["epoch"]))
        rows[e] = {k: float(v) if v not in ("", None) else math.nan for k, v in r.items() if k != "val_error"}
        rows[e]["epoch"] = float(e)
    for e, err in selection.get("curve", []):
        rows.setdefault(int(e), {"epoch": float(e)})["val_error"] = float(err)
    further = selection.get("members", [])[1:]
    for k, member in enumerate(further, start=1):
        for e, err in member.get("curve", []):
            rows.setdefault(int(e), {"epoch": float(e)})[f"{MEMBER_ERROR}{k}"] = float(err)
    best, diverged = selection.get("best_epoch"), set(selection.get("diverged_epochs", []))
    out = []
    for e in sorted(rows):
        r = {
            "epoch": float(e),
            "val_error": math.nan,
            **{f"{MEMBER_ERROR}{k}": math.nan for k in range(1, len(further) + 1)},
        }
        r.update(rows[e])
        r["selected"] = 1.0 if best is not None and e == best else 0.0
        r["diverged"] = 1.0 if e in diverged else 0.0
        out.append(r)
    return out


def fitted_step_noise(selection: dict[str, Any]) -> str:
    """The step-noise shape a model's fit chose, per state (``state: shape``), "-" when none was fitted
    (normal draws asked for, or a deterministic head). Records written before the two-scale family
    hold degrees of freedom only."""
    fit = selection.get("step_noise")
    if not fit:
        return "-"
    parts = []
    for st in fit.get("states", []):
        shape = st.get("shape") or (f"t{st['dof']}" if st.get("dof") else "normal")
        parts.append(f"{st.get('state', '?')}: {shape}")
    return ", ".join(parts) or "-"


def member_rows(rec: Any) -> list[list[str]]:
    """The verdict's rows: one per model, each seed ensemble member with its own seed, kept epoch,
    closed-loop error there and fitted step-noise shape (a single model is one row)."""
    sel = rec.selection
    members = sel.get("members") or [{"seed": rec.seed, **sel}]
    out = []
    for k, m in enumerate(members):
        curve = dict((int(e), float(err)) for e, err in m.get("curve", []))
        best = m.get("best_epoch")
        err = curve.get(int(best)) if best is not None else None
        out.append(
            [
                f"{k} (seed {m.get('seed', rec.seed)})" if len(members) > 1 else f"seed {rec.seed}",
                rec.algorithm,
                str(len(rec.data)),
                str(len(rec.validation)),
                str(len(curve)),
                str(best if best is not None else "-"),
                f"{err:.4f}" if err is not None and math.isfinite(err) else "-",
                fitted_step_noise(m),
            ]
        )
    return out


def read_loss_csv(path: Path) -> list[dict[str, Any]]:
    """The rows of a GAIL ``curves.csv`` (empty when absent)."""
    if not path.is_file():
        return []
    with path.open(newline="") as f:
        return list(csv.DictReader(f))


def write_curves_csv(rows: Sequence[dict[str, float]], path: Path) -> Path:
    """The curves as CSV, written atomically: a crash mid-write keeps the earlier curves whole."""
    fields = list(dict.fromkeys(k for r in rows for k in r)) or ["epoch", "val_error", "selected", "diverged"]
    text = io.StringIO(newline="")
    w = csv.DictWriter(text, fieldnames=fields)
    w.writeheader()
    for r in rows:
        w.writerow({k: "" if isinstance(v, float) and math.isnan(v) else f"{v:g}" for k, v in r.items()})
    return atomic_write_text(path, text.getvalue())


def tensorboard_writer(logdir: Path) -> Any:
    """A ``SummaryWriter``; ImportError naming the extra when tensorboard is not installed."""
    try:
        import tensorboard  # noqa: F401  (torch's writer needs it, and says so less clearly)
    except ImportError:
        raise ImportError(f"--tensorboard needs the tensorboard package: {TENSORBOARD_HINT}") from None
    from torch.utils.tensorboard import SummaryWriter

    return SummaryWriter(log_dir=str(logdir))


def write_tensorboard(rows: Sequence[dict[str, float]], logdir: Path) -> Path:
    """Every series of ``rows`` as TensorBoard scalars under ``train/<name>`` by epoch."""
    writer = tensorboard_writer(logdir)
    try:
        for r in rows:
            step = int(r["epoch"])
            for k, v in r.items():
                if k != "epoch" and math.isfinite(v):
                    writer.add_scalar(f"train/{k}", v, step)
    finally:
        writer.close()
    return logdir


def training_report(ckpt: Any, model_path: Path, rows: Sequence[dict[str, float]]) -> Report:
    """The page: what was selected and why first, the curves, then the record and provenance."""
    from .plots import training_curves

    rec = ckpt.record
    sel = rec.selection
    verdict = Table(
        [
            "member" if sel.get("members") else "model",
            "algorithm",
            "training logs",
            "validation logs",
            "epochs evaluated",
            "selected epoch",
            "closed-loop error",
            "step noise",
        ],
        member_rows(rec),
        numeric=frozenset({2, 3, 4, 5, 6}),
    )
    stopped = f" Training stopped: {sel['stopped']}." if sel.get("stopped") else ""
    if sel.get("members"):
        stopped += (
            " The seed ensemble's members are selected each on its own curve: val_error is member 0's (its"
            " kept epoch and stop above), val_error_member<k> member k's."
        )
    guide = [
        Text(
            f"Selection: {sel.get('criterion', '-')}.{stopped}"
            + (f" Warning: {sel['warning']}" if sel.get("warning") else "")
        )
    ]
    seeds = [str(m["seed"]) for m in sel.get("members", [])]
    title = f"{rec.algorithm}: {len(rec.data)} training logs, " + (
        f"members of seeds {', '.join(seeds)}" if seeds else f"seed {rec.seed}"
    )
    hyper = Table(["hyper-parameter", "value"], [[k, str(v)] for k, v in rec.hyper.items()])
    return Report(
        f"Training report: {model_path.name}",
        verdict,
        Provenance.collect(model_path, ckpt.system.name if ckpt.system else None),
        guide,
        [Section("Training curves", [training_curves(rows, title)]), Section("Hyper-parameters", [hyper])],
        {"selection": sel, "curves": list(rows)},
    )


def training_output_paths(model_path: Path) -> list[Path]:
    """The files :func:`write_training_outputs` writes beside ``model_path`` (tensorboard aside)."""
    stem = model_path.with_suffix("")
    ends = (".curves.csv", ".training.html", ".training.md", ".training.json")
    return [stem.with_name(stem.name + end) for end in ends]


def write_training_outputs(
    ckpt: Any, model_path: Path, losses_csv: Path | None = None, tensorboard: Path | None = None
) -> dict[str, Path]:
    """Beside the checkpoint ``model.pt``: ``model.curves.csv`` and ``model.training.{html,md,json}``;
    with ``tensorboard`` the scalars in that folder."""
    rows = curve_rows(ckpt.record.selection, read_loss_csv(losses_csv) if losses_csv else [])
    stem = model_path.with_suffix("")
    out = {"curves": write_curves_csv(rows, training_output_paths(model_path)[0])}
    files: ReportFiles = write_files(
        training_report(ckpt, model_path, rows), model_path.parent, stem.name + ".training"
    )
    out["html"] = files.html
    if tensorboard is not None:
        out["tensorboard"] = write_tensorboard(rows, tensorboard)
    return out
