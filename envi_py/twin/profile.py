"""A twin profile: the robot's physical parameters plus the effects that are on by default.

The shipped profile (``profiles/default.json``) is the one calibrated to the real field logs, so
``generate`` without a profile produces logs that look like the real robot's.
"""

from __future__ import annotations

import json
import math
import os
from dataclasses import asdict, dataclass, field, fields
from pathlib import Path
from typing import Any, Callable

from envi_py.files import parse_json, read_text

from ..atomic import atomic_write_text
from .effects import resolve

PROFILE_DIR = Path(__file__).resolve().parent / "profiles"
DEFAULT_PROFILE = PROFILE_DIR / "default.json"

#: The physical fields' ranges beyond being a finite number: (rule in words, test). A zero speed,
#: period or spot width would divide by zero, a huge warm-up run for ever.
_RULES: dict[str, tuple[str, Callable[[float], bool]]] = {
    **{k: ("a number above 0", lambda v: v > 0) for k in ("speed", "wheelbase", "spot", "gamma", "period_ms")},
    **{k: ("a number of at least 0", lambda v: v >= 0) for k in ("ahead", "black", "white")},
    "warmup": ("a whole number from 0 to 100000", lambda v: v == int(v) and 0 <= v <= 100_000),
}


@dataclass
class TwinProfile:
    """Physics of the robot and the track. Lengths in mm, speeds in mm/s, reflectance in colour units.

    Colour logs identify only ratios (speed/spot, speed/wheelbase, ahead/spot), so the wheelbase
    is fixed at a nominal LEGO value and speed, spot and sensor lead are fitted.
    """

    speed: float = 150.0  # forward speed, mm/s
    wheelbase: float = 120.0  # mm; yaw rate = speed / wheelbase * tan(steering angle) * grip
    spot: float = 10.0  # width of the black-to-white blend under the sensor, mm
    ahead: float = 40.0  # sensor distance ahead of the rear axle, mm
    black: float = 5.0
    white: float = 75.0
    gamma: float = 1.0  # sensor non-linearity: reading = black + (white - black) * blend ** gamma
    period_ms: float = 40.0  # nominal control period, before jitter
    warmup: int = 40  # unlogged ticks before a run, so a log starts inside the limit cycle
    effects: dict[str, Any] = field(default_factory=dict)
    fit: dict[str, Any] = field(default_factory=dict)  # calibration summary (for reproduction tests)

    def to_json(self) -> dict[str, Any]:
        return asdict(self)

    @staticmethod
    def from_json(d: dict[str, Any]) -> "TwinProfile":
        """A profile from its JSON object; a ValueError names an unknown field, a value that is not a
        finite number in its range, or a bad effect (checked as :func:`.effects.resolve` would)."""
        if not isinstance(d, dict):
            raise ValueError(f"twin profile: a JSON object is expected, got {type(d).__name__}")
        known = {f.name for f in fields(TwinProfile)}
        unknown = set(d) - known
        if unknown:
            raise ValueError(f"twin profile: unknown field(s) {', '.join(sorted(map(str, unknown)))}")
        for name, value in d.items():
            if name in ("effects", "fit"):
                if not isinstance(value, dict):
                    raise ValueError(f"twin profile: {name} must be a JSON object, got {value!r}")
                continue
            rule, fits = _RULES.get(name, ("a finite number", lambda v: True))
            number = isinstance(value, (int, float)) and not isinstance(value, bool) and math.isfinite(value)
            if not (number and fits(value)):
                raise ValueError(f"twin profile: {name} must be {rule}, got {value!r}")
        resolve(d.get("effects", {}), None)  # every effect known, finite and within its range
        return TwinProfile(**d)

    def save(self, path: str | os.PathLike) -> Path:
        path = Path(path)
        return atomic_write_text(path, json.dumps(self.to_json(), indent=1) + "\n")

    @staticmethod
    def load(path: str | os.PathLike) -> "TwinProfile":
        """The profile in ``path``: a regular file (a named pipe would block the read forever)."""
        return TwinProfile.from_json(parse_json(read_text(path, "a twin profile"), str(path), "a twin profile"))

    def replace(self, **changes: Any) -> "TwinProfile":
        d = self.to_json()
        d.update(changes)
        return TwinProfile.from_json(d)


def default_profile() -> TwinProfile:
    """The shipped profile calibrated to the real lane-keeping logs (a plain one if none is shipped)."""
    return TwinProfile.load(DEFAULT_PROFILE) if DEFAULT_PROFILE.exists() else TwinProfile()
