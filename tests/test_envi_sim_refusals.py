"""envi_sim and the native loader refuse what a review found them running or overwriting: an export
with non-finite weights or normaliser (hash made over them), an unknown value of an enumerated
metadata entry (envi.head "laplace", ...), an --out folder that already holds logs (as envi simulate
refuses it, unless --force), and a bad --controller @FILE, named by its file. Each refusal is one
stderr line naming the file, exit code 2, and nothing already recorded lost or mixed."""

from __future__ import annotations

import json
import subprocess
from pathlib import Path

import numpy as np
import onnx
import pytest
from onnx import numpy_helper

from envi_py import native
from envi_py.export import CONTENT_KEY, content_sha256, to_onnx

from .test_envi_sim_bad_input import LINES
from .test_export import paper_ckpt
from .test_native import envi_sim

pytestmark = pytest.mark.skipif(envi_sim() is None, reason="envi_sim binary not built")


def rehashed(model: onnx.ModelProto) -> bytes:
    """The file with its content hash made again: only the loader's own checks can refuse it."""
    keep = [p for p in model.metadata_props if p.key != CONTENT_KEY]
    del model.metadata_props[:]
    model.metadata_props.extend(keep)
    model.metadata_props.add(key=CONTENT_KEY, value=json.dumps(content_sha256(model)))
    return model.SerializeToString()


def sim(model: Path, init: Path, *options: str) -> subprocess.CompletedProcess:
    cmd = [envi_sim(), "--model", str(model), "--init", str(init), "--steps", "5", "--threads", "1", *options]
    return subprocess.run(cmd, capture_output=True, text=True, timeout=60, check=False)


def refused(done: subprocess.CompletedProcess, *named: str) -> str:
    """Exit 2 and one stderr line 'envi_sim: ...' holding every `named` text; nothing on stdout."""
    lines = done.stderr.splitlines()
    assert done.returncode == 2, (done.returncode, done.stderr)
    assert len(lines) == 1 and lines[0].startswith("envi_sim: "), done.stderr
    for text in named:
        assert text in lines[0], (text, lines[0])
    assert done.stdout == ""
    return lines[0]


def folder_bytes(folder: Path) -> dict[str, bytes]:
    """Every entry of `folder` (hidden ones too: a staging folder left behind is a failure)."""
    return {p.name: p.read_bytes() if p.is_file() else b"<dir>" for p in sorted(folder.iterdir())}


@pytest.fixture()
def init_log(tmp_path) -> Path:
    path = tmp_path / "init" / "log_30_0.csv"
    path.parent.mkdir()
    path.write_text("\n".join(LINES) + "\n")
    return path


@pytest.fixture(scope="module")
def gaussian() -> onnx.ModelProto:
    """The paper's model with a Gaussian head: weights, biases and Clip bounds of three heads."""
    return to_onnx(paper_ckpt("gaussian"))


# ---------------------------------------------------------------- 1. non-finite weights and normaliser

WEIGHTS = ["body0.weight", "body1.bias", "mean_head.weight", "log_std_head.bias"]


