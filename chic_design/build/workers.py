"""The build's picture jobs (preview, tilt plot, precision map): in a worker process, or in this one.

The pictures need only the geometry objects and the feasibility report, so by
default a worker process (the second core) draws them while this process
does the CAD work. Each job returns its wall time (s). The worker ends with
the build, even when the build is killed (:func:`chic_design.lifeline.die_with_parent`).
"""

from __future__ import annotations

import functools
import multiprocessing
import os
from concurrent.futures import Future, ProcessPoolExecutor

from chic_design.lifeline import die_with_parent


class PictureJobs:
    """Jobs submitted by name; :meth:`collect` waits for them and returns their wall times."""

    def __init__(self, in_worker: bool):
        self.executor = (ProcessPoolExecutor(max_workers=1, mp_context=multiprocessing.get_context("spawn"),
                                             initializer=die_with_parent, initargs=(os.getpid(),))
                         if in_worker else None)
        self.jobs: list[tuple[str, object]] = []

    def submit(self, name: str, fn, *args) -> None:
        job = self.executor.submit(fn, *args) if self.executor else functools.partial(fn, *args)
        self.jobs.append((name, job))

    def collect(self) -> dict[str, float]:
        return {name: job.result() if isinstance(job, Future) else job() for name, job in self.jobs}

    def close(self, cancel: bool = False) -> None:
        """Wait for the worker (so nothing writes into the folder afterwards) and stop it."""
        if self.executor is not None:
            self.executor.shutdown(wait=True, cancel_futures=cancel)
            self.executor = None
