"""The step noise's shape: unit-variance Student-t and two-scale normal draws on both engines, the
shape fitted after training on held-out windows, and the setting from the system description or
the command line."""

from __future__ import annotations


import numpy as np
import pytest
import torch
from scipy import stats

from envi_py import native
from envi_py.cli import main
from envi_py.export import read_metadata, export
from envi_py.model import Checkpoint, ModelConfig
from envi_py.simulate import rollout
from envi_py.system import TrainingDefaults, load_system
from envi_py.train import train
from envi_py.simulate import simulate_versions
from envi_py.train.step_noise import CANDIDATES, FAMILIES, Shape, fit_noise_shape, set_shape, third_differences
from envi_py.twin import TwinProfile, generate

from .test_export import paper_ckpt, with_metadata
from .test_native import LANE, windows


def test_student_t_draws_have_unit_variance_and_heavy_tails():
    model = paper_ckpt("gaussian", noise_dof=(5,)).model
    draws = model.step_noise(torch.Size([200_000, 1]), torch.Generator().manual_seed(0))[:, 0].numpy()
    assert draws.var() == pytest.approx(1.0, abs=0.03)
    assert stats.kurtosis(draws) > 2  # a normal's excess kurtosis is 0; a t5's is 6
    assert stats.kstest(draws / np.sqrt(3 / 5), "t", args=(5,)).pvalue > 0.001


def test_two_scale_draws_have_unit_variance_and_a_share_of_wide_steps():
    """A share p = 0.05 at k = 4 times the scale: variance 1, and the normal's 0.27 % beyond 3 sd
    becomes about 5 % x P(|z| > 3 / (4 s)) = 1.6 % (s = 0.76, the narrow steps' scale)."""
    model = paper_ckpt("gaussian", noise_mix=((0.05, 4.0),)).model
    draws = model.step_noise(torch.Size([200_000, 1]), torch.Generator().manual_seed(0))[:, 0].numpy()
    assert draws.var() == pytest.approx(1.0, abs=0.03)
    s = 1 / np.sqrt(1 - 0.05 + 0.05 * 16)
    want = 0.95 * 2 * stats.norm.sf(3 / s) + 0.05 * 2 * stats.norm.sf(3 / (4 * s))
    assert np.mean(np.abs(draws) > 3) == pytest.approx(want, rel=0.08)
    assert np.mean(np.abs(draws) < 0.5 * s) == pytest.approx(
        0.95 * (1 - 2 * stats.norm.sf(0.5)) + 0.05 * (1 - 2 * stats.norm.sf(0.125)), rel=0.03
    )


@pytest.mark.parametrize("bad", [(2,), (31,), (4, 4), (3.5,), (True,)])
def test_a_bad_noise_shape_is_refused(bad):
    with pytest.raises(ValueError, match="noise_dof must give each"):
        ModelConfig(n_state=1, n_action=1, head="gaussian", noise_dof=bad)


@pytest.mark.parametrize(
    "bad", [((0.5, 4.0),), ((0.05, 1.0),), ((0.05, 21.0),), ((0.0, 4.0),), ((0.1, 2.0), (0.1, 2.0))]
)
def test_a_bad_two_scale_shape_is_refused(bad):
    with pytest.raises(ValueError, match="noise_mix must give each"):
        ModelConfig(n_state=1, n_action=1, head="gaussian", noise_mix=bad)


def test_a_state_takes_one_shape_not_two():
    with pytest.raises(ValueError, match="not both"):
        ModelConfig(n_state=1, n_action=1, head="gaussian", noise_dof=(5,), noise_mix=((0.05, 4.0),))
    ok = ModelConfig(n_state=2, n_action=1, head="gaussian", noise_dof=(5, 0), noise_mix=((0.0, 1.0), (0.05, 4.0)))
    assert ok.noise_mix == ((0.0, 1.0), (0.05, 4.0))


