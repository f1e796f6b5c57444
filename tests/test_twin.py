"""The physics twin: effects act as they should, seeds repeat, logs validate, the shipped fit holds."""

from __future__ import annotations

import argparse
import json
import numpy as np
import pytest

from envi_py.controllers import ControllerSpec
from envi_py.logs import load_logs, read_log
from envi_py.system import lane_keeping
from envi_py.twin import EFFECTS, TwinProfile, TwinWorld, default_profile, generate, parse_effects, resolve, write_logs
from envi_py.twin.cli import register

BARE = TwinProfile()  # no effects: every test switches on exactly what it checks
LOOP = TwinProfile(effects={"delay": 1, "rate_limit": 800})  # a realistic limit cycle to change
LK = ControllerSpec("lane-keeping", {"x": 30})
STRAIGHT = ControllerSpec("pid", {"kp": 0.0})  # angle 0 always: the trajectory does not see the sensor


class DitherSteer:
    """Lane keeping plus a large independent random angle: an excitation whose effect can be traced."""

    def __init__(self, seed: int = 0) -> None:
        self.rng = np.random.default_rng(int(seed))
        self.last = np.zeros((0, 1))

    def reset(self, n: int) -> None:
        self.last = np.zeros((n, 1))

    def __call__(self, states: np.ndarray) -> np.ndarray:
        # within the steering's declared range, which the twin holds every controller to
        self.last = np.clip(20 * self.rng.standard_normal((states.shape[0], 1)), -80, 80)
        return np.sign(states[:, :1] - 40) * 10 + self.last


def arrays(logs):
    return (
        np.stack([lg.states[:, 0] for lg in logs]),
        np.stack([lg.actions[:, 0] for lg in logs]),
        np.stack([lg.time for lg in logs]),
    )


def crossings(color: np.ndarray) -> float:
    above = color > 40
    return float((above[:, 1:] != above[:, :-1]).sum(1).mean())


def test_seeds_repeat_and_differ():
    a = arrays(generate(LK, 20, 60, {"noise": 1.0, "jitter": 2.0}, seed=3, profile=BARE))
    b = arrays(generate(LK, 20, 60, {"noise": 1.0, "jitter": 2.0}, seed=3, profile=BARE))
    c = arrays(generate(LK, 20, 60, {"noise": 1.0, "jitter": 2.0}, seed=4, profile=BARE))
    for u, v in zip(a, b):
        np.testing.assert_array_equal(u, v)
    assert not np.array_equal(a[0], c[0])


def test_logs_round_trip_through_the_validator(tmp_path):
    logs = generate(LK, 5, 50, {"delay": 2, "noise": 1.5}, seed=1)
    paths = write_logs(logs, tmp_path)
    for lg, p in zip(logs, paths):
        back = read_log(p)
        np.testing.assert_array_equal(back.states, lg.states)
        np.testing.assert_array_equal(back.time, lg.time)
        assert back.meta.source == "twin"
        prov = back.meta.provenance
        assert prov["effects"]["delay"]["ticks"] == 2 and prov["effects"]["noise"]["sigma"] == 1.5
        assert prov["injected"] == ["delay", "noise"] and prov["seed"] == 1
        assert back.meta.controller == {"name": "lane-keeping", "params": {"x": 30}}
    assert load_logs(tmp_path, lane_keeping().with_pattern("twin_{x}_{run}.csv"))[0].param["x"] == 30


def test_thousands_of_runs_in_seconds():
    import time

    t = time.monotonic()
    logs = generate(LK, 3000, 100, None, seed=0)
    assert len(logs) == 3000 and time.monotonic() - t < 10


@pytest.mark.parametrize("k", [1, 2, 3])
def test_delay_shifts_the_cross_correlation_peak_by_k(k):
    """The random part of the angle first moves the colour k ticks later with a delay of k ticks."""

    def peak(effects):
        logs = generate(ControllerSpec("tests.test_twin:DitherSteer", {"seed": 5}), 300, 100, effects, 0, BARE)
        color, angle, _ = arrays(logs)
        lane = np.sign(color - 40) * 10
        e = angle - lane  # the dither
        dc = np.diff(color, axis=1)
        corr = [abs(np.corrcoef(e[:, 5:80].ravel(), dc[:, 5 + lag : 80 + lag].ravel())[0, 1]) for lag in range(6)]
        return int(np.argmax(corr))

    assert peak({"delay": k}) - peak(None) == k


