"""The report document and its one writer: order, escaping, strict JSON, figures, training curves."""

from __future__ import annotations

import csv
import importlib.util
import json
import math

import numpy as np
import pytest

from envi_py.cli import main
from envi_py.controllers import ControllerSpec
from envi_py.report.document import Figure, Provenance, Report, Section, Table, Text
from envi_py.report.files import write_files
from envi_py.report.html import to_html
from envi_py.report.markdown import to_markdown
from envi_py.report.training import curve_rows, write_training_outputs
from envi_py.train import train
from envi_py.twin import generate, write_logs

PNG = bytes.fromhex(
    "89504e470d0a1a0a0000000d4948445200000001000000010806000000"
    "1f15c4890000000d49444154789c6360000002000100e221bc330000000049454e44ae426082"
)


def _report(figures: list[Figure] | None = None) -> Report:
    return Report(
        "T <b>",
        Table(["version", "verdict"], [["x=1", "**PASS**"], ["<script>alert(1)</script>", "FAIL"]]),
        Provenance("0.1.0", "envi verify --real a", "2026-01-01T00:00:00+00:00", "lane-keeping", extra={"seed": 3}),
        [Text("how to read `acc`")],
        [Section("Evidence", [Table(["a", "b"], [["1", "2"]], "numbers", frozenset({1})), *(figures or [])])],
        {"groups": [{"acc": float("nan"), "w1": [1.0, float("inf")], "n": np.int64(3), "m": np.array([0.5, np.nan])}]},
    )


def test_markdown_and_html_put_the_verdict_first_and_provenance_last() -> None:
    rep = _report()
    md = to_markdown(rep)
    assert md.startswith("# T <b>\n\n| version | verdict |")
    assert md.index("## Evidence") < md.index("## Provenance") and md.rstrip().endswith("- seed: 3")
    page = to_html(rep)
    assert page.index('<table class="verdict">') < page.index("<h2>Evidence</h2>") < page.index('id="provenance"')
    assert "<script>" not in page and "&lt;script&gt;" in page  # cells are escaped, the page has no script
    assert '<span class="pass"><strong>PASS</strong></span>' in page and "<code>acc</code>" in page


def test_writer_gives_strict_json_with_provenance_and_embedded_figures(tmp_path) -> None:
    files = write_files(_report([Figure("traces_x=1", PNG, "a figure")]), tmp_path, "report")
    js = json.loads(files.json.read_text())
    assert js["groups"][0]["acc"] is None and js["groups"][0]["w1"] == [1.0, None]
    assert js["groups"][0]["n"] == 3 and js["groups"][0]["m"] == [0.5, None]
    assert js["provenance"]["command"] == "envi verify --real a" and js["provenance"]["seed"] == 3
    assert files.figures == [tmp_path / "report_figures" / "traces_x=1.png"] and files.figures[0].read_bytes() == PNG
    assert "](report_figures/traces_x=1.png)" in files.markdown.read_text()
    assert "data:image/png;base64,iVBOR" in files.html.read_text()
    with pytest.raises(ValueError, match="two figures"):
        write_files(_report([Figure("f", PNG, "a"), Figure("f", PNG, "b")]), tmp_path, "dup")


def test_a_table_row_of_the_wrong_width_is_refused() -> None:
    with pytest.raises(ValueError, match="2 cells, not 3"):
        Table(["a", "b", "c"], [["1", "2"]])


def test_provenance_hashes_the_model_file(tmp_path) -> None:
    model = tmp_path / "m.pt"
    model.write_bytes(b"abc")
    p = Provenance.collect(model, "car")
    assert p.model_sha256 == "ba7816bf8f01cfea414140de5dae2223b00361a396177a9cb410ff61f20015ad"
    assert p.system == "car" and p.date.endswith("+00:00") and p.envi
    assert Provenance.collect(tmp_path / "missing.pt").model_sha256 is None


