"""The README's real-log workflow with a model of several versions: logs named by a file-name pattern
(no sidecar), a BC model of x = 10, 30, 50, diagnosed against logs of all five x. The training and
validation logs are re-read from the checkpoint with the version it recorded for each, the pauses of
the real logs are flagged first, and every version is scored."""

from __future__ import annotations

import json
import shutil

from envi_py.cli import main

PATTERN = "log_{x}_{run}.csv"
#: Logs of x = 10 whose time stamps pause for 9-13 s inside a 4 s log.
PAUSED = ["log_10_1.csv", "log_10_5.csv", "log_10_13.csv", "log_10_17.csv"]


def _copy(names, src, dst):
    dst.mkdir(parents=True, exist_ok=True)
    for name in names:
        shutil.copy(src / name, dst / name)
    return dst


def test_multi_version_model_is_diagnosed_against_all_five_versions(real_dir, tmp_path, capsys):
    train = _copy([f"log_{x}_{i}.csv" for x in (10, 30, 50) for i in (2, 3, 6)], real_dir, tmp_path / "train")
    val = _copy([f"log_{x}_{i}.csv" for x in (10, 30, 50) for i in (7, 8)], real_dir, tmp_path / "val")
    others = [f"log_{x}_{i}.csv" for x in (20, 30, 40, 50) for i in (41, 42, 43, 45)]
    real = _copy(PAUSED + others, real_dir, tmp_path / "real")
    model = tmp_path / "bc.pt"
    assert (
        main(
            ["train", "--logs", str(train), "--val-logs", str(val), "--pattern", PATTERN, "--algorithm", "bc"]
            + ["--epochs", "3", "--eval-every", "3", "--history", "4", "--quiet", "-o", str(model)]
        )
        == 0
    )
    capsys.readouterr()  # the training's own lines
    out = tmp_path / "diag"
    args = ["diagnose", "--model", str(model), "--real", str(real), "--pattern", PATTERN]
    assert main(args + ["--runs", "2", "--no-retrain", "--out", str(out)]) == 0
    captured = capsys.readouterr()
    steps = [line.split()[1] for line in captured.err.splitlines() if line.startswith("[diagnose] ")]
    assert steps == ["1/6", "2/6", "3/6", "4/6", "5/6"], captured.err
    d = json.loads((out / "diagnosis.json").read_text())
    assert [g["controller"] for g in d["gaps"]] == [f"x={x}" for x in (10, 20, 30, 40, 50)]
    # the pauses are found first, with file, time into the log and length
    pauses = [q for q in d["data_quality"] if q["kind"] == "pause" and q["logs"] == "diagnosed"]
    assert len(pauses) == 1 and set(pauses[0]["files"]) == set(PAUSED)
    assert all(w["pause_s"] > 9.0 for w in pauses[0]["where"])
    verdict = captured.out
    assert verdict.startswith("Data quality first: In the diagnosed logs: 4 of 20 logs pause inside the log")
    md = (out / "diagnosis.md").read_text()
    assert "| diagnosed | log_10_1.csv | " in md  # the pause table: file, time into the log, row, length
    # the misfit is compared with the model's own held-out (validation) logs, re-read with their versions
    assert d["held_out"]["n_held_out"] == 6
    # one number per concept: the coverage of the verdict is the coverage line's
    share = d["coverage"]["outside_share"]
    text = f"{share:.1%}" if share < 0.1 else f"{share:.0%}"
    assert f"{text} of simulated windows lie outside" in verdict and f"Coverage: {text} of" in md
    # and of the diagnosed logs' own windows (x = 20 and 40 were never trained on), said in both places
    own = d["coverage"]["diagnosed_outside_share"]
    assert 0.0 <= own <= 1.0
    own_text = f"{own:.1%}" if own < 0.1 else f"{own:.0%}"
    assert f"and {own_text} of the diagnosed logs' own windows" in verdict
    assert f"and {own_text} of the diagnosed logs' own windows are farther" in md
