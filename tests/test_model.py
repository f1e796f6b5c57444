"""Model structure, checkpoint round trip and safe loading, closed-loop rollout."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from envi_py.controllers import ControllerSpec
from envi_py.dataset import Normaliser
from envi_py.export import to_onnx
from envi_py.logs import LANE_KEEPING_SCHEMA
from envi_py.model import Checkpoint, EnvModel, ModelConfig, TrainingRecord
from envi_py.simulate import rollout, simulate_logs

from .conftest import make_log


def small_ckpt(head: str = "deterministic", **cfg) -> Checkpoint:
    torch.manual_seed(0)
    logs = [make_log(np.linspace(5, 80, 30))]
    model = EnvModel(ModelConfig(n_state=1, n_action=1, hidden=(16, 16), head=head, **cfg))
    return Checkpoint(model.eval(), Normaliser.fit(logs), LANE_KEEPING_SCHEMA, TrainingRecord("bc", 0))


def test_paper_structure():
    m = EnvModel(ModelConfig(n_state=1, n_action=1))
    linears = [lin for lin in m.modules() if isinstance(lin, torch.nn.Linear)]
    assert [(lin.in_features, lin.out_features) for lin in linears] == [(20, 256), (256, 256), (256, 1)]
    out, log_std = m(torch.zeros(4, 20))
    assert out.shape == (4, 1) and log_std is None and torch.all(out.abs() <= 1)


def test_checkpoint_round_trip(tmp_path):
    ck = small_ckpt("gaussian", round_to=(1.0,))
    path = ck.save(tmp_path / "m.pt")
    back = Checkpoint.load(path)
    x = torch.randn(5, 20)
    for a, b in zip(ck.model(x), back.model(x)):
        torch.testing.assert_close(a, b)
    assert back.config.round_to == (1.0,) and back.config.head == "gaussian"
    assert back.record.versions["torch"] == str(torch.__version__)


@pytest.mark.parametrize(
    "part, key, value, says",
    [
        ("config", "limits", [(100.0, 0.0)], "limits must give each of the 1 states a finite low <= high"),
        ("config", "limits", [(float("nan"), 1.0)], "finite low <= high"),
        ("config", "round_to", [-1.0], "round_to must give each of the 1 states a resolution > 0"),
        ("record", "period_ms", 0.0, "period_ms must be a positive number of milliseconds"),
        ("record", "period_ms", float("nan"), "period_ms must be a positive number"),
    ],
)
def test_damaged_post_processing_is_refused_on_loading(tmp_path, part, key, value, says):
    """Values a consistent content hash can still carry (the record is not hashed): reversed limits
    once pinned every simulated state to one edge, and a bad period or resolution was taken by one
    engine and refused, naming no file, by the other."""
    from envi_py.model import _content_hash

    path = small_ckpt("gaussian", round_to=(1.0,), limits=((0.0, 100.0),)).save(tmp_path / "m.pt")
    blob = torch.load(path, weights_only=False)
    blob[part][key] = value
    blob["sha256"] = _content_hash(blob["config"], blob["norm"], blob["state_dict"], blob.get("members") or [])
    torch.save(blob, path)
    with pytest.raises(ValueError, match="m.pt: damaged envi checkpoint") as exc:
        Checkpoint.load(path)
    assert says in str(exc.value)


def test_loading_never_runs_pickled_code(tmp_path):
    class Evil:
        def __reduce__(self):
            return (print, ("pwned",))

    path = tmp_path / "evil.pt"
    torch.save({"format": "envi-model", "payload": Evil()}, path)
    with pytest.raises(ValueError, match="not an envi model checkpoint"):
        Checkpoint.load(path)
    (tmp_path / "junk.pt").write_bytes(b"not a model at all")
    with pytest.raises(ValueError, match="junk.pt"):
        Checkpoint.load(tmp_path / "junk.pt")
    with pytest.raises(ValueError, match="no such model file"):
        Checkpoint.load(tmp_path / "missing.pt")


def test_rollout_applies_controller_and_keeps_range():
    ck = small_ckpt(round_to=(1.0,))
    init = np.stack([make_log(np.linspace(20, 60, 10)).values, make_log(np.linspace(60, 20, 10)).values])
    out = rollout(ck, ControllerSpec("lane-keeping", {"x": 30}), init, steps=20, runs=2)
    assert out.shape == (4, 30, 2)
    np.testing.assert_array_equal(out[0, :10], init[0])
    np.testing.assert_array_equal(out[2, :10], init[1])
    sim = out[:, 10:]
    np.testing.assert_array_equal(sim[..., 1], np.sign(sim[..., 0] - 40) * 30)
    assert np.all(sim[..., 0] == np.round(sim[..., 0])) and sim[..., 0].min() >= 0 and sim[..., 0].max() <= 100


def test_stochastic_rollout_repeats_with_seed_and_varies_without():
    ck = small_ckpt("gaussian")
    with torch.no_grad():
        ck.model.log_std.bias.fill_(-1.0)
    init = make_log(np.linspace(20, 60, 10)).values[None]
    spec = ControllerSpec("lane-keeping", {"x": 30})
    a = rollout(ck, spec, init, 15, runs=3, seed=5)
    b = rollout(ck, spec, init, 15, runs=3, seed=5)
    c = rollout(ck, spec, init, 15, runs=3, seed=6)
    np.testing.assert_array_equal(a, b)
    assert not np.array_equal(a, c)
    assert not np.array_equal(a[0], a[1])  # runs from one window differ


def test_random_baseline_ignores_action():
    from envi_py.train.random import train_random

    logs = [make_log(np.linspace(5, 80, 30))]
    ck = train_random(logs)
    init = logs[0].values[:10][None]
    a = rollout(ck, ControllerSpec("lane-keeping", {"x": 10}), init, 50, seed=1)
    b = rollout(ck, ControllerSpec("lane-keeping", {"x": 50}), init, 50, seed=1)
    np.testing.assert_array_equal(a[..., 0], b[..., 0])
    assert a[0, 10:, 0].min() >= 5 and a[0, 10:, 0].max() <= 80 and a[0, 10:, 0].std() > 5


def test_simulated_logs_carry_metadata():
    ck = small_ckpt()
    src = make_log(np.linspace(20, 60, 40), run="7")
    logs = simulate_logs(ck, ControllerSpec("lane-keeping", {"x": 30}), [src], runs=2)
    assert len(logs) == 2 and len(logs[0]) == 40
    assert logs[0].meta.source == "sim" and logs[1].meta.run_id == "7-sim1"
    assert np.all(np.diff(logs[0].time) > 0)


def test_a_flipped_byte_or_a_nan_weight_is_refused_on_load(tmp_path):
    """Bit rot and hostile edits: the content hash catches a changed weight, the finiteness check a
    NaN (which a hash made after the edit would not)."""
    from envi_py.train.common import model_config, new_checkpoint

    logs = [make_log(np.linspace(20, 60, 30), run=str(i)) for i in range(2)]
    ck = new_checkpoint("bc", logs, [], model_config(logs, history=4, hidden=(8,)), 0, {})
    path = ck.save(tmp_path / "m.pt")
    blob = torch.load(path, weights_only=True)
    blob["state_dict"]["mean.weight"][0, 0] = 4e36
    torch.save(blob, tmp_path / "flipped.pt")
    with pytest.raises(ValueError, match="does not match its hash"):
        Checkpoint.load(tmp_path / "flipped.pt")
    with torch.no_grad():
        ck.model.mean.weight[0, 0] = float("nan")
    with pytest.raises(ValueError, match="NaN or inf"):
        ck.save(tmp_path / "nan.pt")
    blob["state_dict"]["mean.weight"][0, 0] = float("nan")
    blob.pop("sha256")  # an older or hand-made file without a hash
    torch.save(blob, tmp_path / "nan_nohash.pt")
    with pytest.raises(ValueError, match="NaN or inf"):
        Checkpoint.load(tmp_path / "nan_nohash.pt")


def test_the_torch_decoding_is_the_numpy_decoding():
    """GAIL's rollouts decode in torch, every other engine in numpy: one owner, two forms, equal."""
    from envi_py.train.common import model_config, new_checkpoint

    logs = [make_log(np.linspace(20, 60, 30), run=str(i)) for i in range(2)]
    ck = new_checkpoint("bc", logs, [], model_config(logs, history=4, hidden=(8,), round_to=(1.0,)), 0, {})
    z = np.random.default_rng(0).normal(0, 1.5, (500, 1))  # beyond [-1, 1] too: clamping must agree
    np.testing.assert_array_equal(ck.decode_states_torch(torch.from_numpy(z)).numpy(), ck.decode_states(z))
    rows = np.stack([lg.values[:4] for lg in logs])
    enc = ck.encode_rows(rows)
    np.testing.assert_allclose(enc, ck.norm.encode(rows), rtol=0, atol=1e-6)


