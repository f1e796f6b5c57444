"""The native engine against the Python reference: rollout, controllers, metrics, errors, envi_sim."""

from __future__ import annotations

import json
import os
import re
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import onnx
import pytest
import torch

from envi_py import native
from envi_py.controllers import ControllerSpec
from envi_py.export import export, to_onnx
from envi_py.logs import load_logs, read_log, sidecar_path, write_log
from envi_py.system import lane_keeping
from envi_py.metrics import MetricConfig, driving_metrics
from envi_py.simulate import initial_windows, rollout

from .conftest import make_log
from .test_controller_parity import reference_rollout
from .test_export import paper_ckpt

pytestmark = pytest.mark.skipif(not native.available(), reason="native engine not built")

LANE = ControllerSpec("lane-keeping", {"x": 30})
PID = ControllerSpec("pid", {"kp": 2.0, "ki": 5.0, "kd": 0.05, "setpoint": 45.0, "out_min": -40, "out_max": 40})


def windows(n: int = 4, seed: int = 0) -> np.ndarray:
    rng = np.random.default_rng(seed)
    out = []
    for _ in range(n):
        log = make_log(np.clip(40 + np.cumsum(rng.normal(0, 8, 10)), 0, 100), x=30)
        out.append(log.values)
    return np.stack(out)


@pytest.fixture(scope="module")
def trained(real_dir):
    """A model briefly trained by BC on the real x=30 logs, and those logs."""
    from envi_py.train.bc import train_bc

    logs = load_logs(real_dir, lane_keeping().with_pattern("log_{x}_{run}.csv"), where={"x": [30]}, min_length=11)
    return train_bc(logs[:40], epochs=15, lr=1e-3, seed=0, head="deterministic"), logs


@pytest.mark.parametrize("spec", [LANE, PID], ids=["lane-keeping", "pid"])
def test_deterministic_rollout_matches_pytorch(spec):
    ck = paper_ckpt()
    init = windows(5)
    # the simulator's protocol (reset, warm-up on sigma_0, closed loop) written out in the test
    want = reference_rollout(ck, spec, init, 120, runs=3)
    got = native.rollout(ck, spec, init, 120, runs=3, threads=2)
    assert got.shape == want.shape == (15, 130, 2)
    np.testing.assert_array_equal(got[:, :10], want[:, :10])
    np.testing.assert_allclose(got, want, atol=1e-4, rtol=0)
    if spec.name == "lane-keeping":  # stateless: the PyTorch engine agrees with or without a warm-up
        np.testing.assert_allclose(got, rollout(ck, spec, init, 120, runs=3), atol=1e-4, rtol=0)


def test_every_registered_controller_is_native():
    from envi_py.controllers import REGISTRY

    ck = paper_ckpt()
    assert {"bang-bang", "lane-keeping", "pid", "combine"} <= set(REGISTRY)
    for name in REGISTRY:
        assert native.unsupported(ck, ControllerSpec(name)) is None, name
    assert "not a registered one" in native.unsupported(ck, ControllerSpec("mypkg.ctl:f"))


def test_pid_default_period_comes_from_the_checkpoint():
    ck = paper_ckpt()
    spec = ControllerSpec("pid", {"kp": 0.5, "ki": 2.0, "kd": 0.05})
    init = windows(3)
    ck.record.period_ms = 100.0
    assert native.load(ck).period_ms == 100.0
    slow = native.rollout(ck, spec, init, 30)
    np.testing.assert_allclose(slow, reference_rollout(ck, spec, init, 30), atol=1e-4, rtol=0)
    ck.record.period_ms = 20.0
    fast = native.rollout(ck, spec, init, 30)
    np.testing.assert_allclose(fast, reference_rollout(ck, spec, init, 30), atol=1e-4, rtol=0)
    assert np.abs(slow[:, 10:, 1] - fast[:, 10:, 1]).max() > 1


