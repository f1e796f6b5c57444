"""Each candidate-effect test on synthetic residuals with a known answer, and the Holm correction."""

from __future__ import annotations

import numpy as np
import pytest

from envi_py.dataset import Normaliser
from envi_py.diagnose.effects import (
    CANDIDATES,
    Finding,
    _nested_first,
    holm,
    lattice_step,
    misfit_share,
    run_candidates,
    typical_share,
)
from envi_py.dataset import play_offsets
from envi_py.diagnose.residuals import BEYOND, PLAY_WIDTHS, Residuals, ResidualSet
from envi_py.logs import LANE_KEEPING_SCHEMA
from envi_py.model import Checkpoint, EnvModel, ModelConfig, TrainingRecord

RUNS, ROWS, HIST = 30, 90, 10


def ckpt() -> Checkpoint:
    rec = TrainingRecord("bc", 0, period_ms=40.0)
    norm = Normaliser(np.array([5.0, -30.0]), np.array([80.0, 30.0]))
    return Checkpoint(EnvModel(ModelConfig(1, 1, hidden=(4,))), norm, LANE_KEEPING_SCHEMA, rec)


def synthetic(r_extra=None, seed: int = 0, noise: float = 0.05) -> Residuals:
    """Residuals of a well-structured model on an oscillating closed loop: tiny white noise plus a
    misfit that is a smooth function of the window (which no test may mistake for an effect).

    Each run is the same limit cycle at its own phase, so every window has look-alike windows in
    other runs, as in real closed-loop logs."""
    rng = np.random.default_rng(seed)
    n = RUNS * ROWS
    run = np.repeat(np.arange(RUNS), ROWS)
    row = np.tile(np.arange(HIST, HIST + ROWS), RUNS)
    phase = row / 3.0 + 2 * np.pi * rng.random(RUNS)[run]
    state = 40 + 30 * np.sin(phase)
    action = np.sign(state - 40) * 30
    pred = 40 + 30 * np.sin(phase + 1 / 3.0)
    # what an actuator with play would do under a slowly wandering command the window does not show
    drift = np.cumsum(rng.normal(0, 3, (RUNS, ROWS)), axis=1)
    play = np.concatenate([np.stack([play_offsets(a, w * 60) for w in PLAY_WIDTHS], axis=1) for a in drift])
    dt = 40 + rng.normal(0, 4, n)
    lags = phase[:, None] - np.arange(HIST)[None, :] / 3.0
    window = np.stack([np.sin(lags), np.sign(np.sin(lags))], axis=2).reshape(n, HIST * 2)
    beyond = rng.normal(size=(n, BEYOND * 2))
    misfit = 0.5 * np.sin(2 * phase)
    res = Residuals(
        r=misfit + rng.normal(0, noise, n),
        pred_std=None,
        predicted=pred,
        real_next=pred + 0.3,
        state=state,
        action=action,
        run=run,
        row=row,
        dt=dt,
        window=window,
        beyond=beyond,
        play=play,
    )
    if r_extra is not None:
        res.r = res.r + r_extra(res, rng)
    res.real_next = res.predicted + res.r
    return res


CASES = {
    "noise": lambda res, rng: rng.normal(0, 2.0, len(res)),
    "drift": lambda res, rng: 0.05 * (res.row - 50),
    "run_to_run": lambda res, rng: rng.normal(0, 1.0, RUNS)[res.run],
    "memory_delay": lambda res, rng: 1.5 * res.beyond[:, 0],
    "backlash": lambda res, rng: 0.3 * res.play[:, 3],
    "jitter": lambda res, rng: 0.8 * (res.dt / 40 - 1) * (res.predicted - res.state) * 10,
}


def _previous_interval(res: Residuals) -> np.ndarray:
    """The interval ending at each window's last row (nominal at a run's first residual)."""
    prev = np.concatenate([[40.0], res.dt[:-1]])
    prev[np.concatenate([[True], res.run[1:] != res.run[:-1]])] = 40.0
    return prev


@pytest.mark.parametrize("effect", sorted(CASES))
def test_injected_effect_is_ranked_first(effect):
    res = synthetic(CASES[effect])
    findings = run_candidates(ResidualSet.of(res), ckpt())
    assert findings[0].effect == effect and findings[0].significant, [(f.effect, f.p_holm, f.share) for f in findings]