def test_curve_rows_merge_validation_selection_and_losses() -> None:
    sel = {"curve": [(2, 0.5), (4, 0.2)], "best_epoch": 4, "diverged_epochs": [2]}
    rows = curve_rows(sel, [{"epoch": "1", "disc_loss": "0.7", "val_error": "nan"}, {"epoch": "2", "disc_loss": ""}])
    assert [r["epoch"] for r in rows] == [1.0, 2.0, 4.0]
    assert math.isnan(rows[0]["val_error"]) and rows[0]["disc_loss"] == 0.7 and math.isnan(rows[1]["disc_loss"])
    assert rows[1]["val_error"] == 0.5 and rows[1]["diverged"] == 1.0 and rows[2]["selected"] == 1.0
    assert curve_rows({}) == []


@pytest.fixture(scope="module")
def twin_logs(tmp_path_factory):
    d = tmp_path_factory.mktemp("twin")
    return write_logs(generate(ControllerSpec("lane-keeping", {"x": 30}), 4, 40, seed=1), d)


def test_training_curves_are_written_beside_the_checkpoint(twin_logs, tmp_path) -> None:
    from envi_py.logs import load_logs

    logs = load_logs(twin_logs)
    ckpt = train("bc", logs[:3], logs[3:], epochs=4, eval_every=2, hidden=(8,), history=5, seed=0)
    path = ckpt.save(tmp_path / "m.pt")
    out = write_training_outputs(ckpt, path)
    assert out["curves"] == tmp_path / "m.curves.csv" and out["html"] == tmp_path / "m.training.html"
    with out["curves"].open() as f:
        rows = list(csv.DictReader(f))
    assert [r["epoch"] for r in rows] == ["2", "4"]
    assert [r["selected"] for r in rows].count("1") == 1
    assert rows[[r["selected"] for r in rows].index("1")]["epoch"] == str(ckpt.record.selection["best_epoch"])
    # the report says why training ended (here: the 4-epoch cap), not only which epoch was kept
    assert "Training stopped: reached the epoch cap (4)." in (tmp_path / "m.training.md").read_text()
    page = out["html"].read_text()
    assert '<table class="verdict">' in page and "data:image/png;base64," in page and "model sha256" in page


def test_an_ensembles_training_report_shows_every_member(twin_logs, tmp_path) -> None:
    """Each member is selected on its own curve: the verdict has a row per member (its seed and kept
    epoch) and the CSV a validation-error column per further member, not member 0's alone."""
    from envi_py.logs import load_logs

    logs = load_logs(twin_logs)
    ckpt = train("bc", logs[:3], logs[3:], epochs=4, eval_every=2, hidden=(8,), history=5, seed=5, members=2)
    path = ckpt.save(tmp_path / "e.pt")
    out = write_training_outputs(ckpt, path)
    with out["curves"].open() as f:
        rows = list(csv.DictReader(f))
    second = ckpt.record.selection["members"][1]
    assert [float(r["val_error_member1"]) for r in rows] == pytest.approx([e for _, e in second["curve"]], rel=1e-5)
    assert [float(r["val_error"]) for r in rows] != [float(r["val_error_member1"]) for r in rows]
    table = [line.strip("|").split("|") for line in (tmp_path / "e.training.md").read_text().splitlines()]
    verdict = {cells[0].strip(): [c.strip() for c in cells[1:]] for cells in table if "(seed " in cells[0]}
    assert list(verdict) == ["0 (seed 5)", "1 (seed 6)"]
    assert verdict["1 (seed 6)"][4] == str(second["best_epoch"]) and verdict["1 (seed 6)"][0] == "bc"


def test_train_tensorboard_without_the_package_names_the_extra(twin_logs, tmp_path, monkeypatch, capsys) -> None:
    real_find = importlib.util.find_spec
    monkeypatch.setattr(importlib.util, "find_spec", lambda n, *a: None if n == "tensorboard" else real_find(n, *a))
    argv = ["train", "--logs", *map(str, twin_logs), "--epochs", "1", "-o", str(tmp_path / "m.pt")]
    assert main([*argv, "--tensorboard", str(tmp_path / "tb")]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert err == ["envi train: error: --tensorboard needs the tensorboard package: pip install 'envi[tensorboard]'"]
    assert not (tmp_path / "m.pt").exists()  # refused before training
