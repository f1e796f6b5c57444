"""A checkpoint as one self-describing ONNX file (the ``envi-export`` command: :mod:`envi_py.export_cli`).

The graph is built directly with ``onnx.helper`` from the checkpoint's weights rather than traced:
the model is a plain chain of ``Gemm`` and ``Tanh`` (the Gaussian head adds a second ``Gemm`` and
a ``Clip`` for the log-std), which is exactly what the native runtime's loader accepts, and tracing
would pull in torch's dynamo exporter and onnxscript for no gain. A residual mean head adds a fixed
group of ``residual.*`` nodes (:func:`_residual_base`) that the loader checks against the metadata
``envi.residual`` and computes natively. Everything a runtime needs to
close the loop without the checkpoint (schema, normalisation, history, post-processing) and
everything needed to trace the model back to its data goes into ``metadata_props`` as JSON. The
last entry, ``envi.content_sha256``, hashes the graph, its weights and that metadata
(:func:`content_sha256`): the native runtime recomputes it and refuses a file changed after export.
"""

from __future__ import annotations

import hashlib
import json
import struct
from collections.abc import Iterator, Sequence
from dataclasses import asdict
from pathlib import Path
from typing import Any

import numpy as np
import onnx
from onnx import TensorProto, helper, numpy_helper

from . import __version__
from .atomic import atomic_write
from .effect_layers import layers_json
from .model import LIMIT_LEVEL_TOL, LOG_STD_MAX, LOG_STD_MIN, RESIDUAL_SCALE, Checkpoint

OPSET = 17
FORMAT = "envi-onnx"
FORMAT_VERSION = 1
INPUT = "window"
PARITY_TOL = 1e-5
#: metadata key of the content hash, and the version tag its canonical serialisation starts with
CONTENT_KEY = "envi.content_sha256"
CONTENT_VERSION = "envi-content-v1"
#: metadata key of a residual mean head's description (null for a model without one)
RESIDUAL_KEY = "envi.residual"


def post_processing(ckpt: Checkpoint) -> dict[str, Any]:
    """The simulator's output post-processing with the limits resolved, as ``Checkpoint.post_process`` does."""
    cfg = ckpt.config
    low, high = ckpt.limits()
    return {
        "clamp": bool(cfg.clamp),
        "limits": [[float(lo), float(hi)] for lo, hi in zip(low, high)],
        "round_to": None if cfg.round_to is None else list(cfg.round_to),
    }


def residual_metadata(ckpt: Checkpoint) -> dict[str, Any] | None:
    """``envi.residual``: ``mean = scale * tanh(head) + base``, the base each state's last reading in
    the window; for each ``[state, level]`` of ``limit_levels`` (a limit event's reading, normalised)
    the last reading farther than ``tolerance`` from ``level``, the last reading when none is. None
    for a model whose mean head is not residual."""
    cfg = ckpt.config
    if not cfg.residual:
        return None
    levels = ckpt.model.limit_levels.tolist() if cfg.limit_events else []
    return {
        "scale": RESIDUAL_SCALE,
        "tolerance": LIMIT_LEVEL_TOL,
        "limit_levels": [[i, float(level)] for (i, _), level in zip(cfg.limit_events, levels)],
    }


def metadata(ckpt: Checkpoint) -> dict[str, str]:
    """``metadata_props``: every value is JSON so any runtime parses it the same way."""
    cfg, rec = ckpt.config, ckpt.record
    items: dict[str, Any] = {
        "envi.format": FORMAT,
        "envi.format_version": FORMAT_VERSION,
        "envi.version": __version__,
        "envi.schema": ckpt.schema.to_json(),
        "envi.normaliser": ckpt.norm.to_json(),
        "envi.history": cfg.history,
        "envi.period_ms": rec.period_ms,
        "envi.head": cfg.head,
        "envi.log_std_range": [LOG_STD_MIN, LOG_STD_MAX],
        "envi.post": post_processing(ckpt),
        "envi.limit_events": [[i, v] for i, v in cfg.limit_events],
        RESIDUAL_KEY: residual_metadata(ckpt),
        "envi.layers": layers_json(ckpt.layers),
        "envi.noise_dof": list(cfg.noise_dof),
        "envi.noise_mix": [list(pk) for pk in cfg.noise_mix],
        "envi.context": cfg.context,
        "envi.config": asdict(cfg),
        "envi.algorithm": rec.algorithm,
        "envi.seed": rec.seed,
        "envi.hyper": rec.hyper,
        "envi.data": rec.data,
        "envi.validation": rec.validation,
        "envi.controllers": rec.controllers,
        "envi.selection": rec.selection,
        "envi.versions": rec.versions,
        "envi.system": None if ckpt.system is None else ckpt.system.to_json(),
    }
    return {k: json.dumps(v, allow_nan=True) for k, v in items.items()}


