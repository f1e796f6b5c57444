"""Effect layers on both engines: the C++ engine (cpp/src/engine.cpp) against its Python twin
(envi_py.effect_layers.LayerStack in envi_py.simulate.rollout), the export that carries them, the
loader that checks them, and the commands that take a layers file."""

from __future__ import annotations

import json
import subprocess

import numpy as np
import pytest
import torch
from scipy import stats

from envi_py import native
from envi_py.cli import main as envi_main
from envi_py.effect_layers import Layer, describe, read_layers
from envi_py.export import read_metadata
from envi_py.export_cli import main as export_main
from envi_py.logs import load_logs, read_log, write_log
from envi_py.simulate import initial_windows, rollout
from envi_py.system import lane_keeping

from .test_export import paper_ckpt, with_metadata
from .test_native import LANE, PID, envi_sim, windows

pytestmark = pytest.mark.skipif(not native.available(), reason="native engine not built")

#: every deterministic layer, a delay longer than sigma_0 (its first commands are sigma_0's first),
#: and a stack of several (applied in order)
DETERMINISTIC = {
    "delay 2": [Layer("delay", 2)],
    "delay 15": [Layer("delay", 15)],
    "lag": [Layer("lag", 2.5)],
    "play": [Layer("play", 8)],
    "gain drift": [Layer("gain_drift", -0.3)],
    "quantise": [Layer("quantise", 3)],
    "saturation": [Layer("saturation", 0, 30.0, 45.0)],
    "stack": [Layer("delay", 1), Layer("lag", 1), Layer("saturation", 0, 20.0, 70.0), Layer("play", 4)],
}


@pytest.mark.parametrize("spec", [LANE, PID], ids=["lane-keeping", "pid"])
@pytest.mark.parametrize("name", list(DETERMINISTIC))
def test_deterministic_layers_run_alike_on_both_engines(name, spec):
    ck = paper_ckpt().with_layers(DETERMINISTIC[name])
    init = windows(4)
    want = rollout(ck, spec, init, 80, runs=2)
    got = native.rollout(ck, spec, init, 80, runs=2, threads=2)
    np.testing.assert_array_equal(got[:, :10], want[:, :10])
    np.testing.assert_allclose(got, want, atol=1e-4, rtol=0)
    plain = rollout(paper_ckpt(), spec, init, 80, runs=2)
    assert not np.allclose(want, plain, atol=1e-3), "the layer changed nothing: the test would not see a wrong one"


def _model_states(ck, layered: np.ndarray, actions_seen: np.ndarray) -> np.ndarray:
    """The plain model stepped by hand along a layered run: from sigma_0, each next state predicted
    from the model's own earlier predictions and ``actions_seen`` (B, l+steps), as the engine's window
    should hold them."""
    raw = layered[:, :, 0].copy()
    for t in range(10, layered.shape[1]):
        window = np.stack([raw[:, t - 10 : t], actions_seen[:, t - 10 : t]], axis=2)
        x = ck.model_input(torch.from_numpy(ck.encode_rows(window)), None)
        raw[:, t] = ck.next_state(x)[:, 0]
    return raw


def test_the_model_sees_the_delayed_commands_and_the_log_keeps_the_commands():
    ck = paper_ckpt()
    layered = native.rollout(ck.with_layers([Layer("delay", 3)]), PID, windows(2), 40)
    actions = layered[:, :, 1]
    seen = np.concatenate([actions[:, :10], actions[:, 7:-3]], axis=1)  # row j >= l holds command j - 3
    np.testing.assert_allclose(_model_states(ck, layered, seen), layered[:, :, 0], atol=1e-3)


def test_the_model_keeps_its_own_prediction_the_log_and_controller_see_the_clipped_one():
    ck = paper_ckpt()
    low, high = 35.0, 45.0
    layered = native.rollout(ck.with_layers([Layer("saturation", 0, low, high)]), PID, windows(2), 40)
    raw = _model_states(ck, layered, layered[:, :, 1])
    assert np.any((raw[:, 10:] < low) | (raw[:, 10:] > high)), "the model never left the band: nothing is tested"
    np.testing.assert_allclose(np.clip(raw[:, 10:], low, high), layered[:, 10:, 0], atol=1e-3)


@pytest.mark.parametrize(
    "layer, statistic",
    [
        (Layer("noise", 4.0), lambda tr: tr[:, 30, 0]),  # a state seen through noise
        (Layer("run_gain", 0.3), lambda tr: tr[:, 11:, 0].std(axis=1)),  # runs differ by their gain
    ],
    ids=["noise", "run_gain"],
)
def test_stochastic_layers_draw_the_same_distribution_on_both_engines(layer, statistic):
    """Draws differ between engines (Philox keys in C++, NumPy in Python), so the runs are compared as
    samples: 2,000 runs a side, a two-sample KS test and the spread; without the layer every run is one."""
    ck = paper_ckpt().with_layers([layer])
    init = windows(1)
    py = statistic(rollout(ck, PID, init, 40, runs=2000, seed=5))
    cc = statistic(native.rollout(ck, PID, init, 40, runs=2000, seed=5))
    assert np.ptp(py) > 1 and np.ptp(cc) > 1
    assert stats.ks_2samp(py, cc).pvalue > 0.001
    assert cc.std() == pytest.approx(py.std(), rel=0.1)
    assert not np.array_equal(cc, statistic(native.rollout(ck, PID, init, 40, runs=2000, seed=6)))


