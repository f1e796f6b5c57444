"""The car twin: logs carry all 11 columns, repeat per seed, are exactly what the declared controller
answers, stay in the declared ranges, see the lead vanish (255) in some runs, and the shipped versions
differ where their gains say they should (paired tests on common random numbers, alpha 0.01)."""

from __future__ import annotations

import argparse

import numpy as np
import pytest
from scipy import stats

from envi_py.controllers import ControllerSpec
from envi_py.logs import load_logs, read_log
from envi_py.system import load_system, pattern_regex
from envi_py.twin import (
    CAR_GAINS,
    CAR_TRAINED,
    CAR_UNSEEN,
    car_versions,
    generate_car,
    generate_car_versions,
    write_car_logs,
)
from envi_py.twin.cli import register

CAR = load_system("car")
ALPHA = 0.01  # significance level of the version-difference tests
RUNS = 20  # runs per version in the statistical tests


@pytest.fixture(scope="module")
def versions_logs():
    """20 runs x 100 rows of each shipped version, all on seed 0: common random numbers, so run r of
    every version meets the same lane, lead and sensor noise and differences are the controller's."""
    return [lg for spec in car_versions() for lg in generate_car(spec, RUNS, 100, seed=0)]


def by_version(logs):
    out: dict[int, list] = {}
    for lg in logs:
        out.setdefault(lg.meta.provenance["version"], []).append(lg)
    return out


def test_logs_round_trip_with_all_eleven_columns(tmp_path):
    logs = generate_car(car_versions()[3], 4, 50, seed=2)
    paths = write_car_logs(logs, tmp_path)
    header = paths[0].read_text().splitlines()[0].split(",")
    assert header == [
        "time",
        "color",
        "distance",
        "steering",
        "speed",
        "steer_p",
        "steer_i",
        "steer_d",
        "speed_p",
        "speed_i",
        "speed_d",
    ]
    back = load_logs(tmp_path)
    assert len(back) == 4
    for lg, bk in zip(logs, sorted(back, key=lambda b: b.meta.provenance["run"])):
        assert bk.meta.schema == CAR.schema
        assert bk.meta.source == "twin" and bk.meta.period_ms == 40.0
        assert ControllerSpec.from_json(bk.meta.controller) == car_versions()[3]
        np.testing.assert_array_equal(bk.time, lg.time)
        np.testing.assert_array_equal(bk.states, lg.states)
        np.testing.assert_array_equal(bk.actions, lg.actions)
        np.testing.assert_array_equal(bk.logged, lg.logged)
        assert bk.logged.shape == (50, 6) and np.abs(bk.logged).sum() > 0


def test_file_names_carry_the_version_gains_and_never_collide(tmp_path):
    logs = generate_car_versions(2, 10, seed=1)
    paths = write_car_logs(logs, tmp_path)
    assert len({p.name for p in paths}) == len(logs) == 10
    rx = pattern_regex("car_{kp_steer}_{kp_speed}_{run}.csv")
    for lg, p in zip(logs, paths):
        m = rx.match(p.name)
        assert m is not None, p.name
        gains = CAR_GAINS[lg.meta.provenance["version"]]
        assert (float(m["kp_steer"]), float(m["kp_speed"])) == gains
    with pytest.raises(ValueError, match="both be written"):
        write_car_logs(logs[:1] + logs[:1], tmp_path / "again")


def test_seeds_repeat_and_differ():
    spec = car_versions()[0]
    a, b, c = (generate_car(spec, 6, 40, seed=s) for s in (5, 5, 6))
    for x, y in zip(a, b):
        np.testing.assert_array_equal(x.values, y.values)
        np.testing.assert_array_equal(x.logged, y.logged)
    assert not np.array_equal(np.stack([x.values for x in a]), np.stack([z.values for z in c]))


@pytest.mark.parametrize("version", range(5))
def test_logged_actions_are_the_declared_controller_from_row_0(tmp_path, version):
    """Rebuilt from the sidecar and reset, the controller reproduces steering, speed and the six PID
    terms on every row: generation resets it right before the first logged row."""
    write_car_logs(generate_car(car_versions()[version], 8, 60, seed=10 + version), tmp_path)
    logs = load_logs(tmp_path)
    ctrl = ControllerSpec.from_json(logs[0].meta.controller).build(2, 2, logs[0].meta.period_ms)
    states = np.stack([lg.states for lg in logs])
    ctrl.reset(len(logs))
    for t in range(states.shape[1]):
        out = ctrl(states[:, t])
        terms = np.concatenate([lp.terms for lp in ctrl.inner.loops], axis=1)
        for r, lg in enumerate(logs):
            np.testing.assert_array_equal(out[r], lg.actions[t], err_msg=f"{lg.name} row {t}")
            np.testing.assert_array_equal(terms[r], lg.logged[t], err_msg=f"{lg.name} row {t}")


