"""The schedule: the pipeline thread runs jobs one at a time in submission order, off the calling thread, and hands
back their results and errors; the worker pool maps a function over the batch's shares."""

import threading

import pytest

from torchevtrack.schedule import Job, PipelineThread, Schedule, thread_count, usable_cores


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


def test_a_failing_share_waits_for_the_others():
    """The caller works the first share, the pool the others; an error in the first still lets them finish (they
    use the tracker's state) before it propagates."""
    import time

    schedule = Schedule(3, workers=3)
    done, threads = [], set()

    def fn(rows, item):
        threads.add(threading.current_thread().name)
        if rows.start == 0:
            raise RuntimeError(f"share {item} failed")
        time.sleep(0.05)
        done.append(item)
        return item

    assert schedule.map(lambda rows, item: (rows, item), ["a", "b", "c"]) == [
        (slice(0, 1), "a"), (slice(1, 2), "b"), (slice(2, 3), "c")]
    with pytest.raises(RuntimeError, match="share a failed"):
        schedule.map(fn, ["a", "b", "c"])
    assert sorted(done) == ["b", "c"] and threading.current_thread().name in threads and len(threads) >= 2
    schedule.close()


@pytest.mark.parametrize("bad", [0, -1, True, 1.5, "2"])
def test_a_thread_count_is_a_positive_int_or_none_for_every_caller(bad):
    assert thread_count(None) == usable_cores() and thread_count(3) == 3
    with pytest.raises(ValueError, match="workers must be a positive int or None"):
        thread_count(bad)
    with pytest.raises(ValueError, match="workers must be a positive int or None"):
        Schedule(batch_size=2, workers=bad)
