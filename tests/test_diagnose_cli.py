"""``envi diagnose`` end to end on twin logs with a known unmodelled effect: report, JSON, the staged
diagnosis of a deterministic model against a world whose runs vary."""

from __future__ import annotations

import json

from envi_py.cli import main
from envi_py.controllers import ControllerSpec
from envi_py.logs import load_logs
from envi_py.train import train
from envi_py.twin import TwinProfile, generate, write_logs


def test_deterministic_model_of_a_noisy_world_is_refitted_before_the_rest_is_diagnosed(tmp_path, capsys):
    lane = ControllerSpec("lane-keeping", {"x": 30})
    write_logs(generate(lane, 15, 100, {"noise": 3.0}, seed=1, profile=TwinProfile()), tmp_path / "fit")
    write_logs(generate(lane, 24, 100, {"noise": 3.0}, seed=2, profile=TwinProfile()), tmp_path / "real")
    fit = load_logs(tmp_path / "fit")
    # unrounded: a deterministic model whose output is rounded to the sensor's step (the training default
    # since stop 21) spreads its runs as widely as the real ones here (median sd ratio 1.30, not 0.41),
    # so stage 1 stays silent and the noise is left to the candidates
    ckpt = train("bc", fit[:12], fit[12:], seed=0, epochs=40, lr=1e-3, history=4, head="deterministic", round_to=None)
    ckpt.save(tmp_path / "bc.pt")
    out = tmp_path / "diag"
    args = ["diagnose", "--model", str(tmp_path / "bc.pt"), "--real", str(tmp_path / "real")]
    assert main(args + ["--runs", "2", "--no-retrain", "--out", str(out)]) == 0
    captured = capsys.readouterr()
    # stage 1 leads: the model class, then the refit
    assert captured.out.startswith("First, the model class: the model is deterministic, while the real runs vary")
    assert "Refitted with a Gaussian head" in captured.out
    assert (out / "bc+refit.pt").stat().st_size > 0 and "model with refit: " in captured.out  # kept, not lost
    assert "3/6 the model is deterministic and the real runs vary: refitting with a Gaussian head" in captured.err
    d = json.loads((out / "diagnosis.json").read_text())
    stage = d["stage"]
    assert stage["too_certain"] and stage["refit"] and stage["head"] == "deterministic"
    assert stage["scatter"][0]["random"] and stage["median_ratio"] < 1.0
    assert stage["mean_w1_after"] < stage["mean_w1_before"]
    # the rest is of the refit: the noise candidate has no fix left to offer (the head is Gaussian)
    noise = next(f for f in d["findings"] if f["effect"] == "noise")
    assert noise["fix"] == {}
    assert len(d["runs"]) == 12 and set(d["confirm_logs"]).isdisjoint(d["choose_logs"])
    assert d["data_quality"] == []
    md = (out / "diagnosis.md").read_text()
    figures = ("metrics.png", "horizon.png", "residual_map.png", "residual_correlation.png")
    assert "| controller | real runs | settled, real | settled, simulated | periods (rows) |" in md
    assert d["cycles"]["runs"] == 12 and len(d["cycles"]["versions"]) == 1
    for part in ("## Data quality", "## Model class", *(f"diagnosis_figures/{f}" for f in figures)):
        assert part in md
        if part.endswith(".png"):
            assert (out / part).stat().st_size > 1000
    html = (out / "diagnosis.html").read_text()
    assert html.count("<img") == md.count("![") and "Provenance" in html and "bc.pt" in html
    assert md.index("| controller |") < md.index("First, the model class")  # the verdict table comes first
    assert d["residual_correlation"] and all(len(c["auto"]) == 26 for c in d["residual_correlation"])