def test_quantisation_yields_integers_and_its_absence_does_not():
    plain, _, _ = arrays(generate(LK, 10, 50, None, 0, BARE))
    q, _, _ = arrays(generate(LK, 10, 50, {"quantise": 1}, 0, BARE))
    q5, _, _ = arrays(generate(LK, 10, 50, {"quantise": 5}, 0, BARE))
    assert not np.all(plain == np.round(plain))
    assert np.all(q == np.round(q))
    assert np.all(q5 % 5 == 0)


@pytest.mark.parametrize("sigma", [0.7, 2.0])
def test_noise_adds_its_variance(sigma):
    """Straight driving (angle 0) makes the trajectory independent of the readings, so the
    difference of the noisy and clean readings is the noise alone."""
    clean, _, _ = arrays(generate(STRAIGHT, 400, 100, None, 7, BARE))
    noisy, _, _ = arrays(generate(STRAIGHT, 400, 100, {"noise": sigma}, 7, BARE))
    inside = (clean > 10) & (clean < 70)  # away from the 0..100 clip
    assert np.var((noisy - clean)[inside]) == pytest.approx(sigma**2, rel=0.05)


def test_glitches_are_rare_outliers_at_their_rate():
    clean, _, _ = arrays(generate(STRAIGHT, 400, 100, None, 7, BARE))
    glitchy, _, _ = arrays(generate(STRAIGHT, 400, 100, {"glitch": 0.02}, 7, BARE))
    assert np.mean(np.abs(glitchy - clean) > 1e-9) == pytest.approx(0.02, rel=0.15)


def test_lowpass_smooths_the_reading():
    sharp, _, _ = arrays(generate(LK, 300, 100, None, 0, BARE))
    smooth, _, _ = arrays(generate(LK, 300, 100, {"lowpass": 80}, 0, BARE))
    rough = lambda c: np.abs(np.diff(c, n=2, axis=1)).mean() / c.std()  # noqa: E731
    assert rough(smooth) < 0.8 * rough(sharp)


def test_saturation_clips_the_range():
    c, _, _ = arrays(generate(LK, 50, 100, {"saturation": {"low": 30, "high": 50}}, 0, BARE))
    assert c.min() == 30 and c.max() == 50 and np.mean(c == 50) > 0.05


@pytest.mark.parametrize("effect", ["delay", "lag", "rate_limit"])
def test_later_or_slower_steering_lengthens_the_limit_cycle(effect):
    """The bang-bang oscillation's period is set by how late and how fast the steering reacts."""
    strong = {"delay": 2, "lag": 80, "rate_limit": 300}
    base, _, _ = arrays(generate(LK, 200, 100, None, 0, LOOP))
    slow, _, _ = arrays(generate(LK, 200, 100, {effect: strong[effect]}, 0, LOOP))
    assert crossings(slow) < 0.85 * crossings(base)


@pytest.mark.parametrize("effect", ["backlash", "deadzone", "patches"])
def test_weaker_steering_shrinks_the_oscillation(effect):
    """Lost steering angle or grip turns the robot less per period, so it strays less from the edge."""
    strong = {"backlash": 30, "deadzone": 15, "patches": {"per_m": 5, "length_mm": 150, "grip": 0.3}}
    base, _, _ = arrays(generate(LK, 200, 100, None, 0, LOOP))
    weak, _, _ = arrays(generate(LK, 200, 100, {effect: strong[effect]}, 0, LOOP))
    assert weak.std() < 0.9 * base.std()


def test_battery_sag_shrinks_the_oscillation_within_the_run():
    sag, _, _ = arrays(generate(LK, 300, 100, {"battery": 0.7}, 0, LOOP))
    flat, _, _ = arrays(generate(LK, 300, 100, None, 0, LOOP))
    ratio = lambda c: c[:, 50:].std() / c[:, :50].std()  # noqa: E731
    assert ratio(sag) < 0.85 * ratio(flat)