@pytest.mark.skipif(not native.available(), reason="native engine not built")
def test_both_engines_draw_the_same_student_t_step(tmp_path):
    """20,000 one-step draws a side: the same distribution (KS), the same spread as normal draws, and
    three times the normal's share beyond 3 sd (a unit-variance t6 puts 1.0 % there, a normal 0.27 %)."""
    ck = paper_ckpt("gaussian", clamp=False, noise_dof=(6,))
    init = windows(1)
    py = rollout(ck, LANE, init, 1, runs=20_000, seed=2)[:, 10, 0]
    cc = native.rollout(ck, LANE, init, 1, runs=20_000, seed=2)[:, 10, 0]
    assert stats.ks_2samp(py, cc).pvalue > 0.001
    assert cc.std() == pytest.approx(py.std(), rel=0.03)
    normal = native.rollout(paper_ckpt("gaussian", clamp=False), LANE, init, 1, runs=20_000, seed=2)[:, 10, 0]
    assert cc.std() == pytest.approx(normal.std(), rel=0.03)

    def beyond_3sd(x: np.ndarray) -> float:
        return float(np.mean(np.abs(x - np.median(x)) > 3 * normal.std()))

    assert beyond_3sd(cc) > 0.006 and beyond_3sd(py) > 0.006 and beyond_3sd(normal) < 0.0045
    path = export(ck, tmp_path / "m.onnx")
    assert read_metadata(path)["envi.noise_dof"] == [6]
    want = native.rollout(ck, LANE, init, 5, runs=3, seed=1)
    np.testing.assert_array_equal(native.rollout(path, LANE, init, 5, runs=3, seed=1), want)


@pytest.mark.skipif(not native.available(), reason="native engine not built")
@pytest.mark.parametrize("value", [[2], [4, 4], [3.5], ["4"]])
def test_the_loader_refuses_a_bad_noise_shape(value):
    with pytest.raises(ValueError, match="envi.noise_dof"):
        native.load(with_metadata(paper_ckpt("gaussian"), "envi.noise_dof", value))


@pytest.mark.skipif(not native.available(), reason="native engine not built")
def test_both_engines_draw_the_same_two_scale_step(tmp_path):
    """20,000 one-step draws a side: the same distribution (KS), the same spread as normal draws, and
    the wide steps' share beyond 3 sd (1.6 % at p = 0.05, k = 4; a normal's 0.27 %)."""
    ck = paper_ckpt("gaussian", clamp=False, noise_mix=((0.05, 4.0),))
    init = windows(1)
    py = rollout(ck, LANE, init, 1, runs=20_000, seed=2)[:, 10, 0]
    cc = native.rollout(ck, LANE, init, 1, runs=20_000, seed=2)[:, 10, 0]
    assert stats.ks_2samp(py, cc).pvalue > 0.001
    normal = native.rollout(paper_ckpt("gaussian", clamp=False), LANE, init, 1, runs=20_000, seed=2)[:, 10, 0]
    assert cc.std() == pytest.approx(normal.std(), rel=0.03) and py.std() == pytest.approx(normal.std(), rel=0.03)

    def beyond_3sd(x: np.ndarray) -> float:
        return float(np.mean(np.abs(x - np.median(x)) > 3 * normal.std()))

    assert beyond_3sd(cc) > 0.012 and beyond_3sd(py) > 0.012 and beyond_3sd(normal) < 0.0045
    path = export(ck, tmp_path / "m.onnx")
    assert read_metadata(path)["envi.noise_mix"] == [[0.05, 4.0]]
    want = native.rollout(ck, LANE, init, 5, runs=3, seed=1)
    np.testing.assert_array_equal(native.rollout(path, LANE, init, 5, runs=3, seed=1), want)


@pytest.mark.skipif(not native.available(), reason="native engine not built")
@pytest.mark.parametrize("value", [[[0.5, 4]], [[0.05, 1]], [[0.05, 21]], [0.05], [[0.05, 4], [0.05, 4]], [["a", 4]]])
def test_the_loader_refuses_a_bad_two_scale_shape(value):
    with pytest.raises(ValueError, match="envi.noise_mix"):
        native.load(with_metadata(paper_ckpt("gaussian"), "envi.noise_mix", value))