def test_a_noise_layer_has_the_declared_spread():
    ck = paper_ckpt(clamp=False)
    init = windows(1)
    clean = native.rollout(ck, LANE, init, 1)[0, 10, 0]
    seen = native.rollout(ck.with_layers([Layer("noise", 2.0)]), LANE, init, 1, runs=20000, seed=1)[:, 10, 0]
    assert abs(seen.mean() - clean) < 4 * 2.0 / np.sqrt(20000)
    assert seen.std() == pytest.approx(2.0, rel=0.02)


@pytest.mark.parametrize("engine", ["python", "native"])
def test_layered_states_are_read_as_the_sensor_reads(engine):
    """A noise layer of sd 50 once wrote colour readings of -113 and 188 that every later command
    refused as a log: a layered state is read within the declared range and at the resolution."""
    ck = paper_ckpt(round_to=(1.0,)).with_layers([Layer("noise", 50.0)])
    roll = rollout if engine == "python" else native.rollout
    colour = roll(ck, PID, windows(2), 60, runs=20, seed=3)[:, 10:, 0]
    assert colour.min() == 0 and colour.max() == 100  # sd 50 reaches both ends: the test sees the clamp
    np.testing.assert_array_equal(colour, np.round(colour))


def test_a_layer_that_makes_a_state_non_finite_is_named_alike_by_both_engines():
    """The message names the layers, as envi_py.effect_layers.describe words them, in both engines."""
    layers = [Layer("delay", 2), Layer("saturation", 0, 0, 20.5), Layer("quantise", 1e-320)]  # s / 1e-320 is inf
    ck = paper_ckpt().with_layers(layers)
    said = []
    for roll in (rollout, native.rollout):
        with pytest.raises(ValueError) as err:
            roll(ck, PID, windows(1), 5)
        said.append(str(err.value))
    want = f"the effect layers {describe(layers)} drive state 'color' to a non-finite value"
    assert "delay 2 ticks, saturation [0, 20.5], quantise 9.99989e-321 state units" in want
    assert said == [want, want]


def test_layers_travel_in_the_export_and_envi_sim_applies_them(tmp_path, real_dir):
    ck = paper_ckpt().with_layers([Layer("delay", 2), Layer("saturation", 0, 20.0)])
    layers_file = tmp_path / "m.layers.json"
    layers_file.write_text(json.dumps({"layers": [{"layer": lay.to_json()} for lay in ck.layers]}))
    plain = tmp_path / "plain.pt"
    paper_ckpt().save(plain)
    assert export_main([str(plain), "-o", str(tmp_path / "m.onnx"), "--layers", str(layers_file)]) == 0
    assert read_metadata(tmp_path / "m.onnx")["envi.layers"] == [lay.to_json() for lay in ck.layers]
    logs = load_logs([real_dir / "log_30_0.csv"], lane_keeping().with_pattern("log_{x}_{run}.csv"))
    init = initial_windows(logs, 10)
    want = native.rollout(ck, LANE, init, 30, runs=2, seed=4)
    np.testing.assert_array_equal(native.rollout(tmp_path / "m.onnx", LANE, init, 30, runs=2, seed=4), want)
    binary = envi_sim()
    if binary is None:
        pytest.skip("envi_sim binary not built")
    cmd = [binary, "--model", str(tmp_path / "m.onnx"), "--init", str(real_dir / "log_30_0.csv")]
    cmd += ["--controller", json.dumps(LANE.to_json()), "--steps", "30", "--runs", "2", "--seed", "4"]
    subprocess.run(cmd + ["--out", str(tmp_path / "sim")], check=True)
    got = read_log(tmp_path / "sim" / "log_30_0-sim1.csv")
    np.testing.assert_allclose(got.values, want[1], atol=1e-4, rtol=0)
    assert got.meta.provenance["layers"] == [lay.to_json() for lay in ck.layers]


@pytest.mark.parametrize(
    "entry, match",
    [
        ({"kind": "wind", "value": 1}, "unknown effect layer 'wind'"),
        ({"kind": "delay", "value": 2.5}, "whole number of ticks"),
        ({"kind": "delay", "value": 5000}, "whole number of ticks"),
        ({"kind": "lag", "value": 1e300}, "time constant up to 1000 rows"),
        ({"kind": "noise", "value": -1}, "finite and not negative"),
        ({"kind": "noise", "value": "1"}, "must be a number"),
        ({"kind": "saturation", "low": 5, "high": 1}, "ordered"),
        ({"kind": "gain_drift", "value": -1e308}, "at most 10 in size"),
        ({"kind": "run_gain", "value": 1e300}, "at most 10 in size"),
        ([1, 2], "object with a 'kind'"),
    ],
)
def test_the_loader_refuses_bad_layers_as_python_does(entry, match):
    with pytest.raises(ValueError, match=match):
        native.load(with_metadata(paper_ckpt(), "envi.layers", [entry]))
    with pytest.raises(ValueError):
        Layer.from_json(entry)  # type: ignore[arg-type]