def test_residual_head_predicts_the_change_from_the_last_state(tmp_path):
    ck = small_ckpt("gaussian", residual=True, history=4)
    cfg = ck.config
    x = torch.randn(6, cfg.in_features)
    plain = EnvModel(ModelConfig(n_state=1, n_action=1, hidden=(16, 16), head="gaussian", history=4))
    plain.load_state_dict(ck.model.state_dict())  # same weights, plain head
    (mean, log_std), (mean0, log_std0) = ck.model(x), plain(x)
    last = (cfg.history - 1) * cfg.row_width
    torch.testing.assert_close(mean, 2 * mean0 + x[:, last : last + cfg.n_state])  # any change in range
    torch.testing.assert_close(log_std, log_std0)
    # a zero output of the head keeps the state where the window's last row left it
    with torch.no_grad():
        ck.model.mean.weight.zero_(), ck.model.mean.bias.zero_()
    torch.testing.assert_close(ck.model(x)[0], x[:, last : last + 1])
    assert cfg.plain  # its input is the window alone: the exporter and the native engine run it
    assert to_onnx(ck).graph.node  # exported (tests/test_residual_export.py checks the graph against PyTorch)
    back = Checkpoint.load(ck.save(tmp_path / "r.pt"))
    assert back.config.residual
    torch.testing.assert_close(back.model(x)[0], ck.model(x)[0])


