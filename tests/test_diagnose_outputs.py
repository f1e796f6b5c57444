"""``envi diagnose`` and its output folder: a new diagnosis replaces the earlier one as a whole (report,
figures, kept models, fitted layer) and leaves the user's own files alone; a failure while writing
keeps the earlier diagnosis; logs too few to measure a gap are refused before any stage runs."""

from __future__ import annotations

import contextlib
import copy
import io
import json
import os
from dataclasses import replace
from pathlib import Path

import pytest
import torch

from envi_py.cli import main
from envi_py.controllers import ControllerSpec
from envi_py.diagnose.layers import Fit
from envi_py.diagnose.run import Diagnosis, diagnose, own_level_text
from envi_py.effect_layers import Layer
from envi_py.logs import load_logs
from envi_py.model import Checkpoint
from envi_py.train import train
from envi_py.twin import generate, write_logs

LANE = ControllerSpec("lane-keeping", {"x": 30})
#: A fitted layer as :func:`~envi_py.diagnose.layers.fit_and_confirm` gives it.
LAYER = {
    "candidate": "noise",
    "fit": Fit(Layer("noise", 0.5), [0.4, 0.6], [], criterion="mean squared one-step error").to_json(),
    "confirm": {"before": 0.2, "after": 0.1, "floor": 0.05, "shrink": 0.5, "shrink_ci": [0.2, 0.7]}
    | {"within_1.5_floor": False},
}


@pytest.fixture(scope="module")
def lane(tmp_path_factory: pytest.TempPathFactory) -> tuple[Checkpoint, Path, Path, Diagnosis]:
    """A two-epoch model of the lane-keeping twin, four real logs and their diagnosis (no retraining)."""
    d = tmp_path_factory.mktemp("lane")
    write_logs(generate(LANE, 4, 60, seed=1), d / "fit")
    write_logs(generate(LANE, 4, 60, seed=2), d / "real")
    ckpt = train("bc", load_logs(d / "fit"), [], epochs=2, hidden=(8, 8), history=5, seed=0)
    return ckpt, ckpt.save(d / "bc.pt"), d / "real", diagnose(ckpt, load_logs(d / "real"), retrain=False, runs=2)


def _cli(argv: list[str]) -> tuple[int, str, str]:
    out, err = io.StringIO(), io.StringIO()
    with contextlib.redirect_stdout(out), contextlib.redirect_stderr(err):
        code = main(argv)
    return code, out.getvalue(), err.getvalue()


def _diagnose_into(monkeypatch, lane, out: Path, d: Diagnosis, kept: dict) -> tuple[int, str, str]:
    """``envi diagnose`` into ``out`` with the stages replaced by ``d`` and the ``kept`` models."""
    _, model, real, _ = lane

    def stages(*args, keep_models, **kwargs):
        keep_models.update(kept)
        return d

    monkeypatch.setattr("envi_py.diagnose.run.diagnose", stages)
    return _cli(["diagnose", "--model", str(model), "--real", str(real), "--quiet", "--out", str(out)])


def _listing(folder: Path) -> dict[str, bytes]:
    return {str(p.relative_to(folder)): p.read_bytes() for p in sorted(folder.rglob("*")) if p.is_file()}


def test_a_new_diagnosis_replaces_the_earlier_one_as_a_whole(lane, tmp_path, monkeypatch):
    ckpt, _, _, d = lane
    out = tmp_path / "diag"
    code, printed, _ = _diagnose_into(monkeypatch, lane, out, replace(d, layer=LAYER), {"refit": ckpt, "lag": ckpt})
    assert code == 0
    written = ["bc+refit.pt", "bc+lag.pt", "bc.pt.layers.json"]
    assert [r["name"] for r in json.loads((out / "diagnosis.json").read_text())["attached_files"]] == written
    for name in written:
        assert (out / name).stat().st_size > 0 and f"{out / name}" in printed
    assert "residual_correlation.png" in os.listdir(out / "diagnosis_figures")
    (out / "notes.txt").write_text("the user's")
    (out / "mine+lag.pt").write_bytes(b"the user's model")  # named like a kept model, but not envi's

    code, printed, _ = _diagnose_into(monkeypatch, lane, out, replace(d, correlation=[]), {})
    assert code == 0 and "model with" not in printed and "fitted layer" not in printed
    assert sorted(_listing(out)) == [
        "diagnosis.html",
        "diagnosis.json",
        "diagnosis.md",
        "diagnosis_figures/horizon.png",
        "diagnosis_figures/metrics.png",
        "diagnosis_figures/residual_map.png",
        "mine+lag.pt",
        "notes.txt",
    ]


def test_the_report_sets_the_layered_gap_against_the_model_alone_on_its_held_out_logs(lane, tmp_path, monkeypatch):
    _, _, _, d = lane
    own = {"gap": 0.12, "floor": 0.06, "ratio": 2.0, "logs": 5, "within_1.5_own": True}
    assert _diagnose_into(monkeypatch, lane, tmp_path / "a", replace(d, layer={**LAYER, "own": own}), {})[0] == 0
    report = (tmp_path / "a" / "diagnosis.md").read_text()
    assert "| model alone on its held-out logs (x their floor) | within 1.5x of that (or the floor) |" in report
    assert "| 2.00x (5 logs) | yes |" in report
    assert own_level_text({**LAYER, "own": own}) == (
        " On 5 of its own held-out logs the model alone is at 2.00x their floor (a layer adds the effect, not "
        "what the model misses on its own world); the layered model is at 2.00x, within 1.5x that level (or the "
        "floor, where it is higher)."
    )
    assert _diagnose_into(monkeypatch, lane, tmp_path / "b", replace(d, layer={**LAYER, "own": None}), {})[0] == 0
    assert "| not measured | - |" in (tmp_path / "b" / "diagnosis.md").read_text()
    assert "not measured: its held-out logs of its training world are fewer than the confirmation logs" in (
        own_level_text({**LAYER, "own": None})
    )
    settled = {"gap": 0.0, "floor": 0.0, "ratio": None, "logs": 6, "within_1.5_own": None}
    assert _diagnose_into(monkeypatch, lane, tmp_path / "c", replace(d, layer={**LAYER, "own": settled}), {})[0] == 0
    assert "| floor 0 (6 logs) | - |" in (tmp_path / "c" / "diagnosis.md").read_text()
    assert "the runs do not vary (floor 0)" in own_level_text({**LAYER, "own": settled})


