"""Goal verdicts with honest confidence: exact binomial intervals, sequential decisions, metric summaries,
verdicts about the real system from simulated plus real runs, and a fair real-vs-real reference.

A pure library (numpy and scipy.stats only): callers simulate and read logs, these modules only decide.
Every result says how many runs it rests on.
"""

from .binomial import BinomialDecision, Verdict, clopper_pearson, decide
from .floor import FairFloor, fair_floor, kld_gaussian, ks_statistic, w1_normalised
from .metric_summary import MeanSummary, MetricSummary, QuantileSummary, mean_interval, quantile_interval, summarise
from .real_system import (
    Estimate,
    ModelOnlyVerdict,
    RealSystemVerdict,
    RectifierCheck,
    control_variate,
    margin_p_value,
    model_only,
    ppi,
    pit_values,
    ppi_verdict,
    rectifier_check,
    trace_summaries,
)
from .sequential import (
    Look,
    SequentialResult,
    confidence_sequence,
    fixed_sample_size,
    mixture_interval,
    sprt,
    sprt_expected_runs,
)

__all__ = [
    "BinomialDecision",
    "Estimate",
    "FairFloor",
    "Look",
    "MeanSummary",
    "MetricSummary",
    "ModelOnlyVerdict",
    "QuantileSummary",
    "RealSystemVerdict",
    "RectifierCheck",
    "SequentialResult",
    "Verdict",
    "clopper_pearson",
    "confidence_sequence",
    "control_variate",
    "decide",
    "fair_floor",
    "fixed_sample_size",
    "kld_gaussian",
    "ks_statistic",
    "margin_p_value",
    "mean_interval",
    "mixture_interval",
    "model_only",
    "pit_values",
    "ppi",
    "ppi_verdict",
    "quantile_interval",
    "rectifier_check",
    "sprt",
    "sprt_expected_runs",
    "summarise",
    "trace_summaries",
    "w1_normalised",
]
