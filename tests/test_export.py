"""envi-export: one self-contained opset-17 file, rich metadata, onnxruntime parity with PyTorch."""

from __future__ import annotations

import json

import numpy as np
import onnx
import pytest
import torch

from envi_py.dataset import Normaliser
from envi_py.export import OPSET, PARITY_TOL, export, main, parity, parity_inputs, read_metadata, to_onnx
from envi_py.logs import LANE_KEEPING_SCHEMA
from envi_py.model import Checkpoint, EnvModel, ModelConfig, TrainingRecord

from .conftest import make_log


def paper_ckpt(head: str = "deterministic", seed: int = 0, **cfg) -> Checkpoint:
    """The paper's 20 -> 256 -> 256 -> 1 structure with seeded random weights and a full record."""
    torch.manual_seed(seed)
    logs = [make_log(np.linspace(5, 80, 30), run="a"), make_log(np.linspace(80, 5, 30), run="b")]
    model = EnvModel(ModelConfig(n_state=1, n_action=1, head=head, **cfg)).eval()
    if head == "gaussian":
        with torch.no_grad():
            model.log_std.bias.fill_(-1.0)
    record = TrainingRecord(
        "bc",
        seed,
        hyper={"epochs": 3},
        period_ms=40.0,
        data=[{"file": lg.name, "sha256": lg.sha256()} for lg in logs],
        controllers=[{"name": "lane-keeping", "params": {"x": 30.0}}],
    )
    return Checkpoint(model, Normaliser.fit(logs), LANE_KEEPING_SCHEMA, record)


@pytest.mark.parametrize("head", ["deterministic", "gaussian"])
def test_onnxruntime_matches_pytorch(head):
    ck = paper_ckpt(head)
    err = parity(ck, to_onnx(ck), n=8192, seed=3)
    assert err <= PARITY_TOL
    x = parity_inputs(20, 8192, 3)
    assert np.abs(x).max() > 100  # the parity set includes saturating inputs, not only [-1, 1]


def test_file_is_self_contained_opset17(tmp_path):
    path = export(paper_ckpt("gaussian"), tmp_path / "m.onnx")
    model = onnx.load(str(path), load_external_data=False)
    onnx.checker.check_model(model, full_check=True)
    assert [(o.domain, o.version) for o in model.opset_import] == [("", OPSET)]
    assert not list(tmp_path.glob("*.data")) and sorted(p.name for p in tmp_path.iterdir()) == ["m.onnx"]
    for t in model.graph.initializer:
        assert t.data_location == onnx.TensorProto.DEFAULT and not t.external_data
    assert {n.op_type for n in model.graph.node} == {"Gemm", "Tanh", "Clip"}
    assert [o.name for o in model.graph.output] == ["mean", "log_std"]


def test_metadata_describes_the_model(tmp_path):
    ck = paper_ckpt(round_to=(1.0,))
    meta = read_metadata(export(ck, tmp_path / "m.onnx"))
    assert meta["envi.schema"]["states"] == [{"name": "color", "unit": "%", "range": [0.0, 100.0], "resolution": 1.0}]
    assert meta["envi.schema"]["actions"][0]["name"] == "angle"
    np.testing.assert_array_equal(meta["envi.normaliser"]["low"], ck.norm.low)
    np.testing.assert_array_equal(meta["envi.normaliser"]["high"], ck.norm.high)
    assert meta["envi.history"] == 10 and meta["envi.period_ms"] == 40.0 and meta["envi.head"] == "deterministic"
    assert meta["envi.post"] == {"clamp": True, "limits": [[0.0, 100.0]], "round_to": [1.0]}
    assert meta["envi.algorithm"] == "bc" and meta["envi.controllers"] == ck.record.controllers
    assert [d["sha256"] for d in meta["envi.data"]] == [d["sha256"] for d in ck.record.data]
    assert meta["envi.version"] == ck.record.versions["envi"] and meta["envi.format"] == "envi-onnx"


def test_cli_writes_and_reports(tmp_path, capsys):
    ck_path = paper_ckpt().save(tmp_path / "m.pt")
    assert main([str(ck_path), "-o", str(tmp_path / "out.onnx")]) == 0
    assert "parity" in capsys.readouterr().out and (tmp_path / "out.onnx").stat().st_size > 250_000
    (tmp_path / "junk.pt").write_bytes(b"junk")
    assert main([str(tmp_path / "junk.pt"), "-o", str(tmp_path / "x.onnx")]) == 2  # bad input: one line, exit code 2
    assert "junk.pt" in capsys.readouterr().err and not (tmp_path / "x.onnx").exists()


def test_refuses_what_runtimes_cannot_feed():
    with pytest.raises(ValueError, match="derived channels"):
        to_onnx(paper_ckpt(extras=("dt",)))
    from envi_py.train.random import train_random

    with pytest.raises(ValueError, match="only MLP"):
        to_onnx(train_random([make_log(np.linspace(5, 80, 30))]))


def test_metadata_values_are_json():
    model = to_onnx(paper_ckpt())
    for prop in model.metadata_props:
        json.loads(prop.value)
