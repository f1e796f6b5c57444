"""Controller versions of an experiment: their labels, and which ones train and which are verified.

A version is named by the system's version parameters (``x=30``, ``kp_steer=0.8,kp_speed=18``;
numbers written with ``:g``), or by the controller's label when the description names none. The
same label keys the grid's splits, the worker's results and the report's tables, so one function
(:func:`version_label`) makes it everywhere.

Which versions a use case trains on and verifies is the user's choice (:class:`VersionChoice`,
from ``--train-versions`` and friends), each version written like its label; numbers compare as
numbers (``x=30.0`` is ``x=30``). Only for the paper's lane-keeping logs (versions told apart by
``x`` alone) are the paper's choices the defaults: TOVK x=30, TMVK x=10,30,50, TMVU x=20,40.
"""

from __future__ import annotations

import hashlib
import math
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

from ..controllers import ControllerSpec
from ..logs import Log
from ..system import SystemDescription

USE_CASES = ("tovk", "tmvk", "tmvu")
#: The paper's choices (Section 6), used only when the logs' versions are lane-keeping x values.
PAPER_X = {"tovk": ((30,), (30,)), "tmvk": ((10, 30, 50), (10, 30, 50)), "tmvu": ((10, 30, 50), (20, 40))}


def _text(value: Any) -> str:
    if isinstance(value, bool) or not isinstance(value, (int, float)):
        return str(value)
    return f"{value:g}"


def version_label(spec: ControllerSpec, system: SystemDescription) -> str:
    """The version's label (:meth:`SystemDescription.version_label`, the one definition)."""
    return system.version_label(spec)


def parse_label(text: str) -> dict[str, str]:
    """``kp_steer=0.8,kp_speed=18`` -> {"kp_steer": "0.8", "kp_speed": "18"}; {} when it is not of that form."""
    out: dict[str, str] = {}
    for part in text.split(","):
        name, sep, value = part.partition("=")
        name, value = name.strip(), value.strip()
        if not sep or not name or not value or name in out or not name.replace("_", "").isalnum():
            return {}
        out[name] = value
    return out


def _same(a: str, b: str) -> bool:
    """Two written values are the same version value: equal as numbers when both are numbers."""
    try:
        fa, fb = float(a), float(b)
    except ValueError:
        return a == b
    return fa == fb or (math.isnan(fa) and math.isnan(fb))


@dataclass(frozen=True)
class Version:
    """One controller version among the logs: its label, parameters and logs (in reading order)."""

    label: str
    params: dict[str, Any]
    logs: tuple[Log, ...]

    def matches(self, choice: str) -> bool:
        """Whether a user's ``name=value[,name=value]`` (or the exact label) names this version."""
        if choice.strip() == self.label:
            return True
        asked = parse_label(choice)
        return (
            bool(asked)
            and set(asked) == set(self.params)
            and all(_same(asked[k], _text(v)) for k, v in self.params.items())
        )

    def entropy(self) -> list[int]:
        """Seed material that identifies the version (whole non-negative numbers as themselves, so
        the paper's x versions keep their draws; anything else through a hash of its text)."""
        values = list(self.params.values()) or [self.label]
        return [
            int(v)
            if isinstance(v, (int, float)) and not isinstance(v, bool) and float(v).is_integer() and v >= 0
            else int.from_bytes(hashlib.sha256(_text(v).encode()).digest()[:4], "big")
            for v in values
        ]


def versions_of(logs: Sequence[Log], system: SystemDescription) -> dict[str, Version]:
    """The logs' versions by label, sorted by their parameters. Two different controllers with the
    same version parameters are an error: a table per version would mix them."""
    specs: dict[str, ControllerSpec] = {}
    grouped: dict[str, list[Log]] = {}
    for lg in logs:
        spec = lg.controller
        label = version_label(spec, system)
        if specs.setdefault(label, spec) != spec:
            raise ValueError(
                f"{lg.name}: controller {spec.label()} and {specs[label].label()} share the version "
                f"{label}; name the parameter that tells them apart in the system's [versions] params"
            )
        grouped.setdefault(label, []).append(lg)

    def order(label: str) -> tuple:
        params = system.version_params(specs[label])
        return tuple(
            (0, float(v), "") if isinstance(v, (int, float)) and not isinstance(v, bool) else (1, 0.0, str(v))
            for v in params.values()
        ) + ((1, 0.0, label),)

    return {
        label: Version(label, system.version_params(specs[label]), tuple(grouped[label]))
        for label in sorted(grouped, key=order)
    }