def test_trained_model_matches_pytorch_on_real_windows(trained):
    ck, logs = trained
    from envi_py.dataset import windows as sliding

    # one step from every window of the held-out logs: float32 agreement
    every = np.concatenate([sliding(lg.values, 10) for lg in logs[40:]])
    one = native.rollout(ck, LANE, every, 1)
    np.testing.assert_allclose(one, rollout(ck, LANE, every, 1), atol=1e-4, rtol=0)
    # closed loop: float32 rounding differences grow slowly along the run but never flip an action
    init = initial_windows(logs[40:], ck.config.history)
    want = rollout(ck, LANE, init, 90, runs=2)
    got = native.rollout(ck, LANE, init, 90, runs=2)
    assert np.ptp(want[:, 10:, 0]) > 10  # the model actually moves the robot through the lane
    np.testing.assert_allclose(got[:, :30], want[:, :30], atol=1e-4, rtol=0)
    np.testing.assert_allclose(got, want, atol=0.05, rtol=0)
    np.testing.assert_array_equal(got[..., 1], want[..., 1])


def test_post_processing_rounds_and_clamps_like_python():
    ck = paper_ckpt(round_to=(1.0,), limits=((20.0, 70.0),))
    init = windows(6, seed=1)
    want = rollout(ck, LANE, init, 60)
    got = native.rollout(ck, LANE, init, 60)
    np.testing.assert_array_equal(got[:, 10:, 0], np.round(got[:, 10:, 0]))
    assert got[:, 10:, 0].min() >= 20 and got[:, 10:, 0].max() <= 70
    assert np.mean(got == want) > 0.999  # rounding may flip only where float32 sums land on .5


def test_onnx_file_and_checkpoint_give_the_same_runs(tmp_path):
    ck = paper_ckpt()
    path = export(ck, tmp_path / "m.onnx")
    a = native.rollout(path, LANE, windows(2), 30)
    b = native.rollout(ck.save(tmp_path / "m.pt"), LANE, windows(2), 30)
    np.testing.assert_array_equal(a, b)


def test_gaussian_draws_do_not_depend_on_threads_or_blocks():
    ck = paper_ckpt("gaussian")
    model = native.load(ck)
    mod = native._native()
    init = windows(3)
    spec = json.dumps(LANE.to_json())
    ref = mod.rollout(model, spec, init, 40, 7, 11, 1, 5)
    for threads in (2, 3):  # threads take whole blocks: bit-identical
        np.testing.assert_array_equal(mod.rollout(model, spec, init, 40, 7, 11, threads, 5), ref)
    # other blocks or another batch: the same draws; GEMM rounding may differ in the last bits
    for block, first in [(256, 3), (1, 3), (3, 1)]:
        got = mod.rollout(model, spec, init[:first], 40, 7, 11, 2, block)
        np.testing.assert_allclose(got, ref[: 7 * first], atol=1e-4, rtol=0)
    assert not np.array_equal(mod.rollout(model, spec, init, 40, 7, 12, 1, 256), ref)
    assert not np.array_equal(ref[0], ref[1])


def test_gaussian_one_step_distribution_matches_the_head():
    ck = paper_ckpt("gaussian", clamp=False)
    init = windows(1)
    n = 40000
    got = native.rollout(ck, LANE, init, 1, runs=n, seed=3)[:, 10, 0]
    x = torch.from_numpy(ck.norm.encode(init[0]).astype(np.float32).reshape(1, -1))
    with torch.no_grad():
        mean, log_std = ck.model(x)
    mu = float(mean) * ck.norm.half[0] + ck.norm.centre[0]
    sd = float(log_std.exp()) * ck.norm.half[0]
    assert abs(got.mean() - mu) < 4 * sd / np.sqrt(n)
    assert abs(got.std() / sd - 1) < 0.02
    z = (got - mu) / sd  # standard normal tails, not uniform or clipped ones
    assert 0.04 < np.mean(np.abs(z) > 2) < 0.052


def test_metrics_match_python():
    rng = np.random.default_rng(1)
    traces = np.concatenate(
        [
            rng.uniform(0, 100, (30, 80)),
            np.clip(40 + np.cumsum(rng.normal(0, 6, (30, 80)), 1), 0, 100),
            np.full((2, 80), 50.0),
            np.full((2, 80), 30.0),
        ]
    )
    traces[0, 20:30] = [50, 50.0000001, 29.9999, 30, 70, 10, 10, 40, 50, 51]
    for cfg in [MetricConfig(), MetricConfig(centre=45, band=5, skip=3)]:
        got = native._native().driving_metrics(traces, cfg.centre, cfg.band, cfg.skip)
        np.testing.assert_array_equal(got, driving_metrics(traces, cfg))


