"""Simulated runs that settle into an exact repeating cycle the real runs never show
(:mod:`envi_py.diagnose.cycles`): found where a deterministic model of the steered twin locks,
counted one simulated run per real window, and said in the verdict."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st

from envi_py.controllers import ControllerSpec
from envi_py.diagnose.cycles import MAX_PERIOD, cycle_check, cycle_text, settled_period
from envi_py.diagnose.report import _cycles_table
from envi_py.diagnose.run import _gaps
from envi_py.diagnose.shrink import scoring_of
from envi_py.logs import Log, LogMeta
from envi_py.system import Channel, LogSchema
from envi_py.train import train
from envi_py.twin import TwinProfile, generate
from tests.test_diagnose_report import _diagnosis

LANE = ControllerSpec("lane-keeping", {"x": 30})
COLOUR = Channel("color", "", 0.0, 100.0, 1.0)
SCHEMA = LogSchema((COLOUR,), (Channel("angle", "deg", -90.0, 90.0),))


def _log(colour: np.ndarray, name: str) -> Log:
    t = np.arange(len(colour)) * 0.04
    meta = LogMeta(schema=SCHEMA, controller=LANE, run_id=name)
    return Log(None, t, colour[:, None].astype(float), np.zeros((len(colour), 1)), meta)


def _drifting(n: int, seed: int) -> np.ndarray:
    """A period-2 swing whose centre drifts by less than a step per cycle, read at resolution 1."""
    rng = np.random.default_rng(seed)
    centre = 40 + np.cumsum(rng.uniform(-0.3, 0.3, n))
    return np.round(centre + 7 * (-1.0) ** np.arange(n))


def _locked(n: int) -> np.ndarray:
    return np.round(40 + 7 * (-1.0) ** np.arange(n))


def test_a_run_is_settled_only_where_its_tail_repeats_within_half_a_resolution_step():
    assert settled_period(_locked(100)[:, None], [COLOUR], 4) == 2
    wobble = _locked(100) + np.where(np.arange(100) % 7 == 0, 0.4, 0.0)  # within half a step of the cycle
    assert settled_period(wobble[:, None], [COLOUR], 4) == 2
    assert settled_period(_drifting(100, 0)[:, None], [COLOUR], 4) is None
    assert settled_period(np.full((100, 1), 40.0), [COLOUR], 4) == 1
    # a run that settles only in its first half is not settled; a tail too short for 4 cycles never is
    early = np.concatenate([_locked(50), _drifting(50, 1)])
    assert settled_period(early[:, None], [COLOUR], 4) is None
    assert settled_period(_drifting(100, 2)[:, None], [COLOUR], 4) is None
    period_9 = np.tile(np.arange(9.0), 20)[:, None]
    assert settled_period(period_9, [COLOUR], 0) is None and MAX_PERIOD < 9
    # without a declared resolution a reading must repeat to 1e-6
    exact = Channel("color", "", 0.0, 100.0)
    assert settled_period((_locked(100) + 1e-3 * (np.arange(100) % 2 == 0))[:, None], [exact], 4) == 2
    assert settled_period((_locked(100) + 1e-3 * np.arange(100))[:, None], [exact], 4) is None


@settings(max_examples=200, deadline=None, database=None, derandomize=True)
@given(
    cycle=st.lists(st.integers(0, 100), min_size=1, max_size=MAX_PERIOD),
    extra=st.integers(0, 40),
    skip=st.integers(0, 10),
    where=st.floats(0.0, 1.0, exclude_max=True),
)
def test_a_periodic_tail_is_settled_at_a_divisor_of_its_period_and_one_odd_reading_unsettles_it(
    cycle, extra, skip, where
):
    """Property: readings that repeat ``cycle`` (period p <= MAX_PERIOD) over a tail long enough for
    4 cycles settle at a period dividing p (the shortest one: by Fine and Wilf's theorem two periods
    of a long enough run share their gcd); one reading in the tail set outside every value of the
    cycle leaves no period at all."""
    p = len(cycle)
    n = skip + 2 * 4 * p + extra  # the tail is the last half of the rows after skip
    x = np.resize(np.array(cycle, dtype=float), n)[:, None]
    found = settled_period(x, [COLOUR], skip)
    assert found is not None and p % found == 0
    tail_start = skip + (n - skip) - (n - skip) // 2
    i = tail_start + int(where * (n - tail_start))
    odd = x.copy()
    odd[i, 0] = max(cycle) + 7.0
    assert settled_period(odd, [COLOUR], skip) is None


def test_the_check_counts_one_simulated_run_per_real_window_and_tests_them_like_with_like():
    real = [_log(_drifting(100, s), f"r{s}") for s in range(12)]
    locked = [_log(_locked(100), f"s{s}") for s in range(12)]
    check = cycle_check([("x=30", real, locked)], [COLOUR], 4)
    assert (check["runs"], check["real_settled"], check["sim_settled"]) == (12, 0, 12)
    assert check["significant"] and check["p"] < 1e-5 and check["periods"] == [2]
    # three runs per window, only the later replicates settled: the first ones are what is counted
    mixed = [lg for s in range(12) for lg in (_log(_drifting(100, 100 + s), "a"), locked[s], locked[s])]
    check = cycle_check([("x=30", real, mixed)], [COLOUR], 4)
    assert check["sim_settled"] == 0 and not check["significant"]
    # real runs that settle as often as the simulated ones: no finding
    check = cycle_check([("x=30", locked, locked)], [COLOUR], 4)
    assert check["real_settled"] == check["sim_settled"] == 12 and not check["significant"]
    assert cycle_text(check) == ""


def test_the_verdict_says_where_simulated_runs_settle_and_the_json_carries_it():
    real = [_log(_drifting(100, s), f"r{s}") for s in range(10)]
    check = cycle_check([("x=30", real, [_log(_locked(100), "s")] * 10)], [COLOUR], 4)
    d = replace(_diagnosis(0.001), cycles=check)
    verdict = d.verdict()
    assert "exact repeating cycle (period 2 rows) in 10 of 10 runs, against 0 of 10 real runs" in verdict
    assert "Fisher exact p=" in verdict and d.to_json()["cycles"] == check
    # after the gap it qualifies, before the horizon
    where = [verdict.index(t) for t in ("largest closed-loop gap", "repeating cycle", "Over the horizon")]
    assert where == sorted(where)
    table = _cycles_table(d)[0]
    assert table.rows == [["x=30", "10", "0", "10", "2"]]
    assert "10 of 10 simulated against 0 of 10 real" in table.caption and "(more than the real ones)" in table.caption
    quiet = cycle_check([("x=30", real, real)], [COLOUR], 4)
    assert _cycles_table(replace(d, cycles=quiet))[0].rows == [["x=30", "10", "0", "0", "-"]]
    assert _cycles_table(replace(d, cycles=None)) == []
    assert "repeating cycle" not in replace(_diagnosis(0.001), cycles=quiet).verdict()
    assert "repeating cycle" not in _diagnosis(0.001).verdict()  # older diagnoses: no check at all


def test_a_deterministic_model_of_the_steered_twin_locks_where_the_real_loop_drifts():
    """The steered twin's clean loop drifts by less than a colour unit per cycle; a deterministic
    model of it, with its readings rounded, repeats a window exactly (seed 100: 20 of 20 windows
    against 2 of 20 real runs); the same model with a Gaussian head does not."""
    fit = generate(LANE, 25, 100, {}, seed=100, profile=TwinProfile())
    held = generate(LANE, 20, 100, {}, seed=4_000_100, profile=TwinProfile())
    found = {}
    for head in ("deterministic", "gaussian"):
        ckpt = train("bc", fit[:20], fit[20:], seed=100, epochs=150, lr=5e-4, history=4, head=head, members=1)
        groups, _ = _gaps(ckpt, held, 2, 100)
        found[head] = cycle_check(groups, ckpt.schema.states, scoring_of(ckpt).skip)
    det, gauss = found["deterministic"], found["gaussian"]
    assert det["significant"] and det["sim_settled"] >= 15 and det["real_settled"] <= 5, det
    assert not gauss["significant"] and gauss["sim_settled"] <= det["real_settled"], gauss
