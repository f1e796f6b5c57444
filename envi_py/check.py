"""``envi check``: does each controller version meet each requirement, and how sure are we?

For every version and requirement (the system description's, or given on the command line):

1. **In simulation**: runs from the versions' initial windows are simulated in batches until a
   sequential test decides (Wald's SPRT around the required probability, with an any-time interval;
   :mod:`envi_py.verdicts.sequential`), so an easy verdict costs few runs.
2. **For the real system**, when real runs of the version exist (TOVK, TMVK): each real run's
   outcome is paired with the model's prediction from that run's own sigma_0 (the fraction of
   ``sims_per_start`` runs meeting the requirement), and prediction-powered inference combines them
   with the model's predictions from further starts of that version (the training and validation
   logs the checkpoint records). A validity check withdraws the model-based claim when the real
   runs contradict the model (their count of successes against the paired predictions, and each real
   run's margin, and the mean, spread and roughness of each signal the requirement reads, against its
   own paired simulated runs'), and the verdict then rests on the real runs alone.
3. **Without real runs** (TMVU, ``--unseen``): the verdict rests on the model only, and the model's
   error measured on the versions that do have real runs is carried beside it.

Simulated runs that leave the training data's range (a state, or a commanded action) are counted and
reported with each row.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any, Sequence

import numpy as np

from .controllers import ControllerSpec
from .goals.evaluate import Runs, signals_of
from .goals.requirements import Requirement, parse, satisfied
from .goals.selection import diverged_runs, runaway_states
from .logs import Log, group_by_controller
from .model import Checkpoint
from .simulate import simulate_logs
from .system import RequirementSpec, SystemDescription, describe_schema
from .verdicts import RectifierCheck, model_only, ppi_verdict, sprt, trace_summaries
from .notes import release
from .verify import version_label


#: How close to 0 or 1 a required probability and its indifference region may come.
SPRT_EDGE = 1e-6


@dataclass
class CheckRow:
    """One version against one requirement: the simulation's verdict and the real system's."""

    version: str
    requirement: str
    expr: str
    p_required: float
    n_real: int
    simulation: dict[str, Any]
    real_system: dict[str, Any]
    outside_training: int  # simulated runs that left the training data's range
    sim_runs: int
    notes: list[str] = field(default_factory=list)

    @property
    def verdict(self) -> str:
        return str(self.real_system["verdict"])

    def to_json(self) -> dict[str, Any]:
        return {
            "version": self.version,
            "requirement": self.requirement,
            "expr": self.expr,
            "p_required": self.p_required,
            "verdict": self.verdict,
            "n_real": self.n_real,
            "simulation": self.simulation,
            "real_system": self.real_system,
            "outside_training": self.outside_training,
            "sim_runs": self.sim_runs,
            "notes": self.notes,
        }


@dataclass
class Checker:
    """Simulates a version from given starts and scores requirements on the runs."""

    ckpt: Checkpoint
    engine: str = "auto"
    seed: int = 0
    _calls: int = 0

    def runs(self, spec: ControllerSpec, starts: Sequence[Log], per_start: int) -> tuple[Runs, np.ndarray]:
        """``per_start`` simulated runs from each start, as goal-ready signals, and which of them (R,)
        left the training data for a tenth of the run or more: some state outside its training range
        (widened by 5 %) or resting on a limit the simulator clamps to, a saturating sensor's no-echo
        reading excepted (:func:`envi_py.goals.selection.runaway_states`), or some action the
        controller commands outside the training range of that action (a version whose parameters lie
        beyond the trained ones: the model then answers commands it never saw)."""
        self._calls += 1
        sims = simulate_logs(
            self.ckpt, spec, starts, runs=per_start, seed=self.seed + 9973 * self._calls, engine=self.engine
        )
        runs = signals_of(sims, sims[0].meta.schema, self.ckpt.config.history, self.ckpt.period_ms)
        schema = self.ckpt.schema
        channels = [*schema.states, *schema.actions]
        low, high = self.ckpt.norm.low, self.ckpt.norm.high
        observed = {c.name: (float(low[i]), float(high[i])) for i, c in enumerate(channels)}
        clamp = list(zip(*(lim.tolist() for lim in self.ckpt.limits())))
        states = runaway_states(schema.states, clamp, self.ckpt.config.limit_events)
        actions = [replace(c, low=-math.inf, high=math.inf) for c in schema.actions]  # judged on the training range
        return runs, diverged_runs(runs, [*states, *actions], observed, None, 0.05)


def _outcomes(req: Requirement, runs: Runs) -> np.ndarray:
    return satisfied(req, runs).astype(float)


def _summaries(req: Requirement, real: Runs, paired: Runs) -> dict[str, tuple[np.ndarray, np.ndarray]]:
    """Each real run's summaries of the signals ``req`` reads beside its paired runs' (n, m), by name
    ("color roughness"), for the validity check (:func:`envi_py.verdicts.trace_summaries`)."""
    out = {}
    for signal in req.reads:
        mine, theirs = trace_summaries(real.scored(signal)), trace_summaries(paired.scored(signal))
        for what, values in mine.items():
            out[f"{signal} {what}"] = (values, theirs[what].reshape(values.size, -1))
    return out


def check(
    ckpt: Checkpoint,
    real: Sequence[Log],
    requirements: Sequence[RequirementSpec],
    unseen: Sequence[ControllerSpec] = (),
    extra_starts: Sequence[Log] = (),
    alpha: float = 0.05,
    delta: float = 0.05,
    max_runs: int = 4000,
    batch: int = 10,
    sims_per_start: int = 40,
    seed: int = 0,
    engine: str = "auto",
) -> list[CheckRow]:
    """Every version of ``real`` and every ``unseen`` one against every requirement (module docstring).

    ``extra_starts``: further logs whose initial windows the model may start from (their outcomes
    are not used): with them the model's predictions cover more starts than the real runs'.
    """
    if not real:
        raise ValueError("envi check needs real logs: their initial windows start the simulations")
    system = ckpt.system or describe_schema(ckpt.schema)
    signals = [c.name for c in ckpt.schema.channels]
    reqs = [parse(r, signals) for r in requirements]
    if not reqs:
        raise ValueError("no requirements: declare [[requirements]] in the system description or pass --require")
    for r in requirements:  # the sequential test's indifference region must fit inside (0, 1)
        if not SPRT_EDGE < r.probability < 1 - SPRT_EDGE:
            raise ValueError(
                f"requirement {r.name!r}: probability {r.probability:g} lies too close to 0 or 1 for a "
                f"sequential test (between {SPRT_EDGE:g} and 1 - {SPRT_EDGE:g})"
            )
    # a fielded version's verdict is about the real system, not the model alone; by label, since the
    # command line's x=30 and a log's x = 30.0 are one version
    fielded = {version_label(spec, system): len(g) for spec, g in group_by_controller(real).items()}
    for label in (version_label(spec, system) for spec in unseen):
        if label in fielded:
            raise ValueError(
                f"--unseen {label}: the real logs hold {fielded[label]} run(s) of this version; --unseen is for "
                "a version never field-tested (drop it to check the version against its real runs)"
            )
    hist = ckpt.config.history
    checker = Checker(ckpt, engine, seed)
    release()  # the request is checked: a command's notes before the simulations, not after them
    groups = group_by_controller(real)
    extra = group_by_controller(extra_starts) if extra_starts else {}
    rows: list[CheckRow] = []
    measured: dict[str, dict[str, RectifierCheck]] = {r.name: {} for r in requirements}
    for spec, logs in groups.items():
        label = version_label(spec, system)
        real_runs = signals_of(logs, logs[0].meta.schema, hist, ckpt.period_ms)
        # by content: a Log holds arrays, so ``lg in logs`` (dataclass ==) is ambiguous and raises
        seen = {lg.sha256() for lg in logs}
        starts = list(logs) + [lg for lg in extra.get(spec, []) if lg.sha256() not in seen]
        paired_runs, outside = checker.runs(spec, logs, sims_per_start)
        extra_runs, extra_outside = (
            checker.runs(spec, starts[len(logs) :], sims_per_start) if len(starts) > len(logs) else (None, None)
        )
        if extra_outside is not None:  # the further starts' runs feed the estimate: they count too
            outside = np.concatenate([outside, extra_outside])
        for spec_req, req in zip(requirements, reqs):
            y = _outcomes(req, real_runs)
            paired = _outcomes(req, paired_runs).reshape(len(logs), sims_per_start).mean(axis=1)
            preds = (
                paired
                if extra_runs is None
                else np.concatenate([paired, _outcomes(req, extra_runs).reshape(-1, sims_per_start).mean(axis=1)])
            )
            sim, sim_outside = _sequential(
                checker, spec, starts, req, spec_req.probability, alpha, delta, max_runs, batch
            )
            notes = []
            if extra_runs is None:
                notes.append(
                    "no further starts of this version than its real runs: the model-based estimate "
                    "cannot narrow the real-only interval much"
                )
            if len(y) >= 2:
                verdict = ppi_verdict(
                    preds,
                    y,
                    paired,
                    spec_req.probability,
                    alpha,
                    sims_per_start=sims_per_start,
                    real_margins=req.margin(real_runs),
                    paired_margins=req.margin(paired_runs).reshape(len(logs), sims_per_start),
                    seed=seed,
                    summaries=_summaries(req, real_runs, paired_runs),
                )
                measured[spec_req.name][label] = verdict.check
                real_json = verdict.to_json()
            else:
                real_json = {
                    "verdict": "UNDECIDED",
                    "basis": "too few real runs",
                    "interval": [0.0, 1.0],
                    "reason": f"{len(y)} real run(s): at least 2 are needed to pair with the model",
                }
            rows.append(
                CheckRow(
                    label,
                    spec_req.name,
                    spec_req.expr,
                    spec_req.probability,
                    len(y),
                    sim.to_json(),
                    real_json,
                    sim_outside + int(outside.sum()),
                    sim.runs + outside.size,
                    notes,
                )
            )
    for spec in unseen:
        label = version_label(spec, system)
        starts = list(real)
        try:
            runs, outside = checker.runs(spec, starts, max(1, -(-max_runs // (4 * len(starts)))))
        except ValueError as exc:  # a controller that drives the model to NaN (x = 1e308): say which version
            raise ValueError(f"--unseen {label}: {exc}") from None
        for spec_req, req in zip(requirements, reqs):
            try:
                sim, sim_outside = _sequential(
                    checker, spec, starts, req, spec_req.probability, alpha, delta, max_runs, batch
                )
            except ValueError as exc:
                raise ValueError(f"--unseen {label}: {exc}") from None
            left = (sim_outside + int(outside.sum()), sim.runs + runs.count)
            verdict = model_only(_outcomes(req, runs), spec_req.probability, measured[spec_req.name], alpha, left)
            rows.append(
                CheckRow(
                    label,
                    spec_req.name,
                    spec_req.expr,
                    spec_req.probability,
                    0,
                    sim.to_json(),
                    verdict.to_json(),
                    left[0],
                    left[1],
                    ["never field-tested: started from the initial windows of the other versions' real logs"],
                )
            )
    return rows


def _sequential(
    checker: Checker,
    spec: ControllerSpec,
    starts: Sequence[Log],
    req: Requirement,
    p: float,
    alpha: float,
    delta: float,
    max_runs: int,
    batch: int,
) -> tuple[Any, int]:
    """Wald's SPRT on simulated runs drawn batch by batch from the starts, in turn, and how many of
    the runs it used left the training data."""
    outside = [0]

    def sample(n: int) -> np.ndarray:
        per_start = -(-n // len(starts))
        runs, left = checker.runs(spec, starts, per_start)
        outside[0] += int(left[:n].sum())
        return _outcomes(req, runs)[:n].astype(bool)

    lo, hi = max(p - delta, SPRT_EDGE), min(p + delta, 1 - SPRT_EDGE)
    result = sprt(
        sample,
        p,
        delta=min(delta, p - lo + 1e-12, hi - p + 1e-12) if 0 < p < 1 else delta,
        alpha=alpha,
        beta=alpha,
        max_runs=max_runs,
        batch=batch,
    )
    return result, outside[0]


def parse_requirement(text: str, probability: float, index: int) -> RequirementSpec:
    """``expr`` or ``expr @ 0.95`` from the command line; STL when it starts with always/eventually."""
    expr, sep, p = text.rpartition("@") if "@" in text else (text, "", "")
    try:
        prob = float(p) if sep else probability
    except ValueError:
        raise ValueError(f"--require {text!r}: the probability after '@' must be a number") from None
    expr = expr.strip()
    kind = "stl" if expr.split("(")[0].split("[")[0].strip() in ("always", "eventually", "not") else "metric"
    if not 0 < prob < 1:
        raise ValueError(f"--require {text!r}: the probability must lie strictly between 0 and 1")
    return RequirementSpec(f"R{index + 1}", expr, kind, prob)


#: The required probability of a command-line requirement that does not give one with '@'.
DEFAULT_PROBABILITY = 0.9


def requirements_of(
    system: SystemDescription | None, given: Sequence[str], probability: float | None = None
) -> list[RequirementSpec]:
    """The command line's requirements when given, else the system description's. ``probability``
    (``--probability``) is for the given ones without '@P'; given where none would use it, it is
    an error rather than silently ignored."""
    if probability is not None and not 0 < probability < 1:  # NaN fails too; it is this option's fault
        raise ValueError(f"--probability {probability:g}: must lie strictly between 0 and 1")
    if probability is not None and all("@" in t for t in given):
        whose = "every --require gives its own '@P'" if given else "the system description's requirements give theirs"
        raise ValueError(f"--probability {probability:g} would apply to no requirement: {whose}")
    prob = DEFAULT_PROBABILITY if probability is None else probability
    if given:
        return [parse_requirement(t, prob, i) for i, t in enumerate(given)]
    return list(system.requirements) if system else []


def to_markdown(rows: Sequence[CheckRow], meta: dict[str, Any]) -> str:
    """The verdict table first, then the evidence, provenance last (:mod:`envi_py.report.requirements`)."""
    from .report.markdown import to_markdown as render
    from .report.requirements import check_report

    return render(check_report(rows, meta, figures=False))


def write_check(rows: Sequence[CheckRow], out: Path, meta: dict[str, Any]) -> tuple[Path, Path]:
    """``check.md``, ``check.html`` (with the intervals drawn) and ``check.json`` in ``out``; returns
    the Markdown and JSON paths."""
    from .report.files import write_files
    from .report.requirements import check_report

    files = write_files(check_report(rows, meta), out, "check")
    return files.markdown, files.json
