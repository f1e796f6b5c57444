"""Where a collector's logs go: the next free run index, and writes that never replace a file.

A log is written with ``envi_py.logs.write_log`` under a private staging name (``.NAME.PID.staging``,
sidecar first, each atomically), given the permissions the process umask asks for, and then hard-
linked to its real name: ``os.link`` fails when the name exists, so an existing log is never
replaced, even by a collector racing this one. The sidecar is linked before the CSV, so a CSV
never appears without the sidecar that describes it. A collector killed between the two links
leaves its staging files behind; :func:`finish_staged` completes the job for the next collector.
"""

from __future__ import annotations

import errno
import os
import re
from pathlib import Path

from envi_py.logs import Log, sidecar_path, write_log

STAGING = re.compile(r"^\.+(?P<name>.+)\.(?P<pid>\d+)\.staging(?:\.csv|\.meta\.json)")


class LogExists(ValueError):
    """The log's name is taken; the message names the file."""


def process_umask() -> int:
    """The umask, without changing it (``os.umask`` can only be read by setting it)."""
    mask = os.umask(0o022)
    os.umask(mask)
    return mask


def index_of(name: str, prefix: str) -> int | None:
    """The run index in ``PREFIX_X_INDEX`` or ``PREFIX_INDEX``; None for another prefix."""
    m = re.fullmatch(re.escape(prefix) + r"_(?:.+_)?(\d+)", name)
    return int(m.group(1)) if m else None


def used_indices(folder: Path, prefix: str, reserved: set[str]) -> dict[int, str]:
    """Index -> a name using it, over the logs and sidecars in ``folder`` and ``reserved`` (the ledger's)."""
    names = set(reserved)
    if folder.is_dir():
        for p in folder.iterdir():
            if p.name.startswith("."):
                continue
            if p.name.endswith(".meta.json"):
                names.add(p.name[: -len(".meta.json")])
            elif p.suffix == ".csv":
                names.add(p.stem)
    return {i: n for n in sorted(names) if (i := index_of(n, prefix)) is not None}


def taken(folder: Path, name: str) -> Path | None:
    """The existing CSV or sidecar of log ``name``, if either exists."""
    csv = folder / f"{name}.csv"
    return next((p for p in (csv, sidecar_path(csv)) if p.exists()), None)


def _staged(folder: Path, name: str, pid: int) -> Path:
    return folder / f".{name}.{pid}.staging.csv"


def _link(src: Path, dst: Path) -> None:
    """Give ``src`` the name ``dst`` unless ``dst`` exists (atomically where hard links exist)."""
    try:
        os.link(src, dst)
    except FileExistsError:
        raise LogExists(f"{dst}: exists; not replacing it") from None
    except OSError as exc:
        if exc.errno not in (errno.EPERM, errno.ENOTSUP, errno.EOPNOTSUPP, errno.EXDEV, errno.EMLINK):
            raise
        if dst.exists():  # a file system without hard links: check, then rename
            raise LogExists(f"{dst}: exists; not replacing it") from None
        os.rename(src, dst)
        return
    os.unlink(src)


def _publish(staged: Path, csv: Path) -> None:
    """Link the staged sidecar, then the staged CSV, to their real names."""
    _link(sidecar_path(staged), sidecar_path(csv))
    try:
        _link(staged, csv)
    except LogExists:
        os.unlink(sidecar_path(csv))  # the sidecar just linked would describe someone else's CSV
        raise


def save_new(log: Log, folder: Path, name: str, umask: int) -> Path:
    """Write ``log`` as ``folder/name.csv`` (+ sidecar) with mode ``0o666 & ~umask``; never replaces.

    Raises :class:`LogExists` naming the file when the name is taken; nothing is left behind then.
    """
    csv = folder / f"{name}.csv"
    existing = taken(folder, name)
    if existing is not None:
        raise LogExists(f"{existing}: exists; not replacing it")
    staged = _staged(folder, name, os.getpid())
    write_log(log, staged)
    try:
        for p in (sidecar_path(staged), staged):
            os.chmod(p, 0o666 & ~umask)  # write_log's temporary files are 0600 whatever the umask
        _publish(staged, csv)
    finally:
        for p in (staged, sidecar_path(staged)):
            if p.exists():
                p.unlink()
    return csv


def _alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        return True
    return True


def finish_staged(folder: Path, name: str) -> Path | None:
    """Publish the log ``name`` a dead collector staged but did not finish linking; its CSV, or None.

    write_log stages the sidecar, then the CSV, each atomically: a staged CSV means a whole log.
    """
    csv = folder / f"{name}.csv"
    for staged in folder.glob(f".{name}.*.staging.csv"):
        m = STAGING.match(staged.name)
        if m is None or m.group("name") != name or _alive(int(m.group("pid"))):
            continue
        if not csv.exists():
            if not sidecar_path(csv).exists():
                _link(sidecar_path(staged), sidecar_path(csv))
            _link(staged, csv)
        return csv
    return None


def remove_stale_staging(folder: Path) -> list[Path]:
    """Delete what dead collectors left half-staged (their pid no longer runs); the paths removed.

    Call after :func:`finish_staged` has had its chance at every unsettled run.
    """
    removed = []
    if not folder.is_dir():
        return removed
    for p in folder.iterdir():
        m = STAGING.match(p.name)
        if m is not None and not _alive(int(m.group("pid"))):
            p.unlink()
            removed.append(p)
    return removed
