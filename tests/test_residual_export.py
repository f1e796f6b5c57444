"""A residual mean head in the exported ONNX file and in the native engine, against PyTorch.

The residual head predicts the change from the window's last state; for a saturating sensor with a
limit event (the car's distance reading 255 when the echo is lost) the change is from its last
reading in range. The export writes that base as ``residual.*`` nodes (onnxruntime runs them), the
native loader checks them against the metadata ``envi.residual`` and computes the base itself. These
tests pin both against ``EnvModel.heads`` on windows whose distance is never, partly and entirely at
the limit, and the native closed loop against a PyTorch one drawing the engine's very noise.
"""

from __future__ import annotations

import json
import subprocess

import numpy as np
import onnx
import onnxruntime as ort
import pytest
import torch

from envi_py import native
from envi_py.export import (
    CONTENT_KEY,
    INPUT,
    PARITY_TOL,
    RESIDUAL_KEY,
    content_sha256,
    export,
    parity_inputs,
    read_metadata,
    to_onnx,
)
from envi_py.logs import read_log, write_log
from envi_py.simulate import initial_windows, rollout
from envi_py.train.bc import train_bc
from envi_py.twin.car import car_versions, generate_car_versions

from .test_export import paper_ckpt
from .test_native import envi_sim

LIMIT = 255.0
DISTANCE = 1  # the car's saturating state


@pytest.fixture(scope="module")
def car_logs():
    return generate_car_versions(4, seed=5, versions=[0, 2])


def car_residual(logs, head: str = "gaussian", **extra):
    """A small residual model of the car twin, briefly trained (limit events found in the logs)."""
    return train_bc(logs, epochs=2, lr=1e-3, seed=0, hidden=(32,), head=head, residual=True, **extra)


@pytest.fixture(scope="module")
def car_ckpt(car_logs):
    ckpt = car_residual(car_logs)
    assert ckpt.config.limit_events == ((DISTANCE, LIMIT),)
    return ckpt


def limit_windows(logs, history: int, seed: int = 0) -> dict[str, np.ndarray]:
    """Physical windows (n, l, C) from the logs whose distance is never at the limit, at it in every
    row, in the last few rows only, and in a few rows before an in-range last row."""
    rng = np.random.default_rng(seed)
    base = np.stack([lg.values[t : t + history] for lg in logs for t in range(0, len(lg) - history, 7)])
    base = base[(base[:, :, DISTANCE] < LIMIT).all(axis=1)]
    never, every, tail, gaps = (base.copy() for _ in range(4))
    every[:, :, DISTANCE] = LIMIT
    for w in tail:
        w[history - rng.integers(1, history) :, DISTANCE] = LIMIT
    for w in gaps:
        w[rng.choice(history - 1, rng.integers(1, history - 1), replace=False), DISTANCE] = LIMIT
    return {"never": never, "every": every, "tail": tail, "gaps": gaps}


def expected_base(ckpt, x: np.ndarray) -> np.ndarray:
    """EnvModel.residual_base written out row by row: the last reading, for a limit state the last
    one off its level (the last reading when none is)."""
    cfg = ckpt.config
    rows = x.reshape(len(x), cfg.history, cfg.row_width)[:, :, : cfg.n_state]
    base = rows[:, -1].copy()
    levels = ckpt.model.limit_levels.tolist() if cfg.limit_events else []
    for (i, _), level in zip(cfg.limit_events, levels):
        for n, col in enumerate(rows[:, :, i]):
            off = np.flatnonzero(np.abs(col - np.float32(level)) > np.float32(1e-5))
            base[n, i] = col[off[-1]] if len(off) else col[-1]
    return base


