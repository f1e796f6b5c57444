"""``envi diagnose`` end to end on twin logs with a known unmodelled effect: report, JSON, retraining."""

from __future__ import annotations

import json

from envi_py.cli import main
from envi_py.controllers import ControllerSpec
from envi_py.logs import load_logs
from envi_py.train import train
from envi_py.twin import TwinProfile, generate, write_logs


def test_diagnose_names_noise_and_retrains_with_a_gaussian_head(tmp_path, capsys):
    lane = ControllerSpec("lane-keeping", {"x": 30})
    write_logs(generate(lane, 15, 100, {"noise": 3.0}, seed=1, profile=TwinProfile()), tmp_path / "fit")
    write_logs(generate(lane, 24, 100, {"noise": 3.0}, seed=2, profile=TwinProfile()), tmp_path / "real")
    fit = load_logs(tmp_path / "fit")
    ckpt = train("bc", fit[:12], fit[12:], seed=0, epochs=80, lr=1e-3, history=4, head="deterministic")
    ckpt.save(tmp_path / "bc.pt")
    out = tmp_path / "diag"
    assert (
        main(
            [
                "diagnose",
                "--model",
                str(tmp_path / "bc.pt"),
                "--real",
                str(tmp_path / "real"),
                "--runs",
                "2",
                "--top",
                "1",
                "--out",
                str(out),
            ]
        )
        == 0
    )
    verdict = capsys.readouterr().out
    assert "Significant candidate effects, most important first: noise" in verdict
    d = json.loads((out / "diagnosis.json").read_text())
    assert d["findings"][0]["effect"] == "noise" and d["findings"][0]["significant"]
    after = d["shrink"]["after"][0]
    assert after["effect"] == "noise" and after["fix"] == {"head": "gaussian"}
    assert after["mean_w1"] < d["shrink"]["before"]["mean_w1"]
    assert len(d["runs"]) == 12 and set(d["confirm_logs"]).isdisjoint(d["choose_logs"])
    md = (out / "diagnosis.md").read_text()
    for part in ("metrics.png", "horizon.png", "residual_map.png", "shrink.png", "Logs with the largest"):
        assert part in md
        if part.endswith(".png"):
            assert (out / part).stat().st_size > 1000
