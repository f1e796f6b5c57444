"""envi_py.atomic: the one way envi writes a file a reader must never see half of."""

from __future__ import annotations

import os

import pytest

from envi_py.atomic import atomic_write, atomic_write_text


def test_the_file_appears_whole_with_the_umask_mode(tmp_path):
    old = os.umask(0o027)
    try:
        path = atomic_write_text(tmp_path / "sub" / "a.json", "{}\n")
    finally:
        os.umask(old)
    assert path.read_text() == "{}\n" and path.stat().st_mode & 0o777 == 0o640
    assert sorted(p.name for p in path.parent.iterdir()) == ["a.json"]


@pytest.mark.parametrize("error", [OSError("disk full"), KeyboardInterrupt()])
def test_a_failed_write_leaves_the_old_file_and_no_temporary_one(tmp_path, error):
    path = atomic_write_text(tmp_path / "a.csv", "old\n")

    def half(fh):
        fh.write(b"ne")
        raise error

    with pytest.raises(type(error)):
        atomic_write(path, half)
    assert path.read_text() == "old\n" and [p.name for p in tmp_path.iterdir()] == ["a.csv"]


def test_a_folder_in_the_way_is_named_not_the_temporary_file(tmp_path) -> None:
    (tmp_path / "a.json").mkdir()
    with pytest.raises(OSError) as exc:
        atomic_write_text(tmp_path / "a.json", "{}\n")
    assert exc.value.filename == str(tmp_path / "a.json") and ".tmp" not in str(exc.value)
    assert [p.name for p in tmp_path.iterdir()] == ["a.json"]  # no temporary file left behind


def test_a_fifo_is_written_through_and_a_link_keeps_pointing(tmp_path) -> None:
    """A rename onto a FIFO or device replaced the node itself (``envi-export -o /dev/null`` as root
    would have replaced /dev/null with a file); through a symbolic link the link itself was replaced."""
    import subprocess

    fifo = tmp_path / "out.fifo"
    os.mkfifo(fifo)
    reader = subprocess.Popen(["cat", str(fifo)], stdout=subprocess.PIPE)
    atomic_write_text(fifo, "through\n")
    assert reader.communicate(timeout=60)[0] == b"through\n"
    assert fifo.is_fifo() and sorted(p.name for p in tmp_path.iterdir()) == ["out.fifo"]
    target, link = tmp_path / "target.txt", tmp_path / "link.txt"
    target.write_text("old\n")
    link.symlink_to(target)
    assert atomic_write_text(link, "new\n") == target
    assert link.is_symlink() and target.read_text() == "new\n"
