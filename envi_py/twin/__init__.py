"""A physics twin of the lane-keeping robot with switchable real-world effects, calibrated to the real logs.

It is the project's fully known world: default data for the main job, the world of the simulated
brick, and the ground truth for scoring the sim-to-real diagnosis (each log's sidecar lists the
effects that made it).
"""

from .effects import EFFECTS, Effect, Param, describe, parse_effects, resolve
from .generate import generate, simulate, write_logs
from .profile import DEFAULT_PROFILE, TwinProfile, default_profile
from .world import Batch, TwinWorld

__all__ = ["EFFECTS", "Effect", "Param", "describe", "parse_effects", "resolve", "generate", "simulate",
           "write_logs", "DEFAULT_PROFILE", "TwinProfile", "default_profile", "Batch", "TwinWorld"]