@pytest.mark.skipif(not native.available(), reason="native engine not built")
def test_the_loader_refuses_two_shapes_for_one_state():
    ck = paper_ckpt("gaussian", noise_dof=(5,))
    with pytest.raises(ValueError, match="both shape state 0"):
        native.load(with_metadata(ck, "envi.noise_mix", [[0.05, 4]]))


@pytest.fixture(scope="module")
def lane_logs():
    logs = generate(LANE, 8, 60, {"noise": 2.0}, seed=0, profile=TwinProfile())
    return logs[:6], logs[6:]


def test_training_fits_the_shape_on_the_validation_logs_and_records_it(lane_logs, tmp_path):
    fit, val = lane_logs
    ck = train("bc", fit, val, seed=0, epochs=3, hidden=(16,), step_noise="student-t", members=1)  # one model's fit
    record = ck.record.selection["step_noise"]
    assert record["on"] == "validation" and record["logs"] == [lg.name for lg in val]
    assert record["states"][0]["real_differences"] == sum(len(lg) - 10 - 3 for lg in val)
    assert set(record["states"][0]["ks"]) == {f"t{nu}" if nu else "normal" for nu in CANDIDATES}
    assert ck.config.noise_dof == ((record["states"][0]["dof"],) if record["states"][0]["dof"] else ())
    assert record["family"] == "student-t" and ck.config.noise_mix == ()
    _, again = fit_noise_shape(ck, val)
    assert again["states"] == record["states"]
    ck.save(tmp_path / "m.pt")
    assert Checkpoint.load(tmp_path / "m.pt").config.noise_dof == ck.config.noise_dof
    assert ck.record.hyper["step_noise"] == "student-t"
    plain = train("bc", fit, val, seed=0, epochs=3, hidden=(16,), step_noise="gaussian")
    assert plain.config.noise_dof == () and "step_noise" not in plain.record.selection
    deterministic = train("bc", fit, val, seed=0, epochs=3, hidden=(16,), head="deterministic", step_noise="student-t")
    assert deterministic.config.noise_dof == () and "step_noise" not in deterministic.record.hyper
    mixed = train("bc", fit, val, seed=0, epochs=3, hidden=(16,), step_noise="two-scale", members=1)
    state = mixed.record.selection["step_noise"]["states"][0]
    assert len(state["ks"]) == len(FAMILIES["two-scale"]) and mixed.config.noise_dof == ()
    assert mixed.config.noise_mix == ((tuple(state["mix"]),) if state["mix"][0] else ())
    assert Shape(mix=tuple(state["mix"])).label == state["shape"]
    with pytest.raises(ValueError, match="step noise must be one of gaussian, student-t, two-scale"):
        train("bc", fit, val, epochs=1, step_noise="laplace")


def test_the_description_sets_the_shape_and_the_command_line_wins(lane_logs, tmp_path, capsys):
    assert load_system("lane-keeping").training.step_noise == "student-t"
    assert load_system("car").training.step_noise == "gaussian"
    assert TrainingDefaults(step_noise="student-t").for_algorithm("random") == {}
    from envi_py.logs import write_log

    for lg in lane_logs[0] + lane_logs[1]:
        write_log(lg, tmp_path / "logs" / f"{lg.meta.run_id}.csv")
    base = ["train", "--logs", str(tmp_path / "logs"), "--epochs", "2", "--hidden", "8", "--quiet"]
    cases = (
        ([], "student-t"),
        (["--step-noise", "two-scale"], "two-scale"),
        (["--step-noise", "gaussian"], "gaussian"),
    )
    for k, (extra, want) in enumerate(cases):
        out = tmp_path / f"m{k}.pt"
        assert main([*base, *extra, "-o", str(out)]) == 0
        ck = Checkpoint.load(out)
        assert ck.record.hyper["step_noise"] == want
        fit = ck.record.selection.get("step_noise")
        shown = f"color: {fit['states'][0]['shape']}" if fit else "| - |"
        assert shown in out.with_suffix(".training.md").read_text(), want  # the report says what was fitted
    assert main([*base, "--head", "deterministic", "--step-noise", "two-scale", "-o", str(tmp_path / "d.pt")]) == 2
    assert "--step-noise two-scale shapes a Gaussian head's draws" in capsys.readouterr().err