@dataclass(frozen=True)
class VersionChoice:
    """The versions the user named (as written): TMVK/TMVU training ones, TMVK's verified ones
    (default: the trained ones), TMVU's unseen ones, and TOVK's single version."""

    train: tuple[str, ...] = ()
    eval: tuple[str, ...] = ()
    unseen: tuple[str, ...] = ()
    tovk: str | None = None


@dataclass(frozen=True)
class Plan:
    """Resolved labels: what each use case trains on and verifies."""

    train: dict[str, tuple[str, ...]]
    eval: dict[str, tuple[str, ...]]

    def to_json(self) -> dict[str, Any]:
        return {uc: {"train": list(self.train[uc]), "eval": list(self.eval[uc])} for uc in self.train}


def _available(versions: dict[str, Version]) -> str:
    return "; ".join(f"{v.label} ({len(v.logs)} logs)" for v in versions.values()) or "none"


def _pick(versions: dict[str, Version], choices: Sequence[str], what: str) -> tuple[str, ...]:
    """The labels of the chosen versions; a choice naming no version (or one twice) is an error."""
    out: list[str] = []
    for choice in choices:
        hits = [v.label for v in versions.values() if v.matches(choice)]
        if not hits:
            raise ValueError(f"{what}: no logs of version {choice!r}; available: {_available(versions)}")
        if hits[0] in out:
            raise ValueError(f"{what}: version {hits[0]} named twice")
        out.append(hits[0])
    return tuple(out)


def _paper(versions: dict[str, Version]) -> bool:
    """Whether the logs are the paper's lane-keeping versions: told apart by ``x`` alone."""
    return bool(versions) and all(list(v.params) == ["x"] for v in versions.values())


def plan_versions(versions: dict[str, Version], use_cases: Sequence[str], choice: VersionChoice) -> Plan:
    """What each use case trains on and verifies, from the user's choice or the paper's defaults."""
    unknown = [uc for uc in use_cases if uc not in USE_CASES]
    if unknown:
        raise ValueError(f"unknown use case {unknown[0]!r}; known: {', '.join(USE_CASES)}")
    for given, flag, needs in (
        (choice.train, "--train-versions", ("tmvk", "tmvu")),
        (choice.eval, "--eval-versions", ("tmvk",)),
        (choice.unseen, "--unseen-versions", ("tmvu",)),
        (choice.tovk, "--tovk-version", ("tovk",)),
    ):
        if given and not set(needs) & set(use_cases):
            raise ValueError(f"{flag} applies to {' and '.join(needs)}, which is not asked for")
    paper = _paper(versions)

    def chosen(given: Sequence[str], flag: str, uc: str, which: int) -> tuple[str, ...]:
        if given:
            return _pick(versions, given, flag)
        if not paper:
            raise ValueError(
                f"{uc}: give {flag} (name=value[,name=value] per version); available: {_available(versions)}"
            )
        return _pick(versions, [f"x={x}" for x in PAPER_X[uc][which]], f"{uc} (the paper's versions)")

    train: dict[str, tuple[str, ...]] = {}
    evals: dict[str, tuple[str, ...]] = {}
    for uc in use_cases:
        if uc == "tovk":
            train[uc] = evals[uc] = chosen([choice.tovk] if choice.tovk else [], "--tovk-version", uc, 0)
            continue
        train[uc] = chosen(choice.train, "--train-versions", uc, 0)
        if uc == "tmvk":
            evals[uc] = _pick(versions, choice.eval, "--eval-versions") if choice.eval else train[uc]
            untrained = [v for v in evals[uc] if v not in train[uc]]
            if untrained:
                raise ValueError(
                    f"tmvk verifies trained versions only; {', '.join(untrained)} is not among "
                    f"--train-versions (verify it as unseen with tmvu and --unseen-versions)"
                )
        else:
            evals[uc] = chosen(choice.unseen, "--unseen-versions", uc, 1)
            seen = [v for v in evals[uc] if v in train[uc]]
            if seen:
                raise ValueError(
                    f"tmvu verifies versions never trained on; {', '.join(seen)} is among --train-versions"
                )
    return Plan(train, evals)