def _canonical_parts(model: onnx.ModelProto) -> Iterator[bytes]:
    """The bytes :func:`content_sha256` hashes, in order; the C++ loader (cpp/src/onnx_loader.cpp,
    ``content_digest``) builds the very same sequence. Counts and lengths are little-endian u64."""

    def u64(v: int) -> bytes:
        return struct.pack("<Q", v & 0xFFFFFFFFFFFFFFFF)

    def text(v: str | bytes) -> bytes:
        b = v.encode() if isinstance(v, str) else v
        return u64(len(b)) + b

    def texts(vs: Sequence[str]) -> bytes:
        return u64(len(vs)) + b"".join(text(v) for v in vs)

    g = model.graph
    yield text(CONTENT_VERSION)
    yield texts([v.name for v in g.input])
    yield texts([v.name for v in g.output])
    yield u64(len(g.node))
    for n in g.node:
        yield text(n.op_type) + text(n.domain) + text(n.name) + texts(n.input) + texts(n.output) + u64(len(n.attribute))
        for a in n.attribute:
            yield text(a.name)
            yield b"\x01" + u64(a.i) if a.HasField("i") else b"\x00"
            yield b"\x01" + struct.pack("<f", a.f) if a.HasField("f") else b"\x00"
    yield u64(len(g.initializer))
    for t in sorted(g.initializer, key=lambda t: t.name.encode()):
        values = numpy_helper.to_array(t)
        yield text(t.name) + struct.pack("<I", t.data_type) + u64(len(t.dims)) + b"".join(u64(d) for d in t.dims)
        raw = np.ascontiguousarray(values, dtype=values.dtype.newbyteorder("<")).tobytes()
        yield u64(len(raw)) + raw
    entries = sorted(
        (p.key.encode(), p.value.encode())
        for p in model.metadata_props
        if p.key.startswith("envi.") and p.key != CONTENT_KEY
    )
    yield u64(len(entries))
    for key, value in entries:
        yield text(key) + text(value)


def content_sha256(model: onnx.ModelProto) -> str:
    """SHA-256 (hex) over a canonical serialisation of the graph (inputs, outputs, nodes in order),
    its initializers (sorted by name: name, data type, shape, little-endian values) and the
    ``envi.*`` metadata but the hash itself (sorted by key). Canonical rather than over the file's
    bytes, because protobuf does not fix one encoding of a message; the runtime recomputes it and
    refuses a file that was changed after export."""
    h = hashlib.sha256()
    for part in _canonical_parts(model):
        h.update(part)
    return h.hexdigest()


def _dense(nodes: list, inits: list, x: str, weight: np.ndarray, bias: np.ndarray, name: str) -> str:
    """``Gemm(x, W, b, transB=1)``: torch's Linear layout, no transpose copy of the weights."""
    inits += [
        numpy_helper.from_array(np.ascontiguousarray(weight, dtype=np.float32), f"{name}.weight"),
        numpy_helper.from_array(np.ascontiguousarray(bias, dtype=np.float32), f"{name}.bias"),
    ]
    nodes.append(
        helper.make_node("Gemm", [x, f"{name}.weight", f"{name}.bias"], [f"{name}.out"], name=f"{name}.gemm", transB=1)
    )
    return f"{name}.out"


def _int64(inits: list, name: str, values: Sequence[int] | np.ndarray) -> str:
    """An int64 constant (the indices and axes ``Slice``, ``Gather`` and ``Squeeze`` take); its name."""
    inits.append(numpy_helper.from_array(np.asarray(values, dtype=np.int64), name))
    return name


