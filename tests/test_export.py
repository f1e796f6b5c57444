"""envi-export: one self-contained opset-17 file, rich metadata, onnxruntime parity with PyTorch."""

from __future__ import annotations

import hashlib
import json
import struct

import numpy as np
import onnx
import pytest
import torch
from onnx import helper, numpy_helper

from envi_py import native
from envi_py.dataset import Normaliser
from envi_py.export import (
    CONTENT_KEY,
    OPSET,
    PARITY_TOL,
    content_sha256,
    export,
    parity,
    parity_inputs,
    read_metadata,
    to_onnx,
)
from envi_py.export_cli import main
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


def with_metadata(ckpt: Checkpoint, key: str, value: object) -> bytes:
    """``ckpt`` exported with metadata ``key`` replaced by ``value`` and the content hash made again:
    a file only the loader's own checks can refuse."""
    model = to_onnx(ckpt)
    for p in model.metadata_props:
        if p.key == key:
            p.value = json.dumps(value)
    kept = [p for p in model.metadata_props if p.key != CONTENT_KEY]
    del model.metadata_props[:]
    model.metadata_props.extend(kept)
    model.metadata_props.add(key=CONTENT_KEY, value=json.dumps(content_sha256(model)))
    return model.SerializeToString()


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
    # an output that is a folder, or under a file: one line naming it, exit code 2, no temporary file left
    (tmp_path / "afile").write_text("x")
    for out in (tmp_path, tmp_path / "afile" / "x.onnx"):
        assert main([str(ck_path), "-o", str(out), "--no-check"]) == 2
        err = capsys.readouterr().err
        assert err.count("\n") == 1 and str(out) in err
    assert not list(tmp_path.glob(".*.tmp"))


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


def _tiny_model(weight: np.ndarray, meta: dict[str, str]) -> onnx.ModelProto:
    """One Gemm with one attribute, one initializer, the given metadata: small enough to serialise by hand."""
    node = helper.make_node("Gemm", ["x", "w"], ["y"], name="g", transB=1)
    graph = helper.make_graph(
        [node],
        "t",
        [helper.make_tensor_value_info("x", onnx.TensorProto.FLOAT, [1, 2])],
        [helper.make_tensor_value_info("y", onnx.TensorProto.FLOAT, [1, 2])],
        [numpy_helper.from_array(weight, "w")],
    )
    model = helper.make_model(graph)
    helper.set_model_props(model, meta)
    return model


def test_content_hash_is_sha256_of_the_documented_serialisation():
    """The canonical bytes written out by hand from the format's description, hashed with hashlib."""
    w = np.array([[1.0, -2.0], [0.5, 3.0]], np.float32)
    meta = {"envi.b": '"second"', "envi.a": "1", "other": "not hashed", CONTENT_KEY: '"ignored"'}

    def u64(v: int) -> bytes:
        return struct.pack("<Q", v)

    def s(v: str) -> bytes:
        return u64(len(v.encode())) + v.encode()

    want = (
        s("envi-content-v1")
        + u64(1) + s("x")  # graph inputs
        + u64(1) + s("y")  # graph outputs
        + u64(1) + s("Gemm") + s("") + s("g") + u64(2) + s("x") + s("w") + u64(1) + s("y")
        + u64(1) + s("transB") + b"\x01" + u64(1) + b"\x00"  # attribute: has i = 1, no f
        + u64(1) + s("w") + struct.pack("<I", 1) + u64(2) + u64(2) + u64(2) + u64(16) + w.astype("<f4").tobytes()
        + u64(2) + s("envi.a") + s("1") + s("envi.b") + s('"second"')  # sorted by key, the hash left out
    )  # fmt: skip
    assert content_sha256(_tiny_model(w, meta)) == hashlib.sha256(want).hexdigest()
    flipped = w.copy()
    flipped.view(np.uint32)[0, 0] ^= 1  # the lowest mantissa bit of one weight
    assert content_sha256(_tiny_model(flipped, meta)) != content_sha256(_tiny_model(w, meta))
    assert content_sha256(_tiny_model(w, {**meta, "envi.a": "2"})) != content_sha256(_tiny_model(w, meta))
    assert content_sha256(_tiny_model(w, {**meta, "other": "x"})) == content_sha256(_tiny_model(w, meta))


@pytest.mark.parametrize("head", ["deterministic", "gaussian"])
def test_export_stores_the_content_hash_last(tmp_path, head):
    model = onnx.load(str(export(paper_ckpt(head), tmp_path / "m.onnx")))
    assert model.metadata_props[-1].key == CONTENT_KEY
    assert json.loads(model.metadata_props[-1].value) == content_sha256(model)
    assert read_metadata(tmp_path / "m.onnx")[CONTENT_KEY] == content_sha256(model)


@pytest.mark.skipif(not native.available(), reason="native engine not built")
def test_the_engines_sha256_is_hashlibs():
    """The C++ SHA-256 against hashlib on every length across the padding boundaries and a long input."""
    rng = np.random.default_rng(7)
    engine = native._native()
    for n in [*range(0, 200), 447, 448, 1000, 4096, 65_537, 1_000_003]:
        data = rng.integers(0, 256, n, dtype=np.uint8).tobytes()
        assert engine.sha256_hex(data) == hashlib.sha256(data).hexdigest(), n


@pytest.mark.skipif(not native.available(), reason="native engine not built")
@pytest.mark.parametrize("head", ["deterministic", "gaussian"])
def test_the_engine_computes_the_exported_hash(head):
    model = to_onnx(paper_ckpt(head, seed=3, round_to=(1.0,)))
    assert native._native().content_sha256(model.SerializeToString()) == content_sha256(model)
