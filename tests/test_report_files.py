"""The report writer replaces an earlier report of the same stem as a whole: no figure of the earlier
report stays beside the new one, a failure while writing leaves the earlier report as it was, and of
the files a report brings along only those the earlier report recorded are ever removed."""

from __future__ import annotations

import fcntl
import hashlib
import json
import os
import stat
from pathlib import Path

import pytest

from envi_py.report import files
from envi_py.report.document import Figure, Provenance, Report, Section, Table
from envi_py.report.files import write_files

PNG = bytes.fromhex(
    "89504e470d0a1a0a0000000d4948445200000001000000010806000000"
    "1f15c4890000000d49444154789c6360000002000100e221bc330000000049454e44ae426082"
)


def _report(*figures: str, run: int = 1) -> Report:
    return Report(
        "T",
        Table(["version", "verdict"], [["x=1", "PASS"]]),
        Provenance("0.1.0", "envi verify --real a", "2026-01-01T00:00:00+00:00", None),
        [],
        [Section("Evidence", [Figure(n, PNG, f"figure {n}") for n in figures])],
        {"run": run},
    )


def _folder(path: Path) -> dict[str, bytes]:
    """Every file under ``path`` (hidden ones included) with its content."""
    return {str(p.relative_to(path)): p.read_bytes() for p in sorted(path.rglob("*")) if p.is_file()}


def _attach(name: str, content: bytes = b"data"):
    def write(folder: Path) -> Path:
        (folder / name).write_bytes(content)
        return folder / name

    return write


def test_figures_of_the_earlier_report_are_gone(tmp_path: Path) -> None:
    write_files(_report("a", "b"), tmp_path)
    new = write_files(_report("c", run=2), tmp_path)
    assert sorted(os.listdir(tmp_path / "report_figures")) == ["c.png"]
    assert new.figures == [tmp_path / "report_figures" / "c.png"]
    assert "report_figures/a.png" not in new.markdown.read_text()
    umask = os.umask(0)
    os.umask(umask)
    assert stat.S_IMODE((tmp_path / "report_figures").stat().st_mode) == 0o777 & ~umask  # not a private temp folder
    write_files(_report(run=3), tmp_path)  # no figures at all: no folder of the earlier ones
    assert sorted(os.listdir(tmp_path)) == ["report.html", "report.json", "report.md"]


def test_a_failure_while_writing_leaves_the_earlier_report_as_it_was(tmp_path: Path, monkeypatch) -> None:
    write_files(_report("a", "b"), tmp_path)
    before = _folder(tmp_path)

    def broken(report: Report) -> str:
        raise RuntimeError("the page does not render")

    monkeypatch.setattr(files, "to_html", broken)
    with pytest.raises(RuntimeError, match="does not render"):
        write_files(_report("c", run=2), tmp_path)
    assert _folder(tmp_path) == before  # neither c.png nor a new Markdown beside the earlier page


def test_two_figures_under_one_file_name_are_refused(tmp_path: Path) -> None:
    with pytest.raises(ValueError, match="two figures are saved as 'a_b.png'"):
        write_files(_report("a b", "a_b"), tmp_path)
    assert _folder(tmp_path) == {}


def test_files_a_report_brings_along_replace_the_earlier_ones_and_nothing_else(tmp_path: Path) -> None:
    out = tmp_path / "out"
    out.mkdir()
    (tmp_path / "outside.txt").write_text("not envi's")
    (out / "notes.txt").write_text("the user's")
    (out / "mine+lag.pt").write_bytes(b"the user's model")  # named like a kept model, never recorded
    first = write_files(_report("a"), out, "diagnosis", [_attach("m+lag.pt"), _attach("m+noise.pt")])
    assert first.attachments == [out / "m+lag.pt", out / "m+noise.pt"]
    js = json.loads(first.json.read_text())
    assert [r["name"] for r in js[files.ATTACHED]] == ["m+lag.pt", "m+noise.pt"]
    # an edited record naming files outside the folder, or the report's own, removes none of them
    for name in ("../outside.txt", str(tmp_path / "outside.txt"), "diagnosis.md", ".."):
        js[files.ATTACHED].append({"name": name, "sha256": hashlib.sha256(b"not envi's").hexdigest()})
    first.json.write_text(json.dumps(js))

    second = write_files(_report("a", run=2), out, "diagnosis", [_attach("m+lag.pt", b"new")])
    assert second.attachments == [out / "m+lag.pt"] and (out / "m+lag.pt").read_bytes() == b"new"
    assert sorted(os.listdir(out)) == [
        "diagnosis.html",
        "diagnosis.json",
        "diagnosis.md",
        "diagnosis_figures",
        "m+lag.pt",
        "mine+lag.pt",
        "notes.txt",
    ]
    assert (tmp_path / "outside.txt").exists()


def test_an_attachment_that_fails_leaves_the_earlier_report_and_its_files(tmp_path: Path) -> None:
    write_files(_report("a"), tmp_path, "diagnosis", [_attach("m+lag.pt")])
    before = _folder(tmp_path)

    def full_disk(folder: Path) -> Path:
        raise OSError(28, "No space left on device")

    with pytest.raises(OSError, match="No space"):
        write_files(_report("b", run=2), tmp_path, "diagnosis", [_attach("m+noise.pt"), full_disk])
    assert _folder(tmp_path) == before and not [p for p in os.listdir(tmp_path) if p.startswith(".")]