def _residual_base(nodes: list, inits: list, ckpt: Checkpoint) -> str:
    """``EnvModel.residual_base`` as nodes named ``residual.*``: the window's last row's state columns
    (a ``Slice``); with limit events, each state's last reading in range instead. For that, the state
    columns of every row are gathered (N, l, |s|) and compared with each state's limit level (+inf for
    a state without a limit event: every reading of it is in range); ``ArgMax`` with
    ``select_last_index`` finds the last row in range, and the last row when none is (all ties)."""
    cfg = ckpt.config
    rows, c, ns = cfg.history, cfg.row_width, cfg.n_state
    axis = _int64(inits, "residual.axis", [1])
    if not cfg.limit_events:
        start = (rows - 1) * c
        starts, ends = _int64(inits, "residual.starts", [start]), _int64(inits, "residual.ends", [start + ns])
        nodes.append(helper.make_node("Slice", [INPUT, starts, ends, axis], ["residual.base"], name="residual.base"))
        return "residual.base"
    levels = np.full(ns, np.inf, dtype=np.float32)
    for (i, _), level in zip(cfg.limit_events, ckpt.model.limit_levels.tolist()):
        levels[i] = level
    inits += [
        numpy_helper.from_array(levels, "residual.levels"),
        numpy_helper.from_array(np.array(LIMIT_LEVEL_TOL, np.float32), "residual.tolerance"),
    ]
    index = _int64(inits, "residual.rows.index", np.arange(rows)[:, None] * c + np.arange(ns)[None, :])
    steps = [
        ("Gather", [INPUT, index], "residual.rows", {"axis": 1}),  # (N, l, |s|)
        ("Sub", ["residual.rows", "residual.levels"], "residual.offset", {}),
        ("Abs", ["residual.offset"], "residual.distance", {}),
        ("Greater", ["residual.distance", "residual.tolerance"], "residual.in_range", {}),
        ("Cast", ["residual.in_range"], "residual.in_range_float", {"to": TensorProto.FLOAT}),
        ("ArgMax", ["residual.in_range_float"], "residual.last_in_range", {"axis": 1, "select_last_index": 1}),
        ("GatherElements", ["residual.rows", "residual.last_in_range"], "residual.picked", {"axis": 1}),
        ("Squeeze", ["residual.picked", axis], "residual.base", {}),  # (N, |s|)
    ]
    for op, inputs, out, attrs in steps:
        nodes.append(helper.make_node(op, inputs, [out], name=out, **attrs))
    return "residual.base"


def _mean_output(nodes: list, inits: list, ckpt: Checkpoint, head: str) -> None:
    """``mean`` from the mean head's ``Gemm`` output: its tanh, scaled and added to the residual base
    for a residual head (``EnvModel.heads``)."""
    if not ckpt.config.residual:
        nodes.append(helper.make_node("Tanh", [head], ["mean"], name="mean_head.act"))
        return
    nodes.append(helper.make_node("Tanh", [head], ["mean_head.tanh"], name="mean_head.act"))
    base = _residual_base(nodes, inits, ckpt)
    inits.append(numpy_helper.from_array(np.array(RESIDUAL_SCALE, np.float32), "residual.scale"))
    nodes += [
        helper.make_node("Mul", ["mean_head.tanh", "residual.scale"], ["residual.change"], name="residual.change"),
        helper.make_node("Add", ["residual.change", base], ["mean"], name="residual.add"),
    ]


def to_onnx(ckpt: Checkpoint) -> onnx.ModelProto:
    """The model as an opset-17 graph: ``window`` (N, l*C) normalised -> ``mean`` [and ``log_std``] (N, |s|)
    [and ``event_logit`` (N, e): the limit events' logits, metadata ``envi.limit_events`` says whose].
    A residual mean head adds its base (the ``residual.*`` nodes, metadata ``envi.residual``). With a run
    context (metadata ``envi.context``) the input ends with it, (N, l*C + 2|s|): each state's mean and
    population sd over sigma_0's l normalised rows (:func:`envi_py.dataset.context_of`)."""
    cfg = ckpt.config
    if ckpt.members:  # one network per file: never member 0 in the ensemble's name
        raise ValueError(f"a seed ensemble of {ckpt.size} members: export one member at a time (Checkpoint.member)")
    if cfg.kind != "mlp":
        raise ValueError(f"only MLP models can be exported, this one is {cfg.kind!r}")
    if cfg.extras:
        raise ValueError(
            "models with derived channels cannot be exported yet "
            "(the runtimes only feed the window of logged channels, and a run context, to the model)"
        )
    if cfg.context and not cfg.hidden:
        raise ValueError("a model with a run context needs a hidden layer to be exported (the runtime adds it there)")
    sd = {k: v.detach().cpu().numpy() for k, v in ckpt.model.state_dict().items()}
    nodes: list = []
    inits: list = []
    h = INPUT
    for i in range(len(cfg.hidden)):
        h = _dense(nodes, inits, h, sd[f"body.{2 * i}.weight"], sd[f"body.{2 * i}.bias"], f"body{i}")
        nodes.append(helper.make_node("Tanh", [h], [f"body{i}.tanh"], name=f"body{i}.act"))
        h = f"body{i}.tanh"
    _mean_output(nodes, inits, ckpt, _dense(nodes, inits, h, sd["mean.weight"], sd["mean.bias"], "mean_head"))
    outputs = [helper.make_tensor_value_info("mean", TensorProto.FLOAT, ["N", cfg.n_state])]
    if cfg.head == "gaussian":
        s = _dense(nodes, inits, h, sd["log_std.weight"], sd["log_std.bias"], "log_std_head")
        inits += [
            numpy_helper.from_array(np.array(LOG_STD_MIN, np.float32), "log_std_min"),
            numpy_helper.from_array(np.array(LOG_STD_MAX, np.float32), "log_std_max"),
        ]
        nodes.append(helper.make_node("Clip", [s, "log_std_min", "log_std_max"], ["log_std"], name="log_std_head.clip"))
        outputs.append(helper.make_tensor_value_info("log_std", TensorProto.FLOAT, ["N", cfg.n_state]))
    if cfg.limit_events:
        if cfg.head != "gaussian":
            raise ValueError("limit events are exported with a Gaussian head only")
        e = _dense(nodes, inits, h, sd["event.weight"], sd["event.bias"], "event_head")
        nodes.append(helper.make_node("Identity", [e], ["event_logit"], name="event_head.out"))
        outputs.append(helper.make_tensor_value_info("event_logit", TensorProto.FLOAT, ["N", len(cfg.limit_events)]))
    graph = helper.make_graph(
        nodes,
        "envi_env_model",
        [helper.make_tensor_value_info(INPUT, TensorProto.FLOAT, ["N", cfg.in_features])],
        outputs,
        inits,
    )
    model = helper.make_model(
        graph, opset_imports=[helper.make_opsetid("", OPSET)], producer_name="envi", producer_version=__version__
    )
    model.ir_version = 8  # the newest IR that opset 17 runtimes of 2022 onwards all read
    helper.set_model_props(model, metadata(ckpt))
    model.metadata_props.add(key=CONTENT_KEY, value=json.dumps(content_sha256(model)))
    onnx.checker.check_model(model, full_check=True)
    return model


