import numpy as np
import pytest
import torch

from torchevtrack.events import EventStream


def _stream(n=1000, seed=0):
    rng = np.random.default_rng(seed)
    t = np.sort(rng.integers(0, 100_000, n))
    return EventStream.from_arrays(rng.integers(0, 64, n), rng.integers(0, 48, n), t, rng.integers(0, 2, n), width=64, height=48)


def test_dtypes_and_polarity_encodings():
    ev = EventStream.from_arrays([1, 2], [3, 4], [10, 20], [-1, 1])
    assert ev.x.dtype == torch.int16 and ev.t.dtype == torch.int64 and ev.p.dtype == torch.int8
    assert ev.p.tolist() == [0, 1]
    assert EventStream.from_arrays([1], [1], [1], [True]).p.tolist() == [1]


def test_slice_time_is_a_view_with_half_open_bounds():
    ev = _stream()
    s = ev.slice_time(20_000, 30_000)
    expected = ((ev.t >= 20_000) & (ev.t < 30_000)).sum()
    assert len(s) == int(expected)
    assert s.t.untyped_storage().data_ptr() == ev.t.untyped_storage().data_ptr()


def test_windows_partition_every_event_once():
    ev = _stream()
    seen = []
    ends = []
    for t_end, w in ev.windows(2000):
        assert (w.t < t_end).all() and (w.t >= t_end - 2000).all()
        seen.append(w.t)
        ends.append(t_end)
    assert torch.equal(torch.cat(seen), ev.t)
    assert np.all(np.diff(ends) == 2000)


def test_windows_yield_empty_windows_in_gaps():
    ev = EventStream.from_arrays([0, 0], [0, 0], [0, 10_000], [1, 1])
    sizes = [len(w) for _, w in ev.windows(2000)]
    assert sizes == [1, 0, 0, 0, 0, 1]


def test_validation_errors():
    with pytest.raises(ValueError, match="not sorted"):
        EventStream.from_arrays([0, 0], [0, 0], [5, 4], [1, 1])
    with pytest.raises(ValueError, match="out of bounds: event 1 has x=64"):
        EventStream.from_arrays([0, 64], [0, 0], [1, 2], [1, 1], width=64, height=48)
    with pytest.raises(ValueError, match="negative timestamp"):
        EventStream.from_arrays([0], [0], [-1], [1])
    with pytest.raises(TypeError, match="integer"):
        EventStream.from_arrays([0.5], [0], [1], [1])
    with pytest.raises(ValueError, match="polarity"):
        EventStream.from_arrays([0], [0], [1], [3])
    with pytest.raises(ValueError, match="positive"):
        list(_stream().windows(0))


def test_concat_and_select():
    ev = _stream(100)
    both = EventStream.concat([ev[:40], ev[40:]])
    assert torch.equal(both.t, ev.t) and torch.equal(both.x, ev.x)
    on = ev.select(ev.p == 1)
    assert (on.p == 1).all() and len(on) == int((ev.p == 1).sum())
