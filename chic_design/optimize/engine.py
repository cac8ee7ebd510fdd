"""Where candidates are evaluated: in this process, on a local process pool, or on a Dask cluster.

Every engine has one method, :meth:`map_unordered`, that runs a top-level
function over argument tuples and yields ``(index, result)`` as each one
finishes (so the driver can store it at once). Order of completion does not
matter to the search: the driver puts results back in ask order before
telling the optimiser, which keeps runs on different engines identical.
"""

from __future__ import annotations

import os
from concurrent.futures import ProcessPoolExecutor, as_completed

from chic_design.optimize.errors import RequirementsError


class SerialEngine:
    """Everything in the calling process (one worker)."""

    workers = 1
    name = "serial"

    def map_unordered(self, fn, arg_tuples):
        for i, args in enumerate(arg_tuples):
            yield i, fn(*args)

    def close(self):
        pass


class LocalEngine:
    """A pool of ``workers`` local processes."""

    name = "local"

    def __init__(self, workers: int):
        self.workers = workers
        self._pool = ProcessPoolExecutor(max_workers=workers)

    def map_unordered(self, fn, arg_tuples):
        futures = {self._pool.submit(fn, *args): i for i, args in enumerate(arg_tuples)}
        try:
            for f in as_completed(futures):
                yield futures[f], f.result()
        finally:
            for f in futures:
                f.cancel()

    def close(self):
        self._pool.shutdown(wait=True, cancel_futures=True)


class DaskEngine:
    """A Dask distributed client: to ``tcp://HOST:PORT``, or to a ``LocalCluster`` of ``n`` workers."""

    name = "dask"

    def __init__(self, scheduler: str):
        from distributed import Client, LocalCluster  # dask: seconds to load, only for a --scheduler run

        self._cluster = None
        if scheduler.startswith("local:"):
            n = int(scheduler.split(":", 1)[1])
            self._cluster = LocalCluster(n_workers=n, threads_per_worker=1, processes=True,
                                         dashboard_address=None)
            self._client = Client(self._cluster)
        else:
            self._client = Client(scheduler, timeout="20s")
        self.workers = max(1, len(self._client.scheduler_info().get("workers", {})))

    def map_unordered(self, fn, arg_tuples):
        from distributed import as_completed as dask_completed  # loaded with the client above

        futures = [self._client.submit(fn, *args, pure=False) for args in arg_tuples]
        index = {f.key: i for i, f in enumerate(futures)}
        try:
            for f in dask_completed(futures):
                yield index[f.key], f.result()
        finally:
            self._client.cancel(futures)

    def close(self):
        self._client.close()
        if self._cluster is not None:
            self._cluster.close()


def parse_scheduler(value: str | None) -> str | None:
    """Check a ``--scheduler`` value: ``tcp://HOST:PORT`` or ``local:N``; returns it unchanged."""
    if value is None:
        return None
    if value.startswith("tcp://") and ":" in value[6:]:
        return value
    if value.startswith("local:") and value[6:].isdigit() and int(value[6:]) >= 1:
        return value
    raise RequirementsError(f"--scheduler {value!r}: allowed are tcp://HOST:PORT or local:N (N >= 1 workers)")


def make_engine(scheduler: str | None = None, workers: int | None = None):
    """Dask when a scheduler is given, else a local pool of ``workers`` (default: the CPU count)."""
    if scheduler is not None:
        return DaskEngine(parse_scheduler(scheduler))
    n = workers if workers is not None else (os.cpu_count() or 1)
    if n < 1:
        raise RequirementsError(f"--workers {n}: allowed is an integer >= 1")
    return SerialEngine() if n == 1 else LocalEngine(n)
