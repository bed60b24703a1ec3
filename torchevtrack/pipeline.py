"""The tracker's pipeline thread: one worker thread whose hand-overs cost little.

The tracker gives its pipeline thread two or three jobs per update (:class:`~torchevtrack.tracker.EventPoseTracker`),
so at 1000 updates/s the cost of a hand-over counts. ``concurrent.futures.ThreadPoolExecutor.submit`` builds a
``Future`` with its condition variable and a work item under two locks, ~10 us of Python per job on this project's
machines; :meth:`PipelineThread.submit` puts the job on a ``queue.SimpleQueue`` (C) and the caller waits on one
plain lock, ~2 us. Jobs run one at a time, in the order they were submitted.

Example:
    >>> from torchevtrack.pipeline import PipelineThread
    >>> thread = PipelineThread("example")
    >>> job = thread.submit(sum, (1, 2, 3))
    >>> job.result()
    6
    >>> thread.close()
"""

from __future__ import annotations

import queue
import threading
from typing import Any, Callable

__all__ = ["Job", "PipelineThread"]


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