def test_replay_detects_wrong_starting_memory():
    """The exact replay above is sensitive: carrying memory from one earlier (warm-up) row breaks it."""
    lg = generate_car(car_versions()[0], 1, 30, seed=3)[0]
    ctrl = ControllerSpec.from_json(lg.meta.controller).build(2, 2, 40.0)
    ctrl.reset(1)
    ctrl(lg.states[:1] + np.array([[10.0, 10.0]]))  # a pretend warm-up row left in memory
    replay = np.concatenate([ctrl(lg.states[t : t + 1]) for t in range(len(lg))])
    assert not np.array_equal(replay, lg.actions)


def test_distance_reads_255_in_some_runs_but_not_all():
    logs = generate_car(car_versions()[1], 40, 100, seed=0)
    dist = np.stack([lg.states[:, 1] for lg in logs])
    lost = (dist == 255).any(1)
    assert 0 < lost.sum() < len(logs)
    # the causes: a lead beyond the echo range, and drop-outs; without both the sensor always answers
    quiet = generate_car(
        car_versions()[1], 40, 100, seed=0, far_start_prob=0.0, dropout_prob=0.0, echo_range=(300.0, 300.0)
    )
    assert not any((lg.states[:, 1] == 255).any() for lg in quiet)
    far = generate_car(car_versions()[1], 10, 5, seed=0, far_start_prob=1.0, warmup=0)
    assert all(lg.states[0, 1] == 255 for lg in far)
    drop = generate_car(
        car_versions()[1], 20, 100, seed=0, far_start_prob=0.0, dropout_prob=0.05, echo_range=(300.0, 300.0)
    )
    hits = np.mean([(lg.states[:, 1] == 255).mean() for lg in drop])
    assert 0.03 < hits < 0.07  # 2000 readings at 5 %: sd 0.5 %


def test_no_run_leaves_the_declared_ranges_and_no_version_collides(versions_logs):
    schema = CAR.schema
    values = np.stack([lg.values for lg in versions_logs])
    assert np.isfinite(values).all() and np.isfinite(np.stack([lg.logged for lg in versions_logs])).all()
    for j, ch in enumerate(schema.channels):
        assert values[..., j].min() >= ch.low and values[..., j].max() <= ch.high, ch.name
        if ch.resolution is not None:
            np.testing.assert_array_equal(values[..., j] % ch.resolution, 0)
    assert all(lg.meta.provenance["contact_ticks"] == 0 for lg in versions_logs)


def test_every_version_meets_the_description_requirements(versions_logs):
    """Stable loops: each version keeps the lane and the distance as car.toml requires, 20 runs each."""
    for v, logs in by_version(versions_logs).items():
        color = np.stack([lg.states[:, 0] for lg in logs])
        dist = np.stack([lg.states[:, 1] for lg in logs])
        assert (np.abs(color - 40).max(1) <= 35).mean() >= 0.9, v
        assert (dist.min(1) >= 10).mean() >= 0.95, v


def closest_approach(lg) -> float:
    """The smallest echo (255 is no echo, not a distance: a run that never saw the lead gets 255)."""
    d = lg.states[:, 1]
    return float(d[d < 255].min()) if (d < 255).any() else 255.0


def test_versions_differ_in_lane_deviation_and_closest_approach(versions_logs):
    """Two goal metrics per run, 20 runs per version: mean |colour - 40| (moved by kp_steer) and the
    closest approach (kp_speed). The runs are paired (same seed), so the tests are paired: Friedman
    over the five versions, and a Wilcoxon signed-rank between the two trained versions that differ
    in that gain, each at alpha 0.01. (Over seeds 0..39 the largest p-values were 1.3e-9 and 1.9e-4
    for Friedman, 8.8e-5 and 4.5e-3 for Wilcoxon: the margin is not luck of seed 0.)"""
    groups = by_version(versions_logs)
    assert sorted(groups) == [0, 1, 2, 3, 4] and all(len(g) == RUNS for g in groups.values())
    for v, g in groups.items():
        assert [lg.meta.provenance["run"] for lg in g] == list(range(RUNS)), v
    dev = np.array([[np.abs(lg.states[:, 0] - 40).mean() for lg in groups[v]] for v in range(5)])
    near = np.array([[closest_approach(lg) for lg in groups[v]] for v in range(5)])
    assert stats.friedmanchisquare(*dev).pvalue < ALPHA
    assert stats.friedmanchisquare(*near).pvalue < ALPHA
    # kp_steer 0.8 vs 2.0 at the same kp_speed: the gentle version strays further from the edge
    assert stats.wilcoxon(dev[0], dev[1]).pvalue < ALPHA
    assert np.median(dev[0]) > np.median(dev[1])
    # kp_speed 18 vs 50: the tight version holds back further when the lead slows or stops
    assert stats.wilcoxon(near[0], near[2]).pvalue < ALPHA
    assert np.median(near[2]) > np.median(near[0])