@pytest.mark.parametrize("value", [np.nan, np.inf, -np.inf])
@pytest.mark.parametrize("name", WEIGHTS)
def test_a_non_finite_weight_is_refused_naming_file_and_initializer(name, value, gaussian, init_log, tmp_path):
    model = onnx.ModelProto()
    model.CopyFrom(gaussian)
    names = {t.name: i for i, t in enumerate(model.graph.initializer)}
    assert name in names, sorted(names)  # the export's naming: the case must damage a real weight
    tensor = model.graph.initializer[names[name]]
    values = numpy_helper.to_array(tensor).copy()
    values.flat[values.size // 2] = value
    tensor.CopyFrom(numpy_helper.from_array(values, tensor.name))
    path = tmp_path / "damaged.onnx"
    path.write_bytes(rehashed(model))
    out, metrics = tmp_path / "sim", tmp_path / "m.json"
    line = refused(sim(path, init_log, "--out", str(out), "--metrics", str(metrics)), str(path), f"'{name}'")
    assert ("NaN" if np.isnan(value) else "inf") in line
    assert not out.exists() and not metrics.exists()
    with pytest.raises(ValueError, match=f"initializer '{name}'"):
        native.load(path)


def test_the_undamaged_export_runs(gaussian, init_log, tmp_path):
    """The damaged files above differ from this one by one value: each refusal is that value's."""
    path = tmp_path / "m.onnx"
    path.write_bytes(rehashed(gaussian))
    done = sim(path, init_log, "--metrics-only", "--metrics", "-")
    assert done.returncode == 0, done.stderr
    assert all(np.isfinite(v) for v in json.loads(done.stdout)["mean"])


def with_meta(model: onnx.ModelProto, key: str, value: object) -> bytes:
    edited = onnx.ModelProto()
    edited.CopyFrom(model)
    entry = next(p for p in edited.metadata_props if p.key == key)
    entry.value = json.dumps(value, allow_nan=True)
    return rehashed(edited)


def test_a_non_finite_normaliser_is_refused_naming_file_and_key(gaussian, init_log, tmp_path):
    norm = json.loads(next(p.value for p in gaussian.metadata_props if p.key == "envi.normaliser"))
    norm["low"][0] = float("nan")
    path = tmp_path / "nannorm.onnx"
    path.write_bytes(with_meta(gaussian, "envi.normaliser", norm))
    refused(sim(path, init_log, "--metrics-only", "--metrics", "-"), str(path), "'envi.normaliser'", "'color'")


# ---------------------------------------------------------------- 2. enumerated metadata

#: (key, value, texts the error line must hold besides the file): each value is one the loader does
#: not know, or one that contradicts the graph (a Gaussian head's file declared deterministic).
METADATA_CASES = {
    "unknown head": ("envi.head", "laplace", ["'envi.head'", '"laplace"', "'deterministic', 'gaussian'"]),
    "head not a string": ("envi.head", None, ["'envi.head'", "'deterministic', 'gaussian'"]),
    "head contradicts the graph": ("envi.head", "deterministic", ["'envi.head'", "log_std"]),
    "newer format version": ("envi.format_version", 2, ["'envi.format_version'", "known versions: 1"]),
    "clamp not a boolean": (
        "envi.post",
        {"clamp": "yes", "limits": [[0.0, 100.0]], "round_to": None},
        ["'envi.post'", "'clamp'", "true, false"],
    ),
    "unknown effect layer": ("envi.layers", [{"kind": "wind", "value": 1}], ["'envi.layers'", "'wind'", "'delay'"]),
}


@pytest.mark.parametrize("case", list(METADATA_CASES))
def test_an_unknown_metadata_value_is_refused_naming_file_key_and_known_values(case, gaussian, init_log, tmp_path):
    key, value, texts = METADATA_CASES[case]
    path = tmp_path / "meta.onnx"
    path.write_bytes(with_meta(gaussian, key, value))
    out = tmp_path / "sim"
    refused(sim(path, init_log, "--out", str(out)), str(path), *texts)
    assert not out.exists()


# ---------------------------------------------------------------- 3. --out holding logs


@pytest.fixture()
def model(tmp_path) -> Path:
    path = tmp_path / "m.onnx"
    path.write_bytes(to_onnx(paper_ckpt()).SerializeToString())
    return path


def test_out_holding_logs_is_refused_and_kept_unless_force(model, init_log, tmp_path):
    out = tmp_path / "sim"
    first = sim(model, init_log, "--runs", "2", "--seed", "1", "--out", str(out))
    assert first.returncode == 0, first.stderr
    (out / "notes.txt").write_text("mine")
    before = folder_bytes(out)
    assert sorted(before) == [
        "log_30_0-sim0.csv",
        "log_30_0-sim0.meta.json",
        "log_30_0-sim1.csv",
        "log_30_0-sim1.meta.json",
        "notes.txt",
    ]

    refused(sim(model, init_log, "--out", str(out)), f"--out {out}", "holds 2 logs", "--force")
    assert folder_bytes(out) == before  # nothing overwritten, added or left behind

    done = sim(model, init_log, "--runs", "1", "--steps", "3", "--out", str(out), "--force")
    assert done.returncode == 0, done.stderr
    assert "replaced 2 earlier logs" in done.stderr
    after = folder_bytes(out)  # exactly the new run, and the user's other file
    assert sorted(after) == ["log_30_0-sim0.csv", "log_30_0-sim0.meta.json", "notes.txt"]
    assert after["notes.txt"] == b"mine" and after["log_30_0-sim0.csv"] != before["log_30_0-sim0.csv"]


def test_out_holding_only_sidecars_is_refused(model, init_log, tmp_path):
    out = tmp_path / "sim"
    out.mkdir()
    (out / "old.meta.json").write_text("{}")
    refused(sim(model, init_log, "--out", str(out)), f"--out {out}", "1 log sidecar")
    assert folder_bytes(out) == {"old.meta.json": b"{}"}


def test_force_never_deletes_the_initial_log(model, init_log, tmp_path):
    before = folder_bytes(init_log.parent)
    refused(sim(model, init_log, "--out", str(init_log.parent), "--force"), str(init_log), "another folder")
    assert folder_bytes(init_log.parent) == before


def test_force_needs_out(model, init_log):
    refused(sim(model, init_log, "--metrics-only", "--metrics", "-", "--force"), "--force", "--out")


# ---------------------------------------------------------------- 4. --controller @FILE

CONTROLLER_FILES = {
    "invalid JSON": ("{bad\n", "JSON"),
    "empty": ("", "JSON"),
    "not a spec": ('"lane-keeping"', "controller spec"),
    "unknown controller": ('{"name": "wall-follow"}', "unknown controller 'wall-follow'"),
    "non-finite number": ('{"name": "lane-keeping", "params": {"x": Infinity}}', "non-finite"),
}


@pytest.mark.parametrize("case", list(CONTROLLER_FILES))
def test_a_bad_controller_file_is_named(case, model, init_log, tmp_path):
    text, why = CONTROLLER_FILES[case]
    ctl = tmp_path / "ctl_bad.json"
    ctl.write_text(text)
    out = tmp_path / "sim"
    refused(sim(model, init_log, "--controller", f"@{ctl}", "--out", str(out)), f"--controller {ctl}: ", why)
    assert not out.exists()


def test_a_good_controller_file_runs(model, init_log, tmp_path):
    ctl = tmp_path / "ctl.json"
    ctl.write_text('{"name": "lane-keeping", "params": {"x": 10}}')
    done = sim(model, init_log, "--controller", f"@{ctl}", "--metrics-only", "--metrics", "-")
    assert done.returncode == 0, done.stderr
    assert json.loads(done.stdout)["controller"]["params"] == {"x": 10}