def test_jitter_seen_through_a_sensor_that_reads_one_period_late():
    """A sensor with a conversion latency shows the previous interval's motion, not the predicted
    one's (the diffdrive twin's): the jitter test reads the intervals before the predicted one too.
    With the predicted interval alone it explained 0.03 % of these residuals, and noise was named."""
    res = synthetic(lambda res, rng: 0.8 * (_previous_interval(res) / 40 - 1) * (res.predicted - res.state) * 10)
    findings = run_candidates(ResidualSet.of(res), ckpt())
    assert findings[0].effect == "jitter" and findings[0].significant and findings[0].share > 0.3, [
        (f.effect, f.p_holm, f.share) for f in findings
    ]


def test_clean_residuals_show_no_significant_effect():
    for seed in range(5):
        findings = run_candidates(ResidualSet.of(synthetic(seed=seed)), ckpt())
        assert not any(f.significant for f in findings), [(f.effect, f.p_holm, f.share) for f in findings]


def test_quantisation_seen_only_when_readings_sit_on_a_lattice_and_model_does_not_round():
    res = synthetic(lambda res, rng: rng.normal(0, 0.3, len(res)))
    res.real_next = np.round(res.real_next)
    res.r = res.real_next - res.predicted
    c = ckpt()
    stat, p, share, _ = next(x for x in CANDIDATES if x.name == "quantisation").test(res, c)
    assert stat == 1.0 and p < 1e-6 and share > 0.3
    c.model.config.round_to = (1.0,)
    assert next(x for x in CANDIDATES if x.name == "quantisation").test(res, c)[1] == 1.0


def test_quantisation_finds_the_lattice_step_and_fixes_with_it():
    res = synthetic(lambda res, rng: rng.normal(0, 1.0, len(res)))
    res.real_next = np.round(res.real_next / 4) * 4
    res.r = res.real_next - res.predicted
    finding = run_candidates(ResidualSet.of(res), ckpt())[0]
    assert finding.effect == "quantisation" and finding.significant and finding.fix == {"round_to": (4.0,)}
    assert lattice_step(res.predicted) is None


def test_saturation_when_real_readings_pile_up_at_a_limit():
    res = synthetic()
    res.real_next = np.clip(res.predicted + res.r, 20, 60)
    res.r = res.real_next - res.predicted
    finding = next(f for f in run_candidates(ResidualSet.of(res), ckpt()) if f.effect == "saturation")
    assert finding.significant and finding.fix == {"limits": ((20.0, 60.0),), "history": 20}


def test_no_saturation_for_a_smooth_response_reaching_its_extremes():
    finding = next(f for f in run_candidates(ResidualSet.of(synthetic()), ckpt()) if f.effect == "saturation")
    assert not finding.significant and finding.p > 0.05


def test_gaussian_model_calibrated_noise_is_not_flagged():
    res = synthetic(lambda res, rng: rng.normal(0, 2.0, len(res)))
    res.pred_std = np.full(len(res), 2.0)
    noise = next(f for f in run_candidates(ResidualSet.of(res), ckpt()) if f.effect == "noise")
    assert not noise.significant
    res.pred_std = np.full(len(res), 0.5)  # under-dispersed model
    noise = next(f for f in run_candidates(ResidualSet.of(res), ckpt()) if f.effect == "noise")
    assert noise.significant


def test_typical_share_is_one_for_gaussian_scatter_and_small_for_a_few_jumps():
    rng = np.random.default_rng(0)
    assert typical_share(rng.normal(0, 3.0, 20_000)) > 0.95
    assert 0.45 < typical_share(rng.standard_t(3, 20_000)) < 0.65
    jumps = rng.normal(0, 0.5, 20_000)
    jumps[::25] += rng.choice([-20.0, 20.0], 800)  # every 25th step kicked: 4 % of them
    assert typical_share(jumps) < 0.05
    assert typical_share(np.zeros(10)) == 1.0


def _kicked(res, rng):
    """A disturbance at every 25th step of each run, holding most of the residual mean square."""
    return np.where(res.row % 25 == 0, rng.choice([-12.0, 12.0], len(res)), 0.0) + rng.normal(0, 0.3, len(res))


def test_a_few_large_jumps_are_not_noise_while_as_much_scatter_at_every_step_is():
    """A periodic kick (a bump in the track) carries most of the residual mean square in 4 % of the
    steps. Noise is scatter at every step, so it is not named; the same mean square spread over
    every step is. The model predicts the scatter of the ordinary steps (a Gaussian head)."""
    kicked = synthetic(_kicked)
    kicked.pred_std = np.full(len(kicked), 0.3)
    noise = next(f for f in run_candidates(ResidualSet.of(kicked), ckpt()) if f.effect == "noise")
    assert not noise.significant, (noise.p_holm, noise.share)
    spread = float(np.sqrt(np.mean((kicked.r - synthetic().r) ** 2)))
    even = synthetic(lambda res, rng: rng.normal(0, spread, len(res)))
    even.pred_std = np.full(len(even), 0.3)
    noise = next(f for f in run_candidates(ResidualSet.of(even), ckpt()) if f.effect == "noise")
    assert noise.significant and noise.share > 0.5, (noise.p_holm, noise.share)