def run_onnx(model: onnx.ModelProto, x: np.ndarray, extra_outputs: tuple[str, ...] = ()) -> dict[str, np.ndarray]:
    model = onnx.ModelProto.FromString(model.SerializeToString())
    for name in extra_outputs:  # expose an inner value of the graph
        model.graph.output.append(onnx.helper.make_tensor_value_info(name, onnx.TensorProto.FLOAT, None))
    sess = ort.InferenceSession(model.SerializeToString(), providers=["CPUExecutionProvider"])
    names = [o.name for o in sess.get_outputs()]
    return dict(zip(names, sess.run(None, {INPUT: x})))


def assert_same_heads(ckpt, got: dict[str, np.ndarray], x: np.ndarray) -> None:
    """Every output as PyTorch's: absolute within [-1, 1], relative beyond (export.parity's measure)."""
    with torch.no_grad():
        mean, log_std, logit = ckpt.model.heads(torch.from_numpy(x))
    want = {"mean": mean, "log_std": log_std, "event_logit": logit}
    want = {k: v.numpy() for k, v in want.items() if v is not None}
    assert sorted(got) == sorted(want)
    for k, w in want.items():
        err = np.abs(got[k] - w) / np.maximum(1, np.abs(w))
        assert err.max() <= PARITY_TOL, (k, err.max())


def encoded(ckpt, windows: np.ndarray) -> np.ndarray:
    return ckpt.norm.encode(windows).astype(np.float32).reshape(len(windows), -1)


# ---------------------------------------------------------------- export


@pytest.mark.parametrize("head", ["deterministic", "gaussian"])
def test_a_residual_model_without_limit_events_exports_and_matches_pytorch(head):
    ck = paper_ckpt(head, residual=True)
    model = to_onnx(ck)
    x = parity_inputs(ck.config.in_features, 4096, seed=1)
    got = run_onnx(model, x, ("residual.base",))
    last = (ck.config.history - 1) * ck.config.row_width
    np.testing.assert_array_equal(got.pop("residual.base"), x[:, last : last + 1])
    assert_same_heads(ck, got, x)
    assert {n.op_type for n in model.graph.node if n.name.startswith("residual.")} == {"Slice", "Mul", "Add"}
    assert json.loads(read_metadata_of(model)[RESIDUAL_KEY]) == {"scale": 2.0, "tolerance": 1e-5, "limit_levels": []}


def read_metadata_of(model: onnx.ModelProto) -> dict[str, str]:
    return {p.key: p.value for p in model.metadata_props}


def test_the_car_model_exports_its_last_in_range_base(car_ckpt, car_logs):
    ck = car_ckpt
    model = to_onnx(ck)
    level = (LIMIT - ck.norm.centre[DISTANCE]) / ck.norm.half[DISTANCE]
    meta = json.loads(read_metadata_of(model)[RESIDUAL_KEY])
    assert meta["scale"] == 2.0 and meta["tolerance"] == 1e-5
    assert meta["limit_levels"] == [[DISTANCE, float(np.float32(level))]]
    groups = limit_windows(car_logs, ck.config.history)
    for name, windows in groups.items():
        x = encoded(ck, windows)
        got = run_onnx(model, x, ("residual.base",))
        base = got.pop("residual.base")
        np.testing.assert_array_equal(base, expected_base(ck, x), err_msg=name)
        assert_same_heads(ck, got, x)
        at_limit = np.abs(base[:, DISTANCE] - np.float32(level)) <= 1e-5
        # only a window entirely at the limit changes from the limit itself
        assert at_limit.all() if name == "every" else not at_limit.any(), name
    x = parity_inputs(ck.config.in_features, 2048, seed=2)
    assert_same_heads(ck, run_onnx(model, x), x)


def test_a_non_residual_model_says_so_and_derived_channels_stay_refused():
    assert read_metadata_of(to_onnx(paper_ckpt()))[RESIDUAL_KEY] == "null"
    ck = paper_ckpt(residual=True, extras=("dt",))
    with pytest.raises(ValueError, match="derived channels cannot be exported") as err:
        to_onnx(ck)
    assert "residual" not in str(err.value)
    if native.available():
        assert native.unsupported(ck, car_versions()[0]) == "the model has derived channels"


