"""One interface to run independent jobs (an experiment grid's trainings, a seed ensemble's members):
local processes by default, Dask on request.

``executor.map(fn, items)`` yields results as jobs finish (with the item's index), so the caller
shows progress and then orders the results; the same command scales from this machine to a
cluster by passing ``--dask tcp://scheduler:8786``.
"""

from __future__ import annotations

import multiprocessing as mp
import os
import signal
import sys
from collections.abc import Callable, Iterator, Sequence
from concurrent.futures import ProcessPoolExecutor, as_completed
from typing import Any, Protocol


PR_SET_PDEATHSIG = 1  # linux/prctl.h


class Executor(Protocol):
    """Runs ``fn`` on every item; yields (index, result) in completion order."""

    def map(self, fn: Callable[[Any], Any], items: Sequence[Any]) -> Iterator[tuple[int, Any]]: ...

    def close(self) -> None: ...


def _worker_init(parent: int) -> None:
    """Each worker: one torch thread, and it dies with the parent. On Linux the kernel sends it
    SIGKILL when the parent dies (``PR_SET_PDEATHSIG``), so a ``kill -9`` of ``envi experiment``
    leaves no worker behind holding hundreds of MB; a parent already gone before that was set is
    caught by comparing the parent pid."""
    if sys.platform.startswith("linux"):
        import ctypes

        ctypes.CDLL(None, use_errno=True).prctl(PR_SET_PDEATHSIG, signal.SIGKILL)
    if os.getppid() != parent:
        os._exit(1)
    import torch

    torch.set_num_threads(1)


class LocalExecutor:
    """A pool of ``workers`` spawned processes (default: the machine's cores), one torch thread each.

    Spawn rather than fork: a forked child of a process that already ran torch can deadlock.
    ``workers=0`` runs in this process (for debugging and tiny grids).
    """

    def __init__(self, workers: int | None = None) -> None:
        self.workers = (os.cpu_count() or 1) if workers is None else workers
        self._pool = (
            ProcessPoolExecutor(
                self.workers, mp_context=mp.get_context("spawn"), initializer=_worker_init, initargs=(os.getpid(),)
            )
            if self.workers > 0
            else None
        )

    def map(self, fn: Callable[[Any], Any], items: Sequence[Any]) -> Iterator[tuple[int, Any]]:
        if self._pool is None:
            for i, item in enumerate(items):
                yield i, fn(item)
            return
        futures = {self._pool.submit(fn, item): i for i, item in enumerate(items)}
        for fut in as_completed(futures):
            yield futures[fut], fut.result()

    def close(self) -> None:
        if self._pool is not None:
            self._pool.shutdown()


class DaskExecutor:
    """Jobs on a Dask cluster through ``distributed.Client``: an address, or a running ``Client``."""

    def __init__(self, address: Any) -> None:
        from distributed import Client

        self._own = not isinstance(address, Client)
        self.client = Client(address) if self._own else address

    def map(self, fn: Callable[[Any], Any], items: Sequence[Any]) -> Iterator[tuple[int, Any]]:
        from distributed import as_completed as dask_completed

        futures = [self.client.submit(fn, item, pure=False) for item in items]
        index = {f.key: i for i, f in enumerate(futures)}
        for fut in dask_completed(futures):
            yield index[fut.key], fut.result()

    def close(self) -> None:
        if self._own:
            self.client.close()


def make_executor(dask: str | None = None, workers: int | None = None) -> Executor:
    return DaskExecutor(dask) if dask else LocalExecutor(workers)
