"""Where chunks of sampling work run: in this process, in local processes (default) or on
a Dask cluster (when a scheduler address or a ``distributed.Client`` is given).

All executors share one method, ``imap_unordered(fn, items)``, which yields ``(item,
result)`` pairs as they complete; the caller (:func:`balustrade.learn.dataset.run_sampling`)
writes each result as soon as it arrives, so the completion order does not matter and no
result is held longer than needed. Tasks must be picklable top-level functions; the
compiled problems are built on the workers (see :class:`~balustrade.learn.sampler.ProblemSpec`).
Dask has a per-task overhead of a few milliseconds: send chunks of hundreds of solves.
"""

from __future__ import annotations

import multiprocessing
import os
from collections.abc import Callable, Iterable, Iterator
from concurrent.futures import FIRST_COMPLETED, Future, ProcessPoolExecutor, wait
from typing import Any, Protocol

from balustrade.errors import BalustradeError


class Executor(Protocol):
    def imap_unordered(self, fn: Callable[..., Any], items: Iterable[Any],
                       *args: Any) -> Iterator[tuple[Any, Any]]: ...

    def close(self) -> None: ...


class SerialExecutor:
    """Run every task here, in order (debugging, tiny jobs)."""

    workers = 1

    def imap_unordered(self, fn: Callable[..., Any], items: Iterable[Any],
                       *args: Any) -> Iterator[tuple[Any, Any]]:
        for item in items:
            yield item, fn(*args, item)

    def close(self) -> None:
        pass

    def __enter__(self) -> SerialExecutor:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


class LocalExecutor:
    """A pool of local worker processes (``concurrent.futures.ProcessPoolExecutor``,
    ``forkserver`` start method: safe with threads in the parent); at most ``2 × workers``
    tasks are in flight so that results stream to disk."""

    def __init__(self, workers: int | None = None, start_method: str = "forkserver"):
        self.workers = int(workers or os.cpu_count() or 1)
        if self.workers < 1:
            raise BalustradeError(f"LocalExecutor: workers must be >= 1, got {workers!r}")
        ctx = multiprocessing.get_context(start_method)
        self.pool = ProcessPoolExecutor(self.workers, mp_context=ctx)

    def imap_unordered(self, fn: Callable[..., Any], items: Iterable[Any],
                       *args: Any) -> Iterator[tuple[Any, Any]]:
        pending: dict[Future, Any] = {}
        it = iter(items)
        exhausted = False
        while True:
            while not exhausted and len(pending) < 2 * self.workers:
                try:
                    item = next(it)
                except StopIteration:
                    exhausted = True
                    break
                pending[self.pool.submit(fn, *args, item)] = item
            if not pending:
                return
            done, _ = wait(list(pending), return_when=FIRST_COMPLETED)
            for fut in done:
                item = pending.pop(fut)
                yield item, fut.result()

    def close(self) -> None:
        self.pool.shutdown(wait=True, cancel_futures=True)

    def __enter__(self) -> LocalExecutor:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


class DaskExecutor:
    """Tasks on a Dask cluster: ``DaskExecutor("tcp://host:8786")`` connects to a running
    scheduler; ``DaskExecutor(client=c)`` reuses a client (e.g. of a ``LocalCluster``).
    Requires ``dask[distributed]`` (the ``learn`` extra)."""

    def __init__(self, address: str | None = None, client: Any = None):
        try:
            from distributed import Client
        except ImportError as exc:  # pragma: no cover - depends on the environment
            raise BalustradeError("DaskExecutor needs 'dask[distributed]' "
                                  "(pip install 'balustrade[learn]')") from exc
        if client is None and address is None:
            raise BalustradeError("DaskExecutor: give a scheduler address or a client")
        self._own = client is None
        self.client = Client(address) if client is None else client

    @property
    def workers(self) -> int:
        """Worker threads (cores) connected now: the sum of ``nthreads`` over the workers
        (a cluster that is still starting has fewer than it will have; run_sampling takes the
        largest count it sees)."""
        info = self.client.scheduler_info().get("workers", {})
        return max(1, sum(int(w.get("nthreads", 1) or 1) for w in info.values()))

    def imap_unordered(self, fn: Callable[..., Any], items: Iterable[Any],
                       *args: Any) -> Iterator[tuple[Any, Any]]:
        from distributed import as_completed

        items = list(items)
        futures = [self.client.submit(fn, *args, item, pure=False) for item in items]
        index = {fut.key: item for fut, item in zip(futures, items)}
        for fut in as_completed(futures):
            result = fut.result()
            fut.release()
            yield index[fut.key], result

    def close(self) -> None:
        if self._own:
            self.client.close()

    def __enter__(self) -> DaskExecutor:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


def make_executor(workers: int | None = None, scheduler: str | None = None,
                  client: Any = None) -> SerialExecutor | LocalExecutor | DaskExecutor:
    """Dask if ``scheduler``/``client`` is given, else local processes (``workers=1``: this
    process)."""
    if scheduler is not None or client is not None:
        return DaskExecutor(scheduler, client)
    if workers == 1:
        return SerialExecutor()
    return LocalExecutor(workers)