def test_export_checks_parity_and_writes_the_file(tmp_path, car_ckpt):
    path = export(car_ckpt, tmp_path / "car.onnx")  # refuses a file drifting from PyTorch by > PARITY_TOL
    assert read_metadata(path)[RESIDUAL_KEY]["limit_levels"][0][0] == DISTANCE


# ---------------------------------------------------------------- native loader


def rehashed(model: onnx.ModelProto) -> bytes:
    """The file with its content hash recomputed: a consistent file whose graph and metadata may disagree."""
    keep = [p for p in model.metadata_props if p.key != CONTENT_KEY]
    del model.metadata_props[:]
    model.metadata_props.extend(keep)
    model.metadata_props.add(key=CONTENT_KEY, value=json.dumps(content_sha256(model)))
    return model.SerializeToString()


def set_meta(model: onnx.ModelProto, key: str, value) -> onnx.ModelProto:
    for p in model.metadata_props:
        if p.key == key:
            p.value = json.dumps(value)
    return model


needs_native = pytest.mark.skipif(not native.available(), reason="native engine not built")


@needs_native
def test_the_loader_refuses_a_residual_graph_its_metadata_does_not_describe(car_ckpt):
    good = to_onnx(car_ckpt)
    meta = json.loads(read_metadata_of(good)[RESIDUAL_KEY])
    assert native.load(good.SerializeToString()).residual
    cases = [
        (set_meta(to_onnx(car_ckpt), RESIDUAL_KEY, None), "declares none"),
        (set_meta(to_onnx(paper_ckpt()), RESIDUAL_KEY, {**meta, "limit_levels": []}), "has no node 'residual"),
        (set_meta(to_onnx(car_ckpt), RESIDUAL_KEY, {**meta, "limit_levels": [[1, 0.5]]}), "'residual.levels'"),
        (set_meta(to_onnx(car_ckpt), RESIDUAL_KEY, {**meta, "scale": 3.0}), "'residual.scale'"),
        (set_meta(to_onnx(car_ckpt), RESIDUAL_KEY, {**meta, "limit_levels": []}), "states of 'envi.limit_events'"),
        (set_meta(to_onnx(car_ckpt), RESIDUAL_KEY, {**meta, "limit_levels": [[0, 0.5]]}), "states of 'envi.limit"),
    ]
    stray = to_onnx(car_ckpt)
    stray.graph.node.append(onnx.helper.make_node("Identity", ["residual.base"], ["copy"], name="residual.copy"))
    cases.append((stray, "'residual.copy' is not part of the residual mean head"))
    first = to_onnx(car_ckpt)
    node = next(n for n in first.graph.node if n.name == "residual.last_in_range")
    next(a for a in node.attribute if a.name == "select_last_index").i = 0  # the first row in range, not the last
    cases.append((first, "'residual.last_in_range' must be ArgMax"))
    for model, match in cases:
        with pytest.raises(ValueError, match=match):
            native.load(rehashed(model))


# ---------------------------------------------------------------- native engine against PyTorch


@needs_native
def test_native_deterministic_residual_closed_loop_matches_pytorch(car_logs):
    ck = car_residual(car_logs, "deterministic", limit_events=(), round_to=None)
    assert native.unsupported(ck, car_versions()[0]) is None
    init = initial_windows(car_logs, ck.config.history)
    spec = car_versions()[0]
    want = rollout(ck, spec, init, 80, runs=2)
    got = native.rollout(ck, spec, init, 80, runs=2, threads=2)
    assert got.shape == want.shape == (16, 90, 4)
    np.testing.assert_array_equal(got[:, :10], want[:, :10])
    np.testing.assert_allclose(got, want, atol=1e-3, rtol=0)
    assert np.ptp(want[:, 10:, DISTANCE]) > 10  # the runs move: not a trivially constant loop


