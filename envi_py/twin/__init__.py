"""A physics twin of the lane-keeping robot with switchable real-world effects, calibrated to the real logs.

``car`` is the second system's twin (a car keeping a lane edge behind a lead vehicle, two PID loops).

The lane twin is the project's fully known world: default data for the main job, the world of the simulated
brick, and the ground truth for scoring the sim-to-real diagnosis (each log's sidecar lists the
effects that made it).
"""

from .car import (
    CAR_GAINS,
    CAR_TRAINED,
    CAR_UNSEEN,
    car_versions,
    generate_car,
    generate_car_versions,
    write_car_logs,
)
from .car_world import CarBatch, CarProfile
from .effects import EFFECTS, Effect, Param, describe, parse_effects, resolve
from .generate import generate, simulate, write_logs
from .profile import DEFAULT_PROFILE, TwinProfile, default_profile
from .world import Batch, TwinWorld

__all__ = [
    "CAR_GAINS",
    "CAR_TRAINED",
    "CAR_UNSEEN",
    "DEFAULT_PROFILE",
    "EFFECTS",
    "Batch",
    "CarBatch",
    "CarProfile",
    "Effect",
    "Param",
    "TwinProfile",
    "TwinWorld",
    "car_versions",
    "default_profile",
    "describe",
    "generate",
    "generate_car",
    "generate_car_versions",
    "parse_effects",
    "resolve",
    "simulate",
    "write_car_logs",
    "write_logs",
]
