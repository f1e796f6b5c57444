"""The step noise's shape: unit-variance Student-t draws on both engines, its degrees of freedom
fitted after training on held-out windows, and the setting from the system description or the
command line."""

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
from envi_py.train.step_noise import CANDIDATES, fit_noise_dof, third_differences
from envi_py.twin import TwinProfile, generate

from .test_export import paper_ckpt, with_metadata
from .test_native import LANE, windows


def test_student_t_draws_have_unit_variance_and_heavy_tails():
    model = paper_ckpt("gaussian", noise_dof=(5,)).model
    draws = model.step_noise(torch.Size([200_000, 1]), torch.Generator().manual_seed(0))[:, 0].numpy()
    assert draws.var() == pytest.approx(1.0, abs=0.03)
    assert stats.kurtosis(draws) > 2  # a normal's excess kurtosis is 0; a t5's is 6
    assert stats.kstest(draws / np.sqrt(3 / 5), "t", args=(5,)).pvalue > 0.001


@pytest.mark.parametrize("bad", [(2,), (31,), (4, 4), (3.5,), (True,)])
def test_a_bad_noise_shape_is_refused(bad):
    with pytest.raises(ValueError, match="noise_dof must give each"):
        ModelConfig(n_state=1, n_action=1, head="gaussian", noise_dof=bad)


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
    assert set(record["states"][0]["ks"]) == {str(nu) for nu in CANDIDATES}
    assert ck.config.noise_dof == ((record["states"][0]["dof"],) if record["states"][0]["dof"] else ())
    dof, again = fit_noise_dof(ck, val)
    assert again["states"] == record["states"]
    ck.save(tmp_path / "m.pt")
    assert Checkpoint.load(tmp_path / "m.pt").config.noise_dof == ck.config.noise_dof
    assert ck.record.hyper["step_noise"] == "student-t"
    plain = train("bc", fit, val, seed=0, epochs=3, hidden=(16,), step_noise="gaussian")
    assert plain.config.noise_dof == () and "step_noise" not in plain.record.selection
    deterministic = train("bc", fit, val, seed=0, epochs=3, hidden=(16,), head="deterministic", step_noise="student-t")
    assert deterministic.config.noise_dof == () and "step_noise" not in deterministic.record.hyper
    with pytest.raises(ValueError, match="step noise must be one of gaussian, student-t"):
        train("bc", fit, val, epochs=1, step_noise="laplace")


def test_the_description_sets_the_shape_and_the_command_line_wins(lane_logs, tmp_path, capsys):
    assert load_system("lane-keeping").training.step_noise == "student-t"
    assert load_system("car").training.step_noise == "gaussian"
    assert TrainingDefaults(step_noise="student-t").for_algorithm("random") == {}
    from envi_py.logs import write_log

    for lg in lane_logs[0] + lane_logs[1]:
        write_log(lg, tmp_path / "logs" / f"{lg.meta.run_id}.csv")
    base = ["train", "--logs", str(tmp_path / "logs"), "--epochs", "2", "--hidden", "8", "--quiet"]
    for extra, want in (([], "student-t"), (["--step-noise", "gaussian"], "gaussian")):
        out = tmp_path / f"m{len(extra)}.pt"
        assert main([*base, *extra, "-o", str(out)]) == 0
        assert Checkpoint.load(out).record.hyper["step_noise"] == want
    assert main([*base, "--head", "deterministic", "--step-noise", "student-t", "-o", str(tmp_path / "d.pt")]) == 2
    assert "a Gaussian head's draws" in capsys.readouterr().err


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
    dof, record = fit_noise_dof(ck, world)
    assert ck.config.noise_dof == ()
    got = dof[0]
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