def test_a_diagnosis_that_cannot_be_written_leaves_the_earlier_one(lane, tmp_path, monkeypatch):
    ckpt, _, _, d = lane
    out = tmp_path / "diag"
    assert _diagnose_into(monkeypatch, lane, out, replace(d, layer=LAYER), {"lag": ckpt})[0] == 0
    before = _listing(out)
    broken = copy.deepcopy(ckpt)
    with torch.no_grad():
        next(broken.model.parameters()).fill_(float("nan"))  # refused when saved, after the figures are drawn
    code, _, err = _diagnose_into(monkeypatch, lane, out, replace(d, correlation=[]), {"refit": broken})
    assert code == 2 and err.startswith(f"envi diagnose: error: {out / 'bc+refit.pt'}: damaged model"), err
    assert _listing(out) == before and not [p for p in os.listdir(out) if p.startswith(".")]


def test_too_few_real_runs_are_refused_before_any_stage(lane, tmp_path):
    _, model, _, _ = lane
    write_logs(generate(LANE, 2, 60, seed=3), tmp_path / "two")  # one to choose with, one to confirm
    out = tmp_path / "diag"
    code, _, err = _cli(["diagnose", "--model", str(model), "--real", str(tmp_path / "two"), "--out", str(out)])
    lines = err.splitlines()  # no '[diagnose] 1/6 ...' progress: the error comes first and alone
    assert code == 2 and len(lines) == 1, err
    assert lines[0] == (
        "envi diagnose: error: the fair floor needs at least 2 real runs of each controller version; "
        "the logs that choose the effect (half of the real logs) have 1 of x=30"
    )
    assert not out.exists()


def test_too_few_confirmation_logs_are_refused_before_any_stage_when_retraining(lane):
    ckpt = lane[0]
    three = generate(LANE, 3, 60, seed=4)  # two choose the effect, one would confirm it
    said: list[str] = []
    with pytest.raises(ValueError, match="the confirmation logs \\(the other half\\) have 1 of x=30"):
        diagnose(ckpt, three, retrain=True, runs=2, progress=said.append)
    assert said == []  # refused before the first stage, not after the retraining


@pytest.mark.parametrize(
    "fit, ci",
    [(Layer("delay", 0.0), [0.1, 0.5]), (Layer("noise", 0.5), [-0.65, 0.23])],
    ids=["identity", "no-shrink-shown"],
)
def test_a_layer_not_shown_to_help_is_neither_saved_nor_suggested(lane, tmp_path, monkeypatch, fit, ci):
    """A delay of 0 ticks, or a layer whose shrink interval reaches below 0 on the confirmation logs,
    is reported but not offered as a fix (it was saved and 'simulate it' suggested)."""
    _, _, _, d = lane
    layer = {**LAYER, "fit": Fit(fit, [0.0, 1.0], [], criterion="x").to_json(), "confirm": {**LAYER["confirm"]}}
    layer["confirm"]["shrink_ci"] = ci
    out = tmp_path / "diag"
    code, printed, _ = _diagnose_into(monkeypatch, lane, out, replace(d, layer=layer), {})
    assert code == 0 and "fitted layer" not in printed
    assert not list(out.glob("*.layers.json")) and "Not saved" in (out / "diagnosis.md").read_text()


def test_only_a_retrained_fix_shown_to_shrink_the_gap_is_kept(lane, monkeypatch):
    """A fix whose shrink interval reaches below 0 (the real-log case: -11 %, -65 % to +23 %) is reported
    with its figures but not kept as a model to offer; one whose interval lies above 0 is."""
    from envi_py.diagnose import shrink as shrink_module
    from envi_py.diagnose.effects import Finding

    ckpt, _, _, _ = lane
    cis = {"memory_delay": [-0.65, 0.23], "noise": [0.1, 0.4]}
    monkeypatch.setattr(shrink_module, "retrain_with", lambda c, f, *a: f.effect)
    monkeypatch.setattr(shrink_module, "simulate_groups", lambda m, *a: m)
    monkeypatch.setattr(shrink_module, "gap_summary", lambda g, *a: {"mean_w1": 0.1})
    monkeypatch.setattr(shrink_module, "shrink_interval", lambda base, groups, *a: cis[groups])
    monkeypatch.setattr(shrink_module, "changes_model", lambda c, f: True)
    findings = [Finding(e, 1.0, 0.01, 0.2, "", {"history": 20}) for e in cis]
    kept: dict = {}
    res = shrink_module.shrink(ckpt, findings, [], [], [], keep=kept)
    assert [a["shrink_ci"] for a in res["after"]] == list(cis.values())  # both reported
    assert list(kept) == ["noise"]
