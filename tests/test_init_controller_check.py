"""envi init checks that the controller it drafts takes the file names' fields: a draft whose pattern
field (v1) the controller does not know used to fail only when a training had already run."""

from __future__ import annotations

from envi_py.cli import main
from envi_py.controllers import ControllerSpec
from envi_py.logs import sidecar_path
from envi_py.twin import generate, write_logs


def _bare_logs(folder):
    """Lane logs named log_<x>_<run>.csv without sidecars, as the real ones."""
    for x in (10, 30):
        for p in write_logs(generate(ControllerSpec("lane-keeping", {"x": x}), 2, 40, seed=x), folder / f"t{x}"):
            path = p
            sidecar_path(path).unlink()
            path.rename(folder / f"log_{x}_{path.stem[-1]}.csv")


def test_a_draft_whose_controller_rejects_the_fields_says_so(tmp_path, capsys):
    _bare_logs(tmp_path)
    assert main(["init", "--logs", str(tmp_path), "-o", str(tmp_path / "s.toml")]) == 0
    err = capsys.readouterr().err
    assert "envi init: note: " in err and "unknown parameter(s) v1; known: x" in err
    named = ["--pattern", "log_{x}_{run}.csv", "-o", str(tmp_path / "ok.toml")]
    assert main(["init", "--logs", str(tmp_path), *named]) == 0
    assert "note" not in capsys.readouterr().err
