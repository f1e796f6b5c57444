"""The ``play`` channel (backlash): one filter, the same values in training pairs, in the PyTorch
rollout and in GAIL's environment, although the latter two compute it step by step from simulated
actions."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from envi_py.controllers import ControllerSpec
from envi_py.dataset import Dataset, play_offsets
from envi_py.model import ModelConfig
from envi_py.simulate import rollout
from envi_py.train.common import model_config, new_checkpoint

from .conftest import make_log

PID = ControllerSpec("pid", {"kp": 1.0, "kd": 0.02, "setpoint": 40.0, "out_min": -30.0, "out_max": 30.0})


def pid_logs(n: int = 3, rows: int = 40) -> list:
    rng = np.random.default_rng(3)
    out = []
    for i in range(n):
        lg = make_log(np.clip(40 + np.cumsum(rng.normal(0, 6, rows)), 0, 100), run=f"r{i}")
        lg.actions[:, 0] = np.clip(40 - lg.states[:, 0], -30, 30)  # P-only steering: varies continuously
        out.append(lg)
    return out


def test_play_filter_holds_until_pushed_and_continues_from_a_row():
    a = np.array([0.0, 2.0, 3.0, 6.0, 5.0, 1.0, -2.0])
    off = play_offsets(a, 4.0)
    np.testing.assert_allclose(off, [0, -2, -2, -2, -1, 2, 2])
    batch = np.stack([a, a[::-1]])
    whole = play_offsets(batch, 4.0)
    np.testing.assert_allclose(whole[0], off)
    start = batch[:, 3] + whole[:, 3]  # position = command + offset, all a row needs to continue
    np.testing.assert_allclose(play_offsets(batch[:, 4:], 4.0, start), whole[:, 4:])


def test_a_play_channel_needs_a_width():
    with pytest.raises(ValueError, match="play_width"):
        ModelConfig(n_state=1, n_action=1, extras=("play",))


def test_training_pairs_carry_the_filter_of_the_whole_action_history():
    logs = pid_logs()
    ds = Dataset.build(logs, 4, extras=("play",), play_width=0.25)
    for lg, z in zip(logs, ds.z):
        a = ds.norm.encode(lg.values)[:, 1]
        np.testing.assert_allclose(z[:, -1], play_offsets(a, 0.5), atol=1e-6)
    assert np.abs(ds.z[0][:, -1]).max() > 0.2  # the filter is not idle on these logs


def play_ckpt(logs: list, history: int = 4):
    return new_checkpoint(
        "bc", logs, [], model_config(logs, history=history, hidden=(16,), extras=("play",), play_width=0.3), 0, {}
    )


def test_rollout_feeds_the_model_the_rows_a_log_of_its_own_trajectory_gives():
    """Run the closed loop, turn the trajectory into logs, build training pairs from them: the model
    inputs must be those pairs' windows, play channel included, at every step."""
    logs = pid_logs()
    ck = play_ckpt(logs)
    seen = []
    original = ck.model.step
    ck.model.step = lambda x, gen=None: (seen.append(x.clone()), original(x, gen))[1]
    traj = rollout(ck, PID, np.stack([lg.values[:4] for lg in logs]), 25)
    sim_logs = [make_log(tr[:, 0], run=f"s{i}") for i, tr in enumerate(traj)]
    for lg, tr in zip(sim_logs, traj):
        lg.actions[:, 0] = tr[:, 1]
    ds = ck.dataset(sim_logs)
    inputs = torch.stack(seen, 1).numpy()  # (runs, steps, in_features)
    for r in range(len(logs)):
        np.testing.assert_allclose(inputs[r], ds.X[r][:25], atol=1e-5)
    assert np.abs(inputs[..., -1]).max() > 0.05


def test_gail_environment_continues_the_filter_from_the_real_rows():
    from envi_py.train.gail_env import WindowEnv

    logs = pid_logs()
    for lg in logs:
        lg.meta.controller = PID.to_json()
    cfg = model_config(logs, history=4, hidden=(16,), head="gaussian", extras=("play",), play_width=0.3)
    ck = new_checkpoint("gail", logs, [], cfg, 0, {})
    env = WindowEnv(ck, logs, horizon=12, stride=100)  # one start window per log: its sigma_0
    ro = env.rollout(torch.Generator().manual_seed(0))
    obs = ro.obs.numpy()
    width = ck.config.row_width
    for b in range(env.batch):
        rows = np.concatenate([obs[b, 0].reshape(4, width), obs[b, 1:, -width:]])  # sigma_0, then simulated
        np.testing.assert_allclose(rows[:, -1], play_offsets(rows[:, 1].astype(np.float64), 0.6), atol=1e-5)
