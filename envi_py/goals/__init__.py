"""Goal metrics over any signal, requirements (metric thresholds and STL) and the model-selection score.

- :mod:`.library`: the standard metrics of one signal (deviations, band time, overshoot, settling,
  rise, integrals, oscillations, min/max/mean/std) and their registry (parameters, units, scales);
- :mod:`.presets`: shipped goal sets (``lane-keeping``: the paper's eight driving metrics);
- :mod:`.registry`: a metric by name, including a user's ``package.module:function``;
- :mod:`.evaluate`: the runs' signals by name and the table of goal metrics over them;
- :mod:`.requirements`: metric and STL requirements, parsed and checked per run;
- :mod:`.selection`: the model-selection score of simulated against real runs, with divergence.
"""

from .evaluate import Runs, goal_scale, goal_table, goal_unit, goal_values, signals_of
from .presets import goals_of, preset_goals
from .registry import KNOWN, metric
from .requirements import parse, satisfied
from .selection import SelectionScore, default_goals, selection_score

__all__ = [
    "KNOWN",
    "Runs",
    "SelectionScore",
    "default_goals",
    "goal_scale",
    "goal_table",
    "goal_unit",
    "goal_values",
    "goals_of",
    "metric",
    "parse",
    "preset_goals",
    "satisfied",
    "selection_score",
    "signals_of",
]