def test_streamed_metrics_equal_metrics_of_the_traces():
    ck = paper_ckpt()
    init = windows(4)
    traces = native.rollout(ck, PID, init, 200, runs=3)
    got = native.rollout_metrics(ck, PID, init, 200, runs=3, threads=2)
    np.testing.assert_array_equal(got, driving_metrics(traces[..., 0]))


@pytest.mark.parametrize(
    "mutate, match",
    [
        (lambda m: m.graph.node[1].__setattr__("op_type", "Softmax"), "Softmax"),
        (lambda m: m.graph.node[1].__setattr__("domain", "com.example"), "foreign domain"),
        (lambda m: m.graph.initializer[0].__setattr__("data_location", onnx.TensorProto.EXTERNAL), "external data"),
        (lambda m: m.metadata_props.pop(), None),
        (lambda m: m.graph.initializer[1].dims.__setitem__(0, 7), "bias"),
    ],
)
def test_unsupported_models_are_clear_errors(mutate, match):
    model = to_onnx(paper_ckpt())
    if match is None:  # drop every envi metadata entry
        del model.metadata_props[:]
        match = "not an envi model"
    else:
        mutate(model)
    with pytest.raises(ValueError, match=match):
        native.load(model.SerializeToString())


def test_malformed_bytes_and_bad_arguments_are_value_errors():
    good = to_onnx(paper_ckpt()).SerializeToString()
    for bad in [b"", b"\xff" * 20, good[: len(good) // 2], good[:-3]]:
        with pytest.raises(ValueError):
            native.load(bad)
    with pytest.raises(ValueError, match="not available in the native runtime"):
        native.rollout(good, ControllerSpec("mypkg.ctl:f"), windows(1), 5)
    with pytest.raises(ValueError, match="unknown parameter"):
        native.rollout(good, ControllerSpec("pid", {"kq": 1}), windows(1), 5)
    with pytest.raises(ValueError, match="initial windows"):
        native.rollout(good, LANE, windows(1)[:, :5], 5)


def test_gil_is_released_while_simulating():
    import threading
    import time

    model = native.load(paper_ckpt())
    ticks = []
    stop = threading.Event()

    def tick():
        while not stop.is_set():
            ticks.append(time.perf_counter())
            time.sleep(0.001)

    th = threading.Thread(target=tick)
    th.start()
    t0 = time.perf_counter()
    native.rollout(model, LANE, windows(1), 3000, runs=64, threads=1)
    t1 = time.perf_counter()
    stop.set()
    th.join()
    inside = [t for t in ticks if t0 < t < t1]
    # holding the GIL would starve the ticker for the whole call; a loaded machine only slows it
    assert t1 - t0 > 0.05 and len(inside) >= max(3, 0.1 * (t1 - t0) / 0.0011)


def envi_sim() -> str | None:
    root = Path(__file__).resolve().parents[1]
    found = shutil.which("envi_sim") or shutil.which("envi_sim", path=str(Path(sys.executable).parent))
    if found:
        return found
    for cand in sorted(root.glob("build/**/envi_sim")):
        if os.access(cand, os.X_OK) and cand.is_file():
            return str(cand)
    return None


@pytest.mark.skipif(envi_sim() is None, reason="envi_sim binary not built")
def test_envi_sim_writes_logs_and_metrics_like_python(tmp_path, real_dir):
    ck = paper_ckpt()
    model = export(ck, tmp_path / "m.onnx")
    files = [real_dir / "log_30_0.csv", real_dir / "log_30_1.csv"]
    spec = json.dumps(LANE.to_json())
    cmd = [
        envi_sim(),
        "--model",
        str(model),
        "--init",
        *map(str, files),
        "--controller",
        spec,
        "--steps",
        "50",
        "--runs",
        "2",
        "--threads",
        "2",
        "--seed",
        "4",
    ]
    subprocess.run(cmd + ["--out", str(tmp_path / "sim"), "--metrics", str(tmp_path / "m.json")], check=True)
    logs = [read_log(tmp_path / "sim" / f"log_30_{i}-sim{r}.csv") for i in (0, 1) for r in (0, 1)]
    real = load_logs(files, lane_keeping().with_pattern("log_{x}_{run}.csv"))
    traces = native.rollout(ck, LANE, initial_windows(real, 10), 50, runs=2)
    for lg, tr in zip(logs, traces):
        assert lg.meta.source == "sim" and lg.meta.controller == LANE.to_json() and len(lg) == 60
        np.testing.assert_allclose(lg.values, tr, atol=1e-4, rtol=0)  # the binary may use another ISA build
        np.testing.assert_array_equal(lg.time[:10], real[0 if "30_0" in lg.name else 1].time[:10])
    for lg in logs:  # byte for byte what envi_py.logs.write_log makes of the same log
        again = write_log(lg, tmp_path / "py" / lg.name)
        assert again.read_bytes() == lg.path.read_bytes()
        assert sidecar_path(again).read_bytes() == sidecar_path(lg.path).read_bytes()
    assert logs[1].meta.provenance == {"init_log": "log_30_0.csv", "model_algorithm": "bc", "seed": 4, "replicate": 1}
    out = json.loads((tmp_path / "m.json").read_text())
    np.testing.assert_array_equal(out["per_run"], driving_metrics(np.stack([lg.states[:, 0] for lg in logs])))
    assert out["mean"] == pytest.approx(np.mean(out["per_run"], axis=0))
    subprocess.run(cmd + ["--metrics-only", "--metrics", str(tmp_path / "m2.json")], check=True)
    assert json.loads((tmp_path / "m2.json").read_text())["per_run"] == out["per_run"]
    bad = subprocess.run(
        cmd[:2] + [str(tmp_path / "nope.onnx")] + cmd[3:] + ["--metrics", "-"],
        capture_output=True,
        text=True,
        check=False,
    )
    assert bad.returncode == 2 and "nope.onnx" in bad.stderr and bad.stderr.count("\n") == 1


@pytest.mark.skipif(envi_sim() is None, reason="envi_sim binary not built")
def test_envi_sim_controller_from_the_model_by_name_and_default_steps(tmp_path, real_dir):
    ck = paper_ckpt()  # trained with one controller: lane-keeping x=30
    model = export(ck, tmp_path / "m.onnx")
    files = [real_dir / "log_30_0.csv", real_dir / "log_50_1.csv"]
    real = load_logs(files, lane_keeping().with_pattern("log_{x}_{run}.csv"))
    init = initial_windows(real, 10)

    def sim(*args: str) -> subprocess.CompletedProcess:
        return subprocess.run(
            [envi_sim(), f"--model={model}", "--init", *map(str, files), *args],
            capture_output=True,
            text=True,
            check=False,
        )

    # no --controller: the model's own; no --steps: each log's length minus the history
    done = sim("--metrics-only", "--metrics=-")
    assert done.returncode == 0, done.stderr
    out = json.loads(done.stdout)
    assert out["controller"] == LANE.to_json() and out["steps"] == len(real[0]) - 10
    traces = native.rollout(ck, LANE, init, len(real[0]) - 10)
    # envi_sim is the portable build, the module the best variant for this CPU (AVX-512 here): the
    # float32 network differs in the last bits between instruction sets, so amplitudes agree to 1e-5
    np.testing.assert_allclose(out["per_run"], driving_metrics(traces[..., 0]), rtol=0, atol=1e-5)
    # logs of other lengths run for their own number of steps; metrics stay in the order given
    short = tmp_path / "log_30_9.csv"
    short.write_text("".join(files[0].read_text().splitlines(keepends=True)[:61]))
    done = subprocess.run(
        [
            envi_sim(),
            f"--model={model}",
            "--init",
            str(files[0]),
            str(short),
            str(files[1]),
            "--metrics-only",
            "--metrics=-",
        ],
        capture_output=True,
        text=True,
        check=False,
    )
    assert done.returncode == 0, done.stderr
    out = json.loads(done.stdout)
    assert out["steps"] == [90, 50, 90]
    # another grouping of runs into blocks: GEMM rounding may move an amplitude in its last float32 bits
    np.testing.assert_allclose(out["per_run"][1], driving_metrics(traces[:1, :60, 0])[0], atol=1e-4, rtol=0)
    np.testing.assert_allclose(np.array(out["per_run"])[[0, 2]], driving_metrics(traces[..., 0]), atol=1e-4, rtol=0)
    # a registered name with --param, --opt=value forms
    pid = ControllerSpec("pid", {"kp": 2.0, "ki": 5.0, "kd": 0.05})
    done = sim(
        "--controller", "pid", "--param", "kp=2", "ki=5", "--param=kd=0.05", "--steps=20", f"--out={tmp_path / 'o'}"
    )
    assert done.returncode == 0, done.stderr
    logs = [read_log(tmp_path / "o" / f"{stem}-sim0.csv") for stem in ("log_30_0", "log_50_1")]
    assert all(lg.meta.controller == pid.to_json() for lg in logs)
    np.testing.assert_allclose(
        np.stack([lg.values for lg in logs]), native.rollout(ck, pid, init, 20), atol=1e-4, rtol=0
    )
    # a combine spec from a file, refused for its width: one line naming the controller, exit 2
    (tmp_path / "c.json").write_text(json.dumps({"name": "combine", "params": {"loops": [LANE.to_json()] * 2}}))
    for args, words in [
        (["--controller", f"@{tmp_path / 'c.json'}"], "'combine' drives 2 action channel(s)"),
        (["--controller", "steer"], "unknown controller 'steer'"),
        (["--controller", "pid", "--param", "kq=1"], "unknown parameter"),
        (["--controller", '{"name": "pid", "params": {"input": 1}}'], "reads state channel 1"),
        (["--frobnicate"], "unknown option --frobnicate"),
        (["--steps=-3"], "--steps must be between 1 and"),
        (["--steps=0"], "--steps must be between 1 and"),  # once blamed --skip: 'runs of 10 rows leave nothing'
    ]:
        bad = sim(*args, "--metrics", "-")
        assert bad.returncode == 2 and words in bad.stderr and bad.stderr.count("\n") == 1, (args, bad.stderr)
    # a model trained under several controllers asks which one
    ck.record.controllers.append({"name": "lane-keeping", "params": {"x": 50.0}})
    export(ck, tmp_path / "m.onnx")
    bad = sim("--metrics", "-")
    assert bad.returncode == 2 and "2 training controller(s); choose one with --controller" in bad.stderr


@pytest.mark.skipif(envi_sim() is None, reason="envi_sim binary not built")
def test_envi_sim_usage_documents_every_option():
    usage = subprocess.run([envi_sim(), "--help"], capture_output=True, text=True, check=True).stdout
    source = (Path(__file__).resolve().parents[1] / "cpp" / "src" / "envi_sim.cpp").read_text()
    options = set(re.findall(r'f == "(--[a-z-]+)"', source)) - {"--help"}
    assert len(options) >= 15
    for opt in options:
        line = next((ln for ln in usage.splitlines() if ln.strip().startswith(opt)), None)
        assert line is not None, opt
    assert "(default" in usage and "--opt=VALUE" in usage


@pytest.mark.skipif(envi_sim() is None, reason="envi_sim binary not built")
def test_envi_sim_metrics_only_memory_is_flat(tmp_path, real_dir):
    model = export(paper_ckpt(), tmp_path / "m.onnx")
    probe = (
        "import resource, subprocess, sys; subprocess.run(sys.argv[1:], check=True, stdout=subprocess.DEVNULL); "
        "print(resource.getrusage(resource.RUSAGE_CHILDREN).ru_maxrss)"
    )

    def peak_kib(runs: int) -> int:
        cmd = [
            envi_sim(),
            "--model",
            str(model),
            "--init",
            str(real_dir / "log_30_0.csv"),
            "--controller",
            json.dumps(LANE.to_json()),
            "--steps",
            "40",
            "--runs",
            str(runs),
            "--metrics-only",
            "--metrics",
            "-",
        ]
        return int(
            subprocess.run([sys.executable, "-c", probe, *cmd], capture_output=True, text=True, check=True).stdout
        )

    small, large = peak_kib(500), peak_kib(50_000)
    # 50 000 kept traces would be 50000 x 50 x 2 doubles = 40 MB; streaming keeps a chunk's worth
    assert large - small < 8 * 1024, (small, large)


def _tampered(tmp_path: Path, how: str) -> Path:
    """An export changed after the fact: a weight bit flipped, a metadata value edited, or the hash
    removed (what a file exported before the content hash looks like)."""
    model = onnx.load(str(export(paper_ckpt(), tmp_path / "m.onnx")))
    if how == "weight":
        w = onnx.numpy_helper.to_array(model.graph.initializer[0]).copy()
        w.view(np.uint32).flat[17] ^= 1 << 3
        model.graph.initializer[0].CopyFrom(onnx.numpy_helper.from_array(w, model.graph.initializer[0].name))
    elif how == "metadata":
        prop = next(p for p in model.metadata_props if p.key == "envi.period_ms")
        prop.value = "20.0"
    else:
        del model.metadata_props[-1]
    path = tmp_path / f"{how}.onnx"
    path.write_bytes(model.SerializeToString())
    return path


@pytest.mark.parametrize(
    "how, reason",
    [
        ("weight", "content hash mismatch: the file was changed after export (re-export it with envi-export)"),
        ("metadata", "content hash mismatch: the file was changed after export (re-export it with envi-export)"),
        ("no hash", "no content hash ('envi.content_sha256')"),
    ],
)
def test_a_model_changed_after_export_is_refused_by_name(tmp_path, how, reason):
    path = _tampered(tmp_path, how)
    with pytest.raises(ValueError) as err:
        native.load(path)
    assert str(err.value).startswith(f"{path}: {reason}") and "\n" not in str(err.value)
    assert str(err.value).endswith("(re-export it with envi-export)")
    with pytest.raises(ValueError, match="content hash|no content hash"):
        native.load(path.read_bytes())
    native.load(tmp_path / "m.onnx")  # the untouched export loads


@pytest.mark.skipif(envi_sim() is None, reason="envi_sim binary not built")
@pytest.mark.parametrize("how", ["weight", "no hash"])
def test_envi_sim_refuses_a_changed_model_in_one_line(tmp_path, how):
    path = _tampered(tmp_path, how)
    init = write_log(make_log(np.linspace(20, 60, 20)), tmp_path / "log_30_0.csv")
    cmd = [envi_sim(), "--model", str(path), "--init", str(init), "--steps", "5", "--metrics-only", "--metrics", "-"]
    bad = subprocess.run(cmd, capture_output=True, text=True, check=False)
    lines = bad.stderr.splitlines()
    assert bad.returncode == 2 and len(lines) == 1 and bad.stdout == "", bad.stderr
    assert lines[0].startswith(f"envi_sim: {path}: ") and "re-export it with envi-export" in lines[0]
    good = subprocess.run(cmd[:2] + [str(tmp_path / "m.onnx")] + cmd[3:], capture_output=True, text=True)
    assert good.returncode == 0, good.stderr


def test_lane_metrics_are_refused_for_a_model_of_another_system(tmp_path):
    """The streamed metrics are the lane-keeping preset's: a car model is not scored with them, in
    the module or in envi_sim (one line, exit 2), and says where its goals are scored instead."""
    from envi_py.train.bc import train_bc
    from envi_py.twin.car import generate_car_versions

    logs = generate_car_versions(3, seed=2, versions=[0])
    ck = train_bc(logs, epochs=1, hidden=(8,), seed=0)
    init = initial_windows(logs[:2], ck.config.history)
    with pytest.raises(ValueError, match="system 'car' declares other goals"):
        native.rollout_metrics(ck, logs[0].controller, init, 20)
    if envi_sim() is None:
        return
    model = export(ck, tmp_path / "car.onnx")
    for lg in logs[:2]:
        write_log(lg, tmp_path / f"{lg.meta.run_id}.csv")
    bad = subprocess.run(
        [
            envi_sim(),
            "--model",
            str(model),
            "--init",
            str(tmp_path / f"{logs[0].meta.run_id}.csv"),
            "--steps",
            "5",
            "--metrics-only",
            "--metrics",
            "-",
        ],
        capture_output=True,
        text=True,
        timeout=60,
    )
    lines = bad.stderr.strip().splitlines()
    assert bad.returncode == 2 and len(lines) == 1 and "declares other goals" in lines[0], bad.stderr