def parity_inputs(in_features: int, n: int = 4096, seed: int = 0) -> np.ndarray:
    """Seeded windows: in-range, slightly beyond, and large (saturating tanh) values."""
    rng = np.random.default_rng(seed)
    parts = [
        rng.uniform(-1, 1, (n // 2, in_features)),
        rng.normal(0, 2, (n // 4, in_features)),
        rng.normal(0, 50, (n - n // 2 - n // 4, in_features)),
    ]
    return np.concatenate(parts).astype(np.float32)


def parity(ckpt: Checkpoint, model: onnx.ModelProto, n: int = 4096, seed: int = 0) -> float:
    """Max difference between onnxruntime and the PyTorch model over every output: absolute for values
    within [-1, 1], relative beyond. A residual mean is its base (an input, up to 175 in the parity set)
    plus a change, and float32 spaces values of that size 1.5e-5 apart: one rounding of the sum must
    not count as drift."""
    import onnxruntime as ort
    import torch

    x = parity_inputs(ckpt.config.in_features, n, seed)
    sess = ort.InferenceSession(model.SerializeToString(), providers=["CPUExecutionProvider"])
    got = sess.run(None, {INPUT: x})
    with torch.no_grad():
        want = [t for t in ckpt.model.heads(torch.from_numpy(x)) if t is not None]
    return max(float(np.max(np.abs(g - w.numpy()) / np.maximum(1, np.abs(w.numpy())))) for g, w in zip(got, want))


def export(ckpt: Checkpoint, path: str | Path, check: bool = True) -> Path:
    """Write ``ckpt`` as ONNX; with ``check`` refuse a file whose onnxruntime output drifts from PyTorch."""
    model = to_onnx(ckpt)
    if check:
        err = parity(ckpt, model)
        if not err <= PARITY_TOL:
            raise ValueError(f"onnxruntime differs from PyTorch by {err:.3g} (> {PARITY_TOL:g}); not written")
    path = Path(path)
    if path.is_dir():
        raise ValueError(f"{path}: is a folder; give the ONNX file to write")
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise ValueError(f"{path}: cannot create its folder: {exc.strerror or exc}") from exc
    data = model.SerializeToString()
    try:  # a reader never sees half a model
        return atomic_write(path, lambda fh: fh.write(data))
    except OSError as exc:
        raise ValueError(f"{path}: cannot write: {exc.strerror or exc}") from exc


def read_metadata(path: str | Path) -> dict[str, Any]:
    """The ``envi.*`` metadata of an exported file, JSON-decoded."""
    model = onnx.load(str(path), load_external_data=False)
    return {p.key: json.loads(p.value) for p in model.metadata_props if p.key.startswith("envi.")}