def test_a_residual_saturating_state_changes_from_its_last_reading_in_range():
    cfg = ModelConfig(
        n_state=2, n_action=1, history=4, hidden=(8,), head="gaussian", residual=True, limit_events=((1, 255.0),)
    )
    model = EnvModel(cfg)
    model.limit_levels.fill_(1.0)  # 255 encodes to +1
    w = cfg.row_width
    x = torch.zeros(3, cfg.in_features)
    x[:, 1::w] = torch.tensor([[0.1, 0.2, 0.3, 0.4], [0.1, 0.2, 1.0, 1.0], [1.0, 1.0, 1.0, 1.0]])
    x[:, 0::w] = torch.tensor([0.5, -0.5, 0.25])[:, None]
    base = model.residual_base(x)
    # the colour-like state: its last reading; the distance: the last one not at 255, else 255
    torch.testing.assert_close(base[:, 0], torch.tensor([0.5, -0.5, 0.25]))
    torch.testing.assert_close(base[:, 1], torch.tensor([0.4, 0.2, 1.0]))


def test_training_sets_the_normalised_limit_levels(tmp_path):
    from envi_py.train.bc import train_bc
    from envi_py.twin.car import generate_car_versions

    logs = generate_car_versions(2, seed=5, versions=[0, 2], far_start_prob=0.7)
    ck = train_bc(logs, epochs=1, hidden=(8,), history=3, residual=True)
    assert ck.config.limit_events == ((1, 255.0),)
    want = ck.norm.encode(np.array([[0.0, 255.0, 0.0, 0.0]]))[0, 1]
    assert ck.model.limit_levels.tolist() == pytest.approx([want])
    back = Checkpoint.load(ck.save(tmp_path / "m.pt"))
    assert back.model.limit_levels.tolist() == pytest.approx([want])


def test_a_failed_save_leaves_no_temporary_file(tmp_path, monkeypatch):
    """Interrupted or failing mid-write (here: torch.save raising), the checkpoint's temporary file goes
    and the error propagates; an existing model file is untouched."""
    ck = small_ckpt()
    path = ck.save(tmp_path / "m.pt")
    before = path.read_bytes()

    def broken(_obj, fh, *_args, **_kwargs):
        fh.write(b"half")
        assert list(tmp_path.glob(".m.pt*.tmp")), "the checkpoint is not written through a temporary file"
        raise KeyboardInterrupt

    monkeypatch.setattr(torch, "save", broken)
    with pytest.raises(KeyboardInterrupt):
        ck.save(path)
    assert not list(tmp_path.glob(".*.tmp")) and path.read_bytes() == before