@pytest.fixture(scope="module")
def small_model(lane_logs):
    fit, val = lane_logs
    return train("bc", fit, val, seed=0, epochs=20, hidden=(16,), step_noise="gaussian")


@pytest.mark.parametrize("truth, low, high", [(3, 3, 4), (0, 12, 0)])
def test_the_closed_loop_fit_finds_the_shape_of_a_world_that_is_the_model(small_model, lane_logs, truth, low, high):
    """Logs simulated by the model itself with a known step-noise shape stand for the real ones: the
    fit, simulating the same model from their sigma_0, finds that shape (a t3 as 3 or 4; normal draws
    as the normal or a t of 12 or more) and leaves the model's own shape as it was. 160 world logs: with
    48 the fit took a t4 world for a t12 once in three seeds."""
    ck = small_model
    ck.config.noise_dof = (truth,) if truth else ()
    world = simulate_versions(ck, lane_logs[0] + lane_logs[1], runs=20, seed=123)
    ck.config.noise_dof = ()
    shapes, record = fit_noise_shape(ck, world)
    assert ck.config.noise_dof == ()
    got = shapes[0].dof
    if truth:
        assert low <= got <= high, record
    else:
        assert got == 0 or got >= low, record


def test_third_differences_leave_out_limit_readings_and_breaks():
    from envi_py.logs import Log, LogMeta

    states = np.array([[0.0], [1.0], [3.0], [6.0], [10.0], [15.0], [255.0], [21.0], [28.0], [36.0]])
    log = Log(None, np.arange(10) * 40.0, states, np.zeros((10, 1)), LogMeta(breaks=(8,)))
    # differences start at rows 0..6: those at 5, 6 span the break before row 8, those at 3..6 touch
    # the 255 of row 6; rows 0..5 are triangular numbers, whose third difference is 0
    assert third_differences([log], 0, 0, [255.0]).tolist() == [0.0, 0.0, 0.0]
    assert len(third_differences([log], 0, 0, [])) == 5
    assert len(third_differences([log], 0, 4, [])) == 1  # from row 4: starts 4..6, not 5 or 6


@pytest.mark.parametrize("truth", [(0.05, 6.0), (0.0, 1.0)])
def test_the_closed_loop_fit_finds_a_two_scale_world(small_model, lane_logs, truth):
    """As above for the two-scale family: a world of the model drawing 5 % of its steps at 6x the
    scale is fitted as a share of 3-10 % at 4-8x, not as the normal; a normal world as the normal or
    a mild mixture (at most 2 % of steps at 2.5-3x, whose third differences a few hundred rows cannot
    tell from a normal's)."""
    ck = small_model
    set_shape(ck, [Shape(mix=truth)])
    world = simulate_versions(ck, lane_logs[0] + lane_logs[1], runs=20, seed=123)
    set_shape(ck, [Shape()])
    shapes, record = fit_noise_shape(ck, world, "two-scale")
    assert ck.config.noise_mix == () and record["family"] == "two-scale"
    p, k = shapes[0].mix
    if truth[0]:
        assert 0.03 <= p <= 0.1 and 4 <= k <= 8, record["states"][0]["shape"]
    else:
        assert p == 0 or (p <= 0.02 and k <= 3), record["states"][0]["shape"]


def test_the_training_report_names_the_fitted_shape_of_old_and_new_records():
    from envi_py.report.training import fitted_step_noise

    new = {"step_noise": {"states": [{"state": "color", "shape": "5% x4", "dof": 0, "mix": [0.05, 4.0]}]}}
    old = {"step_noise": {"states": [{"state": "color", "dof": 3}, {"state": "angle", "dof": 0}]}}
    assert fitted_step_noise(new) == "color: 5% x4"
    assert fitted_step_noise(old) == "color: t3, angle: normal"
    assert fitted_step_noise({}) == "-"