def test_shipped_versions_follow_the_description_and_unseen_lie_inside():
    specs = car_versions()
    assert len(set(specs)) == 5
    for spec, (ks, kv) in zip(specs, CAR_GAINS):
        assert spec == CAR.controller_for({"kp_steer": ks, "kp_speed": kv})
        assert spec.params["loops"][0]["params"]["kp"] == ks and spec.params["loops"][1]["params"]["kp"] == kv
    assert sorted(CAR_TRAINED + CAR_UNSEEN) == [0, 1, 2, 3, 4]
    tri = np.array([CAR_GAINS[i] for i in CAR_TRAINED])
    for i in CAR_UNSEEN:
        # barycentric coordinates of the unseen point in the trained triangle: all strictly positive
        lam = np.linalg.solve(np.vstack([tri.T, np.ones(3)]), np.array([*CAR_GAINS[i], 1.0]))
        assert (lam > 0).all(), (i, lam)


def test_bad_requests_are_one_clear_error():
    spec = car_versions()[0]
    with pytest.raises(ValueError, match="positive"):
        generate_car(spec, 0)
    with pytest.raises(ValueError, match="unknown world parameter 'warp'"):
        generate_car(spec, 1, warp=1.0)
    with pytest.raises(ValueError, match="probability"):
        generate_car(spec, 1, dropout_prob=2.0)
    with pytest.raises(ValueError, match="pair"):
        generate_car(spec, 1, echo_range=100.0)
    with pytest.raises(ValueError, match="non-negative"):
        generate_car(spec, 1, motor_tau_s=float("nan"))
    with pytest.raises(ValueError, match="two PID loops"):
        generate_car(
            ControllerSpec("combine", {"loops": [{"name": "pid", "params": {}}, {"name": "bang-bang", "params": {}}]}),
            1,
        )
    with pytest.raises(ValueError, match="no version 7"):
        generate_car_versions(1, versions=[7])


def _parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser()
    register(p.add_subparsers(dest="command"))
    return p


def _run(argv: list[str]) -> int:
    args = _parser().parse_args(argv)
    return args.func(args)


def test_cli_generates_car_versions_and_keeps_lane_keeping_the_default(tmp_path, capsys):
    assert (
        _run(["twin", "generate", "--system", "car", "--runs", "2", "--steps", "20", "--out", str(tmp_path / "all")])
        == 0
    )
    assert len(list((tmp_path / "all").glob("car_*.csv"))) == 10
    assert (
        _run(
            [
                "twin",
                "generate",
                "--system",
                "car",
                "--param",
                "kp_steer=1",
                "kp_speed=20",
                "--runs",
                "3",
                "--steps",
                "20",
                "--out",
                str(tmp_path / "one"),
            ]
        )
        == 0
    )
    assert sorted(p.name for p in (tmp_path / "one").glob("*.csv")) == [f"car_1_20_{r}.csv" for r in range(3)]
    assert (
        _run(
            [
                "twin",
                "generate",
                "--system",
                "car",
                "--version",
                "3",
                "4",
                "--world",
                "dropout_prob=0",
                "--runs",
                "1",
                "--steps",
                "20",
                "--out",
                str(tmp_path / "unseen"),
            ]
        )
        == 0
    )
    names = sorted(p.name for p in (tmp_path / "unseen").glob("*.csv"))
    assert names == sorted(f"car_{ks:g}_{kv:g}_0.csv" for ks, kv in (CAR_GAINS[3], CAR_GAINS[4]))
    assert _run(["twin", "generate", "--runs", "2", "--steps", "15", "--out", str(tmp_path / "lane")]) == 0
    lane = read_log(next((tmp_path / "lane").glob("*.csv")))
    assert lane.meta.schema.columns == ["time", "color", "angle"] and lane.meta.controller["name"] == "lane-keeping"
    capsys.readouterr()
    for bad in (
        ["--system", "car", "--effects", "noise=1"],
        ["--system", "car", "--world", "warp=1"],
        ["--system", "car", "--version", "9"],
        ["--system", "car", "--version", "1", "--param", "kp_steer=1"],
        ["--version", "1"],
    ):
        assert _run(["twin", "generate", *bad, "--out", str(tmp_path / "bad")]) == 2, bad
        err = capsys.readouterr().err.strip()
        assert err.startswith("envi twin generate: ") and "\n" not in err, err
    assert not (tmp_path / "bad").exists()


def test_pattern_reads_versions_from_names_without_sidecars(tmp_path):
    """Files named by write_car_logs tell their version even when the sidecars are lost."""
    write_car_logs(generate_car_versions(1, 10, seed=4, versions=[0, 4]), tmp_path)
    for side in tmp_path.glob("*.meta.json"):
        side.unlink()
    logs = load_logs(tmp_path, CAR)
    versions = [CAR.version_of(lg.controller) for lg in logs]
    assert sorted((v["kp_steer"], v["kp_speed"]) for v in versions) == sorted([CAR_GAINS[0], CAR_GAINS[4]])