def test_a_recorded_file_goes_only_while_it_is_what_the_report_wrote(tmp_path: Path) -> None:
    """The record is a list of names with their sha256: a file the user edited since, a user's file
    named in a hand-edited record (or in an older writer's list of bare names), a symlink, and the
    command's own input all stay; only an untouched attachment the new report does not write goes."""
    out = tmp_path / "out"
    first = write_files(_report("a"), out, "diagnosis", [_attach(n) for n in ("gone.pt", "edited.pt", "input.pt")])
    (out / "edited.pt").write_bytes(b"changed by the user")
    (out / "user.csv").write_text("time,color,angle\n")
    (tmp_path / "target.txt").write_text("kept")
    js = json.loads(first.json.read_text())
    js[files.ATTACHED] += [
        {"name": "user.csv", "sha256": "0" * 64},
        "user.csv",
        {"name": "link.pt", "sha256": hashlib.sha256(b"kept").hexdigest()},
    ]
    first.json.write_text(json.dumps(js))
    (out / "link.pt").symlink_to(tmp_path / "target.txt")
    write_files(_report("a", run=2), out, "diagnosis", protect=[out / "input.pt"])
    assert sorted(p.name for p in out.iterdir() if p.suffix in (".pt", ".csv")) == [
        "edited.pt",
        "input.pt",
        "link.pt",
        "user.csv",
    ]
    assert (tmp_path / "target.txt").read_text() == "kept"


def test_a_failure_while_moving_in_puts_the_earlier_report_back(tmp_path: Path, monkeypatch) -> None:
    """A rename that fails halfway (or Ctrl-C there) undoes the ones done: no mix of two reports, and
    the earlier figures folder is back."""
    write_files(_report("a"), tmp_path, "report")
    before = _folder(tmp_path)
    real_replace, calls = os.replace, []

    def flaky(src, dst):
        calls.append(dst)
        if len(calls) == 4:  # after the figures folder went out and the new one came in
            raise KeyboardInterrupt
        real_replace(src, dst)

    monkeypatch.setattr(files.os, "replace", flaky)
    with pytest.raises(KeyboardInterrupt):
        write_files(_report("b", run=2), tmp_path, "report")
    monkeypatch.undo()
    assert _folder(tmp_path) == before and not [p for p in os.listdir(tmp_path) if p.startswith(".")]


def test_two_writers_of_one_folder_take_turns(tmp_path: Path) -> None:
    """The second writer waits for the first one's lock on the folder; the folder then holds one whole
    report (the second), never the md of one and the figures of the other."""
    import threading

    write_files(_report("a"), tmp_path, "report")
    fd = os.open(tmp_path, os.O_RDONLY)
    fcntl.flock(fd, fcntl.LOCK_EX)  # a writer holding the folder
    done = threading.Event()
    t = threading.Thread(target=lambda: (write_files(_report("b", run=2), tmp_path, "report"), done.set()))
    t.start()
    assert not done.wait(0.5)  # waits while the folder is held
    os.close(fd)
    t.join(30)
    assert done.is_set() and '"run": 2' in (tmp_path / "report.json").read_text()


def test_a_read_only_folder_is_named_not_the_staging_one(tmp_path: Path, monkeypatch) -> None:
    """The staging folder cannot be made (a read-only --out; as root, made to fail): the message names
    --out, not the hidden '.report.staging-...' that never existed."""

    def refused(**kwargs):
        raise PermissionError(13, "Permission denied", str(tmp_path / ".report.staging-x"))

    monkeypatch.setattr(files.tempfile, "mkdtemp", refused)
    with pytest.raises(OSError, match=f"^{tmp_path}: cannot write the report \\(Permission denied\\)$"):
        write_files(_report("a"), tmp_path, "report")


def test_a_writer_killed_midway_leaves_nothing_the_next_one_keeps(tmp_path: Path) -> None:
    """A staging folder of a writer killed with SIGKILL (a whole model may sit in it) is removed by the
    next writer of that report, under the folder's lock."""
    left = tmp_path / ".report.staging-dead"
    (left / "new").mkdir(parents=True)
    (left / "new" / "m+lag.pt").write_bytes(b"x" * 1000)
    write_files(_report("a"), tmp_path, "report")
    assert not [p for p in os.listdir(tmp_path) if p.startswith(".")]


def test_an_undo_that_fails_keeps_the_earlier_files_and_says_where(tmp_path: Path, monkeypatch) -> None:
    write_files(_report("a"), tmp_path, "report")
    before = (tmp_path / "report.md").read_bytes()
    real_replace = os.replace

    def failing(src, dst):
        if Path(dst) == tmp_path / "report.md":  # moving the new one in fails, and putting the earlier one back
            raise OSError(5, "Input/output error")
        real_replace(src, dst)

    monkeypatch.setattr(files.os, "replace", failing)
    with pytest.raises(files.ReportNotRestored, match="its files are in") as err:
        write_files(_report("b", run=2), tmp_path, "report")
    monkeypatch.undo()
    kept = Path(str(err.value).rsplit("its files are in ", 1)[1])
    assert kept.is_dir() and (kept / "report.md").read_bytes() == before