def _finding(effect: str, share: float, p_holm: float, significant: bool) -> Finding:
    return Finding(effect, 1.0, p_holm, share, "", {}, p_holm, significant)


def test_backlash_beyond_a_leading_memory_is_named_first():
    memory, drift = _finding("memory_delay", 0.12, 1e-20, True), _finding("drift", 0.06, 1e-9, True)
    backlash = _finding("backlash", 0.03, 1e-6, False)  # below the share bar, yet beyond the memory rows
    named = _nested_first([memory, drift, backlash], 0.05)
    assert [f.effect for f in named] == ["backlash", "memory_delay", "drift"] and named[0].significant
    weak = _finding("backlash", 0.03, 0.2, False)  # nothing beyond the rows: memory keeps its place
    assert _nested_first([memory, drift, weak], 0.05) == [memory, drift, weak]
    # Memory not leading (another effect explains more): the order stands.
    assert _nested_first([drift, memory, backlash], 0.05) == [drift, memory, backlash]
    # Memory leading by its what-if (the commands lag): that is its form, backlash does not take over.
    lagging = Finding("memory_delay", 1.0, 1e-20, 0.01, "", {}, 1e-20, True, what_if=0.97)
    assert _nested_first([lagging, drift, backlash], 0.05) == [lagging, drift, backlash]


def test_holm():
    np.testing.assert_allclose(holm([0.01, 0.04, 0.03, 0.5]), [0.04, 0.09, 0.09, 0.5])


def test_misfit_share_separates_a_wrong_model_from_noise():
    """A residual that is a smooth function of the window (the model is wrong alike wherever the logs show
    similar windows) is misfit; white noise is not."""
    assert misfit_share(synthetic()) > 0.9
    assert misfit_share(synthetic(CASES["noise"])) < 0.1


def test_a_small_play_is_named_whatever_its_share():
    """Play acts only at reversals, so a backlash whose closed-loop gap is large can explain under 1 %
    of the differenced residuals (0.3-2.2 % on the diffdrive twin): its test, conditioned on the rows
    before the window, has no share bar. The same residuals without the play show nothing."""
    for seed in (2, 3):
        findings = run_candidates(ResidualSet.of(synthetic(lambda r, rng: 0.005 * r.play[:, 3], seed, 0.2)), ckpt())
        assert findings[0].effect == "backlash" and findings[0].significant, [(f.effect, f.share) for f in findings]
        assert findings[0].share < 0.01 and [f.effect for f in findings if f.significant] == ["backlash"]
        assert not any(f.significant for f in run_candidates(ResidualSet.of(synthetic(None, seed, 0.2)), ckpt()))


def test_a_share_the_model_shows_on_its_own_held_out_logs_counts_only_beyond_it():
    """Logs of another world show what the model misses on its own world too (a window too short for
    the world's own memory). Given the share the memory test finds on the model's held-out logs, memory
    counts for what it explains beyond that: nothing when the two are alike, the rest when the logs
    show more."""
    res = ResidualSet.of(synthetic(lambda r, rng: 0.3 * r.beyond[:, 0]))
    alone = next(f for f in run_candidates(res, ckpt()) if f.effect == "memory_delay")
    assert alone.significant and alone.share > 0.1 and alone.excess == alone.share
    alike = run_candidates(res, ckpt(), held_out={"memory_delay": alone.share})
    memory = next(f for f in alike if f.effect == "memory_delay")
    assert memory.share == alone.share and memory.excess == 0 and not memory.significant
    assert not any(f.significant for f in alike), [(f.effect, f.share) for f in alike]
    less = next(f for f in run_candidates(res, ckpt(), held_out={"memory_delay": alone.share / 2}) if f.significant)
    assert less.effect == "memory_delay" and less.excess == pytest.approx(alone.share / 2)


def test_backlash_is_fixed_with_a_play_channel_of_the_width_found():
    res = synthetic(CASES["backlash"])
    finding = next(f for f in run_candidates(ResidualSet.of(res), ckpt()) if f.effect == "backlash")
    assert finding.fix == {"extras": ("play",), "play_width": PLAY_WIDTHS[3]}


def test_play_offsets_is_a_backlash_filter():
    a = np.array([0.0, 10, 10, 4, 4, -10, 0])
    np.testing.assert_allclose(play_offsets(a, 8.0), [0, -4, -4, 2, 2, 4, -4])