def philox_uniforms(seed: int, run: np.ndarray, step: int, channel: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The engine's counter-based draws (cpp/include/envi/rng.hpp, Philox4x32-10) in numpy: two
    53-bit integers per (run, channel), broadcast."""
    mask = np.uint64(0xFFFFFFFF)
    run, channel = np.broadcast_arrays(np.asarray(run, np.uint64), np.asarray(channel, np.uint64))
    c = [run & mask, run >> np.uint64(32), np.full(run.shape, step, np.uint64), channel & mask]
    k0, k1 = np.uint64(seed & 0xFFFFFFFF), np.uint64(seed >> 32)
    m0, m1 = np.uint64(0xD2511F53), np.uint64(0xCD9E8D57)
    for _ in range(10):
        p0, p1 = m0 * c[0], m1 * c[2]
        c = [(p1 >> np.uint64(32)) ^ c[1] ^ k0, p1 & mask, (p0 >> np.uint64(32)) ^ c[3] ^ k1, p0 & mask]
        k0, k1 = (k0 + np.uint64(0x9E3779B9)) & mask, (k1 + np.uint64(0xBB67AE85)) & mask
    m53 = np.uint64((1 << 53) - 1)
    return ((c[0] << np.uint64(21)) ^ c[1]) & m53, ((c[2] << np.uint64(21)) ^ c[3]) & m53


def engine_normal(seed: int, runs: int, step: int, n: int) -> np.ndarray:
    a, b = philox_uniforms(seed, np.arange(runs)[:, None], step, np.arange(n)[None, :])
    u1, u2 = (a.astype(np.float64) + 1.0) * 2.0**-53, b.astype(np.float64) * 2.0**-53
    return np.sqrt(-2.0 * np.log(u1)) * np.cos(6.283185307179586 * u2)


def engine_uniform(seed: int, runs: int, step: int, n: int) -> np.ndarray:
    a, _ = philox_uniforms(seed, np.arange(runs)[:, None], step, np.arange(n)[None, :] | 0x80000000)
    return a.astype(np.float64) * 2.0**-53


def matched_rollout(ckpt, spec, init: np.ndarray, steps: int, seed: int) -> np.ndarray:
    """The closed loop of envi_py.simulate.rollout (reset, warm-up on sigma_0, post-processing, limit
    events) stepping ``EnvModel.heads`` in PyTorch, with the native engine's draws: sample = mean +
    exp(log_std) * normal(seed, run, step, state), event where uniform(seed, run, step, e) < p."""
    cfg, norm = ckpt.config, ckpt.norm
    ns, hist, batch = cfg.n_state, cfg.history, len(init)
    ctrl = spec.build(ns, cfg.n_action, ckpt.period_ms)
    out = np.empty((batch, hist + steps, cfg.channels))
    out[:, :hist] = init
    ctrl.reset(batch)
    ctrl.warmup(out[:, :hist, :ns], out[:, :hist, ns:])
    window = norm.encode(out[:, :hist]).astype(np.float32)
    for t in range(steps):
        with torch.no_grad():
            mean, log_std, logit = ckpt.model.heads(torch.from_numpy(window.reshape(batch, -1)))
        eps = engine_normal(seed, batch, t, ns).astype(np.float32)
        z = mean.numpy() + np.exp(log_std.numpy()) * eps
        p = 1.0 / (1.0 + np.exp(-logit.numpy().astype(np.float64)))
        s = ckpt.decode_states(z, engine_uniform(seed, batch, t, p.shape[1]) < p)
        out[:, hist + t, :ns] = s
        out[:, hist + t, ns:] = ctrl(s)
        row = norm.encode(out[:, hist + t : hist + t + 1]).astype(np.float32)
        window = np.concatenate([window[:, 1:], row], axis=1)
    return out


@needs_native
def test_native_gaussian_residual_with_limit_events_matches_pytorch_with_the_same_draws(car_ckpt, car_logs):
    ck = car_ckpt
    ck.config.round_to = None  # no rounding to flip on a float32 difference
    try:
        hist = ck.config.history
        groups = limit_windows(car_logs, hist, seed=3)
        init = np.concatenate([g[:6] for g in groups.values()])
        spec = car_versions()[0]
        got = native.rollout(ck, spec, init, 40, runs=1, seed=7, threads=2)
        want = matched_rollout(ck, spec, init, 40, seed=7)
    finally:
        ck.config.round_to = (1.0, 1.0)
    np.testing.assert_array_equal(got[:, :hist], want[:, :hist])
    # float32 on both sides, summed in different orders (Eigen's AVX-512 kernels, PyTorch's oneDNN): the
    # speed loop's PID command (about 100) drifts by some 80 float32 steps over 40 closed-loop steps
    np.testing.assert_allclose(got, want, atol=1e-3, rtol=1e-5)
    sim = want[:, hist:, DISTANCE]
    # the runs exercise the base: limit readings, and in-range readings right after one
    assert (sim == LIMIT).any() and ((sim[:, :-1] == LIMIT) & (sim[:, 1:] < LIMIT)).any()


@needs_native
@pytest.mark.parametrize("group", ["never", "every", "tail", "gaps"])
def test_native_one_step_distribution_is_the_residual_heads(car_ckpt, car_logs, group):
    """Independent of the numpy Philox: 20000 draws from one window against PyTorch's mean and spread
    (no clamping, no rounding), and the limit event's rate against its probability."""
    ck = car_ckpt
    saved = ck.config.clamp, ck.config.round_to
    ck.config.clamp, ck.config.round_to = False, None
    try:
        window = limit_windows(car_logs, ck.config.history, seed=4)[group][:1]
        n = 20000
        got = native.rollout(ck, car_versions()[0], window, 1, runs=n, seed=5)[:, -1, :2]
    finally:
        ck.config.clamp, ck.config.round_to = saved
    with torch.no_grad():
        mean, log_std, logit = ck.model.heads(torch.from_numpy(encoded(ck, window)))
    mu = mean.numpy()[0] * ck.norm.half[:2] + ck.norm.centre[:2]
    sd = np.exp(log_std.numpy()[0]) * ck.norm.half[:2]
    p = float(torch.sigmoid(logit)[0, 0])
    events = got[:, DISTANCE] == LIMIT
    assert abs(events.mean() - p) < 5 * np.sqrt(p * (1 - p) / n) + 1e-4
    for i, values in enumerate([got[:, 0], got[~events, DISTANCE]]):
        assert abs(values.mean() - mu[i]) < 5 * sd[i] / np.sqrt(len(values)), (i, values.mean(), mu[i])
        assert abs(values.std() / sd[i] - 1) < 0.03


@needs_native
@pytest.mark.skipif(envi_sim() is None, reason="envi_sim binary not built")
def test_envi_sim_runs_the_residual_car_model_like_the_module(tmp_path, car_ckpt, car_logs):
    model = export(car_ckpt, tmp_path / "car.onnx")
    files = [write_log(lg, tmp_path / "init" / f"car_{i}.csv").as_posix() for i, lg in enumerate(car_logs[:3])]
    spec = car_versions()[0]
    cmd = [envi_sim(), "--model", str(model), "--init", *files, "--controller", json.dumps(spec.to_json())]
    cmd += ["--steps", "30", "--runs", "2", "--seed", "4", "--out", str(tmp_path / "sim")]
    subprocess.run(cmd, check=True, capture_output=True)
    init = initial_windows(car_logs[:3], car_ckpt.config.history)
    traces = native.rollout(car_ckpt, spec, init, 30, runs=2, seed=4 + 7919 * 30)  # envi_sim's seed of 30 steps
    sims = sorted((tmp_path / "sim").glob("*.csv"))
    assert len(sims) == 6
    for path, trace in zip(sims, traces):
        lg = read_log(path)
        np.testing.assert_allclose(lg.values[:, :4], trace, atol=1e-3, rtol=0)  # the binary may use another ISA
