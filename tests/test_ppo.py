"""PPO pieces on toy problems with known answers."""

from __future__ import annotations

import torch

from envi_py.train.ppo import ValueNet, clipped_surrogate, gae, normalise, value_loss


def test_gae_matches_hand_computation() -> None:
    r = torch.tensor([[1.0, 0.0, 2.0]])
    v = torch.tensor([[0.5, 1.0, -1.0]])
    last = torch.tensor([3.0])
    g, lam = 0.9, 0.8
    d2 = 2.0 + g * 3.0 - (-1.0)
    d1 = 0.0 + g * (-1.0) - 1.0
    d0 = 1.0 + g * 1.0 - 0.5
    a2 = d2
    a1 = d1 + g * lam * a2
    a0 = d0 + g * lam * a1
    adv, ret = gae(r, v, last, g, lam)
    assert torch.allclose(adv, torch.tensor([[a0, a1, a2]]))
    assert torch.allclose(ret, adv + v)


def test_gae_with_lambda_one_is_discounted_return_minus_value() -> None:
    torch.manual_seed(0)
    r, v, last = torch.randn(4, 6), torch.randn(4, 6), torch.randn(4)
    g = 0.95
    adv, _ = gae(r, v, last, g, 1.0)
    ret = last.clone()
    for t in reversed(range(6)):
        ret = r[:, t] + g * ret
        assert torch.allclose(adv[:, t], ret - v[:, t], atol=1e-5)


def test_value_net_fits_a_known_target() -> None:
    torch.manual_seed(0)
    obs, to_go = torch.rand(512, 5) * 2 - 1, torch.rand(512)
    target = obs.sum(1) * to_go + 2.0
    net = ValueNet(5, (32, 32))
    opt = torch.optim.Adam(net.parameters(), lr=1e-2)
    start = value_loss(net, obs, to_go, target).item()
    for _ in range(400):
        loss = value_loss(net, obs, to_go, target)
        opt.zero_grad()
        loss.backward()
        opt.step()
    assert loss.item() < 0.01 * start and loss.item() < 0.05


def test_clipped_surrogate_stops_gradient_beyond_the_clip() -> None:
    old = torch.zeros(2)
    logp = torch.log(torch.tensor([1.5, 1.1])).requires_grad_()
    adv = torch.tensor([1.0, 1.0])
    loss, frac = clipped_surrogate(logp, old, adv, clip=0.2)
    loss.backward()
    assert logp.grad[0] == 0 and logp.grad[1] < 0  # ratio 1.5 is clipped, 1.1 still pushes up
    assert frac.item() == 0.5


def test_normalise_gives_zero_mean_unit_std() -> None:
    a = normalise(torch.tensor([1.0, 2.0, 3.0, 10.0]))
    assert abs(a.mean().item()) < 1e-6 and abs(a.std().item() - 1) < 1e-5