def test_run_variation_spreads_runs_apart():
    same, _, _ = arrays(generate(LK, 200, 100, None, 0, LOOP))
    varied, _, _ = arrays(generate(LK, 200, 100, {"run_variation": {"speed_sd": 0.2, "white_sd": 6}}, 0, LOOP))
    assert np.percentile(varied, 95, axis=1).std() > 2 * np.percentile(same, 95, axis=1).std()


def test_curvature_biases_the_steering():
    _, straight, _ = arrays(generate(LK, 200, 100, None, 0, LOOP))
    _, curved, _ = arrays(generate(LK, 200, 100, {"curvature": {"mean_per_m": 3, "amp_per_m": 0}}, 0, LOOP))
    assert abs(np.mean(np.sign(curved))) > abs(np.mean(np.sign(straight))) + 0.2


def test_jitter_and_pauses_in_the_time_stamps():
    _, _, t = arrays(generate(LK, 200, 100, {"jitter": {"extra_ms": 2, "pause_prob": 0.01}}, 0, BARE))
    _, _, t0 = arrays(generate(LK, 200, 100, None, 0, BARE))
    dt, dt0 = np.diff(t, axis=1), np.diff(t0, axis=1)
    assert np.all(dt0 == BARE.period_ms) and np.all(t0[:, 0] == 0)
    assert dt.min() == BARE.period_ms and np.all(dt == np.round(dt))
    assert np.mean(dt > 1000) == pytest.approx(0.01, rel=0.3)
    assert np.mean(dt[dt < 1000]) - BARE.period_ms == pytest.approx(1 / (np.exp(1 / 2) - 1), rel=0.1)


def test_effect_parsing_and_errors():
    e = parse_effects("delay=2,noise=1.5,jitter.pause_prob=0.01,glitch")
    r = resolve({}, e)
    assert r["delay"]["ticks"] == 2 and r["jitter"]["pause_prob"] == 0.01 and r["glitch"] == {"prob": 0.01}
    assert "noise" not in resolve({"noise": 1.0}, {"noise": 0})
    with pytest.raises(ValueError, match="unknown twin effect"):
        parse_effects("nosie=1")
    with pytest.raises(ValueError, match="unknown parameter"):
        resolve({}, {"noise": {"sd": 1}})
    for eff in EFFECTS.values():
        assert eff.primary in eff.params and all(p.unit for p in eff.params.values())


def test_twin_world_steps_like_the_batch():
    w = TwinWorld(seed=2)
    first = [w.read_color()]
    for _ in range(50):
        c = first[-1]
        w.apply(30.0 if c > 40 else -30.0, 0.041)
        first.append(w.read_color())
    w.reset()
    again = [w.read_color()]
    for _ in range(50):
        c = again[-1]
        w.apply(30.0 if c > 40 else -30.0, 0.041)
        again.append(w.read_color())
    assert first == again and 0 <= min(first) and max(first) <= 100
    assert len({c > 40 for c in first}) == 2  # it crosses the edge: the loop keeps the lane
    assert set(w.state) == {"y_mm", "psi_rad", "delta_deg", "s_mm"}


def _parser():
    p = argparse.ArgumentParser()
    register(p.add_subparsers(dest="command"))
    return p


def test_cli_generate_and_effects(tmp_path, capsys):
    args = _parser().parse_args(
        [
            "twin",
            "generate",
            "--controller",
            "lane-keeping",
            "--param",
            "x=20",
            "--runs",
            "3",
            "--steps",
            "40",
            "--effects",
            "delay=2,noise=1.5",
            "--seed",
            "1",
            "--out",
            str(tmp_path),
        ]
    )
    assert args.func(args) == 0
    logs = load_logs(tmp_path)
    assert len(logs) == 3 and logs[0].param == {"x": 20.0}
    assert _parser().parse_args(["twin", "effects"]).func(_parser().parse_args(["twin", "effects"])) == 0
    assert "rate_limit" in capsys.readouterr().out
    bad = _parser().parse_args(["twin", "generate", "--effects", "warp=9", "--out", str(tmp_path / "fresh")])
    assert bad.func(bad) == 2 and "warp" in capsys.readouterr().err  # the effect refused, not the folder