def test_envi_simulate_takes_a_layers_file_on_either_engine(tmp_path, capsys):
    from envi_py.twin import TwinProfile, generate

    model = tmp_path / "m.pt"
    paper_ckpt().save(model)
    init_dir = tmp_path / "init"
    for lg in generate(LANE, 2, 40, {}, seed=0, profile=TwinProfile()):
        write_log(lg, init_dir / f"{lg.meta.run_id}.csv")
    layers_file = tmp_path / "m.pt.layers.json"
    layers_file.write_text(json.dumps({"layers": [{"layer": Layer("delay", 2).to_json()}]}))
    runs = {}
    for engine in ("native", "torch"):
        out = tmp_path / engine
        args = ["simulate", "--model", str(model), "--init-logs", str(init_dir), "--out", str(out)]
        assert envi_main(args + ["--layers", str(layers_file), "--engine", engine]) == 0
        assert "effect layers: delay 2 ticks" in capsys.readouterr().out
        runs[engine] = [read_log(p) for p in sorted(out.glob("*.csv"))]
        assert all(lg.meta.provenance["layers"] == [Layer("delay", 2).to_json()] for lg in runs[engine])
    for a, b in zip(runs["native"], runs["torch"]):
        np.testing.assert_allclose(a.values, b.values, atol=1e-4, rtol=0)
    layers_file.write_text('{"layers": [{"layer": {"kind": "wind"}}]}')
    args = ["simulate", "--model", str(model), "--init-logs", str(init_dir), "--out", str(tmp_path / "bad")]
    assert envi_main(args + ["--layers", str(layers_file)]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "m.pt.layers.json: not a layers file" in err[0] and "wind" in err[0], err
    assert not (tmp_path / "bad").exists() or not list((tmp_path / "bad").glob("*.csv"))


def test_at_most_64_layers_in_either_engine(tmp_path):
    many = [Layer("lag", 1.0)] * 65
    with pytest.raises(ValueError, match="at most 64"):
        paper_ckpt().with_layers(many)
    with pytest.raises(ValueError, match="at most 64 layers"):
        native.load(with_metadata(paper_ckpt(), "envi.layers", [lay.to_json() for lay in many]))
    path = tmp_path / "m.layers.json"
    path.write_text(json.dumps({"layers": [{"layer": lay.to_json()} for lay in many]}))
    with pytest.raises(ValueError, match="m.layers.json: not a layers file .65 layers, at most 64"):
        read_layers(path)
    assert len(paper_ckpt().with_layers(many[:64]).layers) == 64


def test_a_layers_file_reads_back_what_the_diagnosis_saved(tmp_path):
    from envi_py.diagnose.layers import Fit, save_layers

    path = save_layers(tmp_path / "m.pt", [Fit(Layer("lag", 1.5), [1.0, 2.0], [])])
    assert read_layers(path) == (Layer("lag", 1.5),)
    with pytest.raises(ValueError, match="nope.json: cannot read"):
        read_layers(tmp_path / "nope.json")


def test_envi_check_gives_the_verdicts_of_the_model_with_its_layers(tmp_path, capsys):
    """A what-if verdict: clipping the colour the controller sees to [36, 44] makes the requirement
    'never more than 4 from the edge' hold in every simulated run, whatever the plain model does."""
    from envi_py.twin import TwinProfile, generate

    model = tmp_path / "m.pt"
    paper_ckpt().save(model)
    real = []
    for lg in generate(LANE, 4, 40, {}, seed=0, profile=TwinProfile()):
        real.append(str(write_log(lg, tmp_path / "real" / f"{lg.meta.run_id}.csv")))
    layers_file = tmp_path / "clip.layers.json"
    layers_file.write_text(json.dumps({"layers": [{"layer": Layer("saturation", 0, 36.0, 44.0).to_json()}]}))
    base = ["check", "--model", str(model), "--real", *real, "--require", "max_abs_dev(color, 40) <= 4@0.9"]
    base += ["--max-runs", "200", "--batch", "100", "--sims-per-start", "4"]
    results = {}
    for name, extra in (("plain", []), ("layered", ["--layers", str(layers_file)])):
        assert envi_main(base + extra + ["--out", str(tmp_path / name)]) == 0
        results[name] = json.loads((tmp_path / name / "check.json").read_text())
    sim = results["layered"]["rows"][0]["simulation"]
    assert sim["verdict"] == "PASS" and sim["successes"] == sim["runs"], sim
    assert results["plain"]["rows"][0]["simulation"]["successes"] < results["plain"]["rows"][0]["simulation"]["runs"]
    assert results["layered"]["layers"] == [Layer("saturation", 0, 36.0, 44.0).to_json()]
    assert "layers" not in results["plain"]
    capsys.readouterr()
