"""GAIL: the discriminator, the batched window environment, and a short run that fixes a wrong model."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from envi_py.train.common import closed_loop_score, model_config, new_checkpoint
from envi_py.train.discriminator import Discriminator, bce_loss
from envi_py.train.gail import GailConfig, _Trainer, train_gail
from envi_py.train.gail_env import WindowEnv
from tests.conftest import make_log


def _lane_logs(n: int, seed: int, x: float = 30.0) -> list:
    """Logs of a simple lane-keeping plant: colour drifts with the steering angle, plus noise."""
    rng = np.random.default_rng(seed)
    logs = []
    for k in range(n):
        c = [40.0 + rng.normal(0, 5)]
        for _ in range(59):
            angle = np.sign(c[-1] - 40.0) * x
            c.append(float(np.clip(c[-1] - 0.25 * angle + rng.normal(0, 2.0), 0, 100)))
        logs.append(make_log(np.array(c), x=x, run=str(k)))
    return logs


def test_discriminator_separates_obviously_different_data() -> None:
    torch.manual_seed(0)
    disc = Discriminator(21, (64, 64))
    opt = torch.optim.Adam(disc.parameters(), lr=1e-2)
    real = (torch.rand(256, 20) * 0.2 + 0.5, torch.rand(256, 1) * 0.2 + 0.5)
    fake = (torch.rand(256, 20) * 0.2 - 0.7, torch.rand(256, 1) * 0.2 - 0.7)
    _, acc0 = bce_loss(disc, real, fake)
    for _ in range(30):
        loss, _ = bce_loss(disc, real, fake)
        opt.zero_grad()
        loss.backward()
        opt.step()
    loss, acc = bce_loss(disc, real, fake)
    assert acc == 1.0 and loss.item() < 0.05
    assert (disc.reward(*real) > disc.reward(*fake)).all()  # real-looking pairs earn more


def test_window_env_puts_the_controller_in_the_loop() -> None:
    logs = _lane_logs(3, 0)
    ckpt = new_checkpoint("gail", logs, [], model_config(logs, hidden=(8,), head="gaussian"), 0, {})
    env = WindowEnv(ckpt, logs, horizon=12, stride=5)
    assert env.batch == 3 * len(range(0, 60 - 10 - 12 + 1, 5))
    ro = env.rollout(torch.Generator().manual_seed(0))
    assert ro.obs.shape == (env.batch, 12, 20) and ro.log_prob.shape == (env.batch, 12)
    # the row appended after step t is (state, controller's answer): visible in the window at t+1
    norm = ckpt.norm
    state = norm.decode(np.concatenate([ro.next_state[:, 0].numpy(), np.zeros((env.batch, 1))], 1))[:, 0]
    angle = norm.decode(np.stack([np.zeros(env.batch), ro.obs[:, 1, -1].numpy()], 1))[:, 1]
    np.testing.assert_allclose(angle, np.sign(state - 40.0) * 30.0, atol=1e-3)
    assert torch.allclose(ro.obs[:, 1, -2], ro.next_state[:, 0, 0])
    again = env.rollout(torch.Generator().manual_seed(0))
    assert torch.equal(ro.action, again.action)


def test_short_gail_run_moves_a_wrong_model_toward_the_data() -> None:
    torch.manual_seed(0)
    logs = _lane_logs(4, 1)
    # unclamped: clamped to the observed range (the default since stop 21) the wrong model's states sit at
    # the range's top edge, which the discriminator tells from the data more slowly than 40 epochs allow
    cfg = model_config(logs, hidden=(32, 32), head="gaussian", round_to=None, limits=None)
    ckpt = new_checkpoint("gail", logs, [], cfg, 0, {})
    with torch.no_grad():  # deliberately wrong: always predicts a colour near the top of the range
        ckpt.model.mean.bias.fill_(1.5)
    trainer = _Trainer(
        ckpt,
        logs,
        GailConfig(
            lr=3e-3, disc_lr=3e-3, horizon=15, stride=10, minibatch=256, disc_hidden=(32, 32), value_hidden=(32, 32)
        ),
        seed=0,
    )
    x, y = (torch.from_numpy(a) for a in ckpt.dataset(logs).stacked())

    def one_step() -> float:
        with torch.no_grad():
            return (ckpt.model(x)[0] - y).abs().mean().item()

    before_step, before_loop = one_step(), closed_loop_score(ckpt, logs).distance
    for _ in range(40):
        stats = trainer.epoch()
    after_step, after_loop = one_step(), closed_loop_score(ckpt, logs).distance
    assert np.isfinite(stats["value_loss"]) and 0 <= stats["disc_acc"] <= 1
    assert after_step < 0.5 * before_step
    assert after_loop < before_loop


def test_train_gail_repeats_with_a_seed_and_writes_curves(tmp_path) -> None:
    logs = _lane_logs(4, 2)
    kw = dict(epochs=3, hidden=(8,), horizon=10, disc_hidden=(8,), value_hidden=(8,), eval_every=3)
    a = train_gail(logs[:2], logs[2:], seed=3, curves_dir=tmp_path, **kw)
    b = train_gail(logs[:2], logs[2:], seed=3, **kw)
    for (k, va), vb in zip(a.model.state_dict().items(), b.model.state_dict().values()):
        assert torch.equal(va, vb), k
    assert (tmp_path / "curves.png").stat().st_size > 0
    header = (tmp_path / "curves.csv").read_text().splitlines()
    assert header[0].startswith("epoch,disc_loss,disc_acc") and len(header) == 4
    assert a.record.algorithm == "gail" and a.record.selection["best_epoch"] == 3


def test_gail_refuses_a_deterministic_model() -> None:
    logs = _lane_logs(2, 3)
    ckpt = new_checkpoint("gail", logs, [], model_config(logs, hidden=(8,)), 0, {})
    env = WindowEnv(ckpt, logs, horizon=5)
    with pytest.raises(ValueError, match="stochastic"):
        env.rollout(torch.Generator().manual_seed(0))