def test_cli_default_logs_name_their_version(tmp_path):
    """Without --param the logs record the controller's default x: every command reads logs by version,
    and logs of ``lane-keeping()`` were refused by check, verify and diagnose ("has no version parameter x")."""
    args = _parser().parse_args(["twin", "generate", "--runs", "2", "--steps", "30", "--out", str(tmp_path)])
    assert args.func(args) == 0
    system = lane_keeping()
    logs = load_logs(tmp_path, system=system)
    assert [lg.param for lg in logs] == [{"x": 30.0}] * 2
    assert {system.version_label(lg.controller) for lg in logs} == {"x=30"}


def test_version_defaults_leave_given_and_unregistered_parameters_alone():
    system = lane_keeping()
    given = ControllerSpec("lane-keeping", {"x": 20.0})
    assert system.with_version_defaults(given) is given
    assert system.with_version_defaults(ControllerSpec("bang-bang", {"threshold": 35.0})).params == {
        "threshold": 35.0,
        "x": 30.0,
    }
    user = ControllerSpec("mypkg.ctrl:Steer", {})
    assert system.with_version_defaults(user) is user


def test_cli_calibrate_runs_end_to_end(tmp_path, real_dir):
    args = _parser().parse_args(
        [
            "twin",
            "calibrate",
            "--logs",
            str(real_dir),
            "--pattern",
            "log_{x}_1{run}.csv",
            "--budget",
            "2",
            "--quiet",
            "--out",
            str(tmp_path),
        ]
    )
    assert args.func(args) == 0
    prof = TwinProfile.load(tmp_path / "profile.json")
    assert set(prof.fit["headline"]) == {"10", "20", "30", "40", "50"}
    assert prof.effects["quantise"] == {"step": 1.0} and prof.effects["jitter"]["extra_ms"] > 0
    summary = json.loads((tmp_path / "report.json").read_text())
    assert (tmp_path / "traces.png").stat().st_size > 10000 and "30" in summary["versions"]


def test_shipped_profile_reproduces_its_reported_fit(real_logs):
    from envi_py.twin.report import fit_summary, headline

    prof = default_profile()
    assert prof.fit, "the shipped profile carries its calibration summary"
    again = headline(fit_summary(prof, real_logs, prof.fit["key"], seed=prof.fit["seed"])[0])
    for x, h in prof.fit["headline"].items():
        assert again[x]["within_2x"] == h["within_2x"]
        for k in ("median_w1_ratio", "period_twin", "amplitude_twin"):
            assert again[x][k] == pytest.approx(h[k], rel=1e-6)


def test_profile_save_load_and_search_space_round_trip(tmp_path):
    from envi_py.twin.calibrate import SPACE, from_profile, to_profile

    prof = default_profile()
    assert TwinProfile.load(prof.save(tmp_path / "p.json")) == prof
    base = prof.replace(effects={k: prof.effects[k] for k in ("jitter", "quantise")})
    back = to_profile(from_profile(prof), base)
    assert back.effects == prof.effects
    for name, *_ in SPACE:
        if "." not in name:
            assert getattr(back, name) == pytest.approx(getattr(prof, name), rel=1e-4)
    with pytest.raises(ValueError, match="unknown field"):
        TwinProfile.from_json({"speed": 1.0, "sped": 2.0})


def test_cli_generates_the_second_world_family(tmp_path, capsys):
    """``--family diffdrive`` writes the differential-drive world's logs (the diagnosis's cross-world check)
    with the same schema and pattern, its injected effect in the sidecar; a steered-only option is refused."""
    out = tmp_path / "dd"
    args = _parser().parse_args(
        ["twin", "generate", "--family", "diffdrive", "--param", "x=40", "--runs", "2", "--steps", "30"]
        + ["--effects", "delay=2", "--out", str(out)]
    )
    assert args.func(args) == 0
    logs = load_logs(out, lane_keeping())
    assert len(logs) == 2 and logs[0].param == {"x": 40.0} and logs[0].states.shape == (30, 1)
    assert logs[0].meta.provenance["world"] == "diffdrive" and logs[0].meta.provenance["injected"] == ["delay"]
    assert "diffdrive twin logs" in capsys.readouterr().out
    for extra in (["--profile", "p.json"], ["--system", "car"]):
        bad = _parser().parse_args(["twin", "generate", "--family", "diffdrive", *extra, "--out", str(tmp_path / "x")])
        assert bad.func(bad) == 2
        assert "envi twin generate:" in capsys.readouterr().err
