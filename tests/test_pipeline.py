"""The pipeline thread: jobs run one at a time in submission order, off the calling thread, and hand back their
results and errors."""

import threading

import pytest

from torchevtrack.schedule import Job, PipelineThread


def test_jobs_run_in_order_on_the_thread():
    thread = PipelineThread("test-order")
    seen = []
    gate = threading.Event()
    first = thread.submit(lambda: (gate.wait(5), seen.append(("first", threading.current_thread().name)))[1])
    jobs = [thread.submit(seen.append, (i, threading.current_thread().name)) for i in range(50)]
    gate.set()  # the later jobs were queued while the first one blocked
    jobs[-1].result()
    first.result()
    assert [s[0] for s in seen] == ["first"] + list(range(50))
    assert seen[0][1] == "test-order"  # the job ran on the thread, not the caller
    thread.close()


def test_a_job_hands_back_its_error_and_the_thread_goes_on():
    thread = PipelineThread("test-error")
    bad = thread.submit(lambda: 1 / 0)
    good = thread.submit(lambda x: x + 1, 41)
    bad.wait()  # waiting does not raise
    assert bad.raised() and not good.raised()
    with pytest.raises(ZeroDivisionError):
        bad.result()
    assert good.result() == 42
    thread.close()


def test_a_done_job_and_a_closed_thread():
    assert Job.of("value").result() == "value"
    thread = PipelineThread("test-close")
    slow = thread.submit(lambda: threading.Event().wait(0.05) or "done")
    thread.close()  # lets the submitted job finish
    assert slow.result() == "done"
    with pytest.raises(RuntimeError, match="closed"):
        thread.submit(print)
