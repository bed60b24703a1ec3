"""Run a list of independent tasks serially, on a local process pool, or on a Ray cluster.

An :class:`Executor` maps a function over tasks and returns the results in task order, whatever order they
finish in; the function and the tasks must be picklable for ``"process"`` and ``"ray"`` (a module-level
function, plain data). The benchmark commands run each (sequence, method, draw) as one task, so the three
executors give the same results and differ only in where the work runs.

* ``"serial"``: one task after the other in this process (the default; the only one that shows the tasks' own
  progress bars).
* ``"process"``: a local pool of ``workers`` processes (default: the usable cores), started with ``spawn``;
  each worker runs torch on one thread.
* ``"ray"``: Ray tasks of one CPU each. Without ``address``, a local Ray is started on this machine with
  ``workers`` CPUs (default: the usable cores) and stopped by :meth:`Executor.close`; with ``address``
  (``"auto"``, ``"HOST:6379"`` or ``"ray://HOST:10001"``), the tasks run on that cluster. Ray is an optional
  dependency (``pip install torchevtrack[ray]``).

Example:
    >>> from torchevtrack.executor import make_executor
    >>> with make_executor("serial") as ex:
    ...     ex.map(abs, [-2, 3, -4], progress=False)
    [2, 3, 4]
"""

from __future__ import annotations

import multiprocessing
import os
from collections.abc import Callable, Sequence
from concurrent.futures import ProcessPoolExecutor, as_completed
from typing import Any

from tqdm.auto import tqdm

__all__ = ["EXECUTORS", "Executor", "SerialExecutor", "ProcessExecutor", "RayExecutor", "make_executor"]

EXECUTORS = ("serial", "process", "ray")


class Executor:
    """Runs independent tasks; a context manager (:meth:`close` on exit).

    Attributes:
        name: ``"serial"``, ``"process"`` or ``"ray"``.
        parallel: tasks may run at the same time (in other processes): their own progress bars are best off.
    """

    name = "serial"
    parallel = False

    def map(self, fn: Callable[[Any], Any], tasks: Sequence[Any], *, desc: str = "tasks", progress: bool = True,
            on_done: Callable[[int, Any], None] | None = None) -> list:
        """``[fn(t) for t in tasks]``, in task order; a tqdm bar over finished tasks when ``progress``, and
        ``on_done(index, result)`` called in this process as each task finishes (in the order they finish).

        The first task that raises stops the run and its exception propagates.
        """
        raise NotImplementedError

    def close(self) -> None:
        """Release the workers (and a local Ray this executor started)."""

    def __enter__(self) -> "Executor":
        return self

    def __exit__(self, *exc) -> None:
        self.close()


class SerialExecutor(Executor):
    """Every task in the calling process, one after the other."""

    def map(self, fn, tasks, *, desc="tasks", progress=True, on_done=None):
        out = []
        for i, t in enumerate(tqdm(tasks, desc=desc, unit="task", disable=not progress)):
            out.append(fn(t))
            if on_done is not None:
                on_done(i, out[-1])
        return out


def _one_thread() -> None:
    import torch

    torch.set_num_threads(1)


class ProcessExecutor(Executor):
    """A local pool of ``workers`` processes (default: the usable cores), each running torch on one thread."""

    name = "process"
    parallel = True

    def __init__(self, workers: int | None = None) -> None:
        self.workers = _check_workers(workers)
        self._pool = ProcessPoolExecutor(self.workers, mp_context=multiprocessing.get_context("spawn"),
                                         initializer=_one_thread)

    def map(self, fn, tasks, *, desc="tasks", progress=True, on_done=None):
        futures = [self._pool.submit(fn, t) for t in tasks]
        index = {f: i for i, f in enumerate(futures)}
        try:
            with tqdm(total=len(futures), desc=desc, unit="task", disable=not progress) as bar:
                for f in as_completed(futures):
                    r = f.result()  # the first failure stops the run
                    if on_done is not None:
                        on_done(index[f], r)
                    bar.update()
        except BaseException:
            for f in futures:
                f.cancel()
            raise
        return [f.result() for f in futures]

    def close(self) -> None:
        self._pool.shutdown(cancel_futures=True)


class RayExecutor(Executor):
    """Ray tasks of one CPU each: on the cluster at ``address``, or on a local Ray with ``workers`` CPUs."""

    name = "ray"
    parallel = True

    def __init__(self, address: str | None = None, workers: int | None = None) -> None:
        try:
            import ray
        except ImportError:
            raise ValueError("--executor ray needs Ray: pip install 'torchevtrack[ray]'") from None
        self._ray = ray
        self._started = False
        if not ray.is_initialized():
            if address is None:
                ray.init(num_cpus=_check_workers(workers), include_dashboard=False, log_to_driver=False,
                         runtime_env={"env_vars": _python_path()})
            else:
                ray.init(address=address, log_to_driver=False)
            self._started = True
        self.address = address
        self.cpus = int(ray.cluster_resources().get("CPU", 0))

    def map(self, fn, tasks, *, desc="tasks", progress=True, on_done=None):
        ray = self._ray
        remote = ray.remote(num_cpus=1, max_retries=0)(_apply)
        fn_ref = ray.put(fn)
        refs = [remote.remote(fn_ref, t) for t in tasks]
        index = {r: i for i, r in enumerate(refs)}
        pending = list(refs)
        try:
            with tqdm(total=len(refs), desc=desc, unit="task", disable=not progress) as bar:
                while pending:
                    done, pending = ray.wait(pending, num_returns=1)
                    r = ray.get(done[0])  # the first failure stops the run
                    if on_done is not None:
                        on_done(index[done[0]], r)
                    bar.update(len(done))
        except BaseException:
            for r in pending:
                ray.cancel(r)
            raise
        return ray.get(refs)

    def close(self) -> None:
        if self._started:
            self._ray.shutdown()
            self._started = False


def _apply(fn: Callable[[Any], Any], task: Any) -> Any:
    """``fn(task)``: the Ray task (any picklable callable, e.g. a ``functools.partial``)."""
    return fn(task)


def _python_path() -> dict[str, str]:
    """The driver's ``PYTHONPATH`` for local workers (a source checkout not installed with pip)."""
    path = os.environ.get("PYTHONPATH")
    return {"PYTHONPATH": path} if path else {}


def _check_workers(workers: int | None) -> int:
    if workers is None:
        from torchevtrack.schedule import usable_cores  # (imports torch: only when the default is asked for)

        return usable_cores()
    if isinstance(workers, bool) or not isinstance(workers, int) or workers < 1:
        raise ValueError(f"workers must be a positive integer, got {workers!r}")
    return workers


def make_executor(kind: str = "serial", *, workers: int | None = None, address: str | None = None) -> Executor:
    """An executor by name (see the module docstring). ``address`` only applies to ``"ray"``, ``workers`` to
    ``"process"`` and a local Ray."""
    if kind not in EXECUTORS:
        raise ValueError(f"executor must be one of {', '.join(EXECUTORS)}, got {kind!r}")
    if address is not None and kind != "ray":
        raise ValueError(f"--address is for --executor ray, not {kind}")
    if workers is not None and (kind == "serial" or address is not None):
        raise ValueError("--jobs is for --executor process or a local Ray (no --address)")
    if kind == "serial":
        return SerialExecutor()
    if kind == "process":
        return ProcessExecutor(workers)
    return RayExecutor(address, workers)
