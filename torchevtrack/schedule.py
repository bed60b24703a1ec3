"""Where an update's work runs: the calling thread, a worker pool over shares of the batch, a pipeline thread.

:class:`Schedule` is the tracker's one interface to threads. It splits the batch into contiguous shares, one per
worker (:meth:`Schedule.map` runs a function on each share, the first on the calling thread and the others on a pool
meanwhile), and owns one pipeline thread (:meth:`Schedule.submit`) on which, with one worker, part of an update runs
while the calling thread does the rest. The compiled kernels release the GIL, so each thread runs on a core of its own.

The pipeline thread is a :class:`PipelineThread`: ``concurrent.futures.ThreadPoolExecutor.submit`` builds a
``Future`` with its condition variable and a work item under two locks, ~10 us of Python per job on this project's
machines; :meth:`PipelineThread.submit` puts the job on a ``queue.SimpleQueue`` (C) and the caller waits on one plain
lock, ~2 us, which counts at 1000 updates/s. Jobs run one at a time, in the order they were submitted.

Example:
    >>> from torchevtrack.schedule import Schedule
    >>> schedule = Schedule(batch_size=4, workers=2, pipeline=False)
    >>> schedule.shares
    [slice(0, 2, None), slice(2, 4, None)]
    >>> schedule.map(lambda rows: list(range(4))[rows])
    [[0, 1], [2, 3]]
    >>> schedule.close()
"""

from __future__ import annotations

import os
import queue
import threading
from concurrent.futures import ThreadPoolExecutor, wait
from typing import Any, Callable, TypeVar

import numpy as np
import torch

__all__ = ["Job", "PipelineThread", "Schedule"]

_T = TypeVar("_T")


class Job:
    """A job given to a :class:`PipelineThread`: its result once it has run (or the error it raised)."""

    __slots__ = ("_fn", "_args", "_done", "_value", "_error")

    def __init__(self, fn: Callable[..., Any] | None, args: tuple) -> None:
        self._fn, self._args = fn, args
        self._done = threading.Lock()
        self._done.acquire()  # released once the job has run
        self._value: Any = None
        self._error: BaseException | None = None

    @classmethod
    def of(cls, value: Any) -> "Job":
        """A job already done, with result ``value``."""
        job = cls(None, ())
        job._value = value
        job._done.release()
        return job

    def _run(self) -> None:
        try:
            self._value = self._fn(*self._args)
        except BaseException as e:  # handed to whoever takes the result
            self._error = e
        self._fn = self._args = None
        self._done.release()

    def wait(self) -> None:
        """Block until the job has run (its error, if any, is not raised)."""
        with self._done:
            pass

    def raised(self) -> bool:
        """Whether the job raised, once it has run (waits for it)."""
        self.wait()
        return self._error is not None

    def result(self) -> Any:
        """The job's return value, once it has run; re-raises its error."""
        self.wait()
        if self._error is not None:
            raise self._error
        return self._value


class PipelineThread:
    """One daemon worker thread running submitted jobs in order.

    Args:
        name: the thread's name (shown by debuggers and profilers).
    """

    def __init__(self, name: str) -> None:
        self._jobs: queue.SimpleQueue[Job | None] = queue.SimpleQueue()
        self._thread = threading.Thread(target=self._work, name=name, daemon=True)
        self._thread.start()

    def submit(self, fn: Callable[..., Any], *args: Any) -> Job:
        """Run ``fn(*args)`` on the thread after the jobs before it; returns its :class:`Job`."""
        if self._jobs is None:
            raise RuntimeError("the pipeline thread is closed")
        job = Job(fn, args)
        self._jobs.put(job)
        return job

    def close(self) -> None:
        """Let the submitted jobs finish, then end the thread."""
        if self._jobs is not None:
            self._jobs.put(None)
            self._thread.join()
            self._jobs = None

    def _work(self) -> None:
        while (job := self._jobs.get()) is not None:
            job._run()


def usable_cores() -> int:
    """The cores this process may run on."""
    return len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else os.cpu_count() or 1


def thread_count(workers: int | None) -> int:
    """``workers`` threads as a caller asked for them: a positive int as it is, ``None`` the :func:`usable_cores`.

    Raises:
        ValueError: ``workers`` neither a positive int (a bool is not one) nor None.
    """
    if workers is None:
        return usable_cores()
    if isinstance(workers, bool) or not isinstance(workers, int) or workers < 1:
        raise ValueError(f"workers must be a positive int or None, got {workers!r}")
    return workers


class Schedule:
    """The threads of a batch of ``batch_size`` elements.

    Args:
        batch_size: ``B``.
        workers: threads that share the batch, each a contiguous share of the elements; default ``min(B, usable
            cores)``; 1 runs everything in the calling thread.
        pipeline: with one worker, a pipeline thread for the caller's :meth:`submit` jobs (default: with two or more
            usable cores). ``False``: :attr:`pipelined` is off, and the caller runs its jobs itself.

    Attributes:
        shares: ``slice`` of the batch rows of each worker (one worker: ``slice(0, B)``).
        pipelined: the caller should hand work to :meth:`submit`.
        pooled: two or more workers.

    Raises:
        ValueError: ``workers`` not a positive int or None; ``pipeline=True`` with two or more workers.
    """

    def __init__(self, batch_size: int, workers: int | None = None, pipeline: bool | None = None) -> None:
        B = batch_size
        cores = usable_cores()
        n = min(thread_count(workers), B)
        self.batch_size = B
        self.shares = [slice(i * B // n, (i + 1) * B // n) for i in range(n)]
        # the calling thread works the first share itself (map): the pool's threads take the others
        self._pool = ThreadPoolExecutor(n - 1, thread_name_prefix="torchevtrack") if n > 1 else None
        if pipeline is None:
            pipeline = self._pool is None and cores > 1
        elif pipeline and self._pool is not None:
            raise ValueError("pipeline needs workers=1: the worker threads already share the batch")
        self.pipelined = bool(pipeline)
        self._thread: PipelineThread | None = None  # made on first use

    @property
    def pooled(self) -> bool:
        return self._pool is not None

    def submit(self, fn: Callable[..., Any], *args: Any) -> Job:
        """Run ``fn(*args)`` on the pipeline thread after the jobs before it (the thread is made on first use)."""
        if self._thread is None:
            self._thread = PipelineThread("torchevtrack-intake")
        return self._thread.submit(fn, *args)

    def map(self, fn: Callable[..., _T], *per_share: list) -> list[_T]:
        """``fn(rows, *args)`` of each share of the batch (``rows``) and its items of ``per_share``: the first share on
        the calling thread, the others on the pool's threads meanwhile (one thread hand-over fewer). Returns once all
        are done (also when one failed: the others may still be using shared state), raising the first's error."""
        if self._pool is None:
            return [fn(slice(None), *(a[0] for a in per_share))]
        inference = torch.is_inference_mode_enabled()  # a thread-local mode: the workers take the caller's

        def run(*args):
            with torch.inference_mode(inference):
                return fn(*args)

        jobs = list(zip(self.shares, *per_share))
        others = [self._pool.submit(run, *args) for args in jobs[1:]]
        try:
            first = fn(*jobs[0])
        finally:
            wait(others)
        return [first] + [f.result() for f in others]

    def split(self, x: torch.Tensor, y: torch.Tensor, t: torch.Tensor, p: torch.Tensor,
              b: torch.Tensor | None) -> list[tuple[torch.Tensor, ...]]:
        """The packed events ``(x, y, t, p, b)`` of each share, ``b`` counted from the share's first element (views of
        the packet when it is ordered by element, as the tracker's ``track`` packs it)."""
        bn = np.zeros(x.shape[0], dtype=np.int64) if b is None else b.numpy().astype(np.int64, copy=False)  # numpy:
        if bn.shape[0] < 2 or bool((bn[1:] >= bn[:-1]).all()):  # fewer and cheaper calls than torch on the packet
            cuts = np.searchsorted(bn, [rows.start for rows in self.shares] + [self.batch_size]).tolist()
            picks = [slice(i, j) for i, j in zip(cuts[:-1], cuts[1:])]
        else:
            picks = [torch.from_numpy((bn >= rows.start) & (bn < rows.stop)) for rows in self.shares]
        return [(x[k], y[k], t[k], p[k], torch.from_numpy(bn[k] - rows.start)) for k, rows in zip(picks, self.shares)]

    def close(self) -> None:
        """End the pool's and the pipeline's threads (after their jobs)."""
        if self._pool is not None:
            self._pool.shutdown()
        if self._thread is not None:
            self._thread.close()
        self._thread = None

    def __getstate__(self) -> dict:
        """Copies and pickles hold the shape of the schedule, not its threads (made again on use)."""
        state = dict(self.__dict__)
        state["_pool"] = None if self._pool is None else self._pool._max_workers
        state["_thread"] = None
        return state

    def __setstate__(self, state: dict) -> None:
        threads = state["_pool"]
        state["_pool"] = None if threads is None else ThreadPoolExecutor(threads, thread_name_prefix="torchevtrack")
        self.__dict__.update(state)
