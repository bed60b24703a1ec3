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


@pytest.mark.parametrize("dtype", [torch.int8, torch.uint8, torch.int32, torch.int64, torch.bool])
def test_polarity_of_any_integer_dtype(dtype):
    # every encoding maps to int8 {0, 1}, against a per-element reference; int8 {0, 1} is taken without a copy
    values = [0, 1, 1, 0] if dtype in (torch.uint8, torch.bool) else [0, 1, -1, 1]
    p = torch.tensor(values).to(dtype)
    ev = EventStream.from_arrays([0] * 4, [0] * 4, [1, 2, 3, 4], p)
    assert ev.p.dtype == torch.int8 and ev.p.tolist() == [int(v > 0) for v in values]
    assert (ev.p.data_ptr() == p.data_ptr()) == (dtype == torch.int8 and min(values) >= 0)
    if dtype != torch.bool:  # a bool is always a polarity
        with pytest.raises(ValueError, match="polarity"):
            EventStream.from_arrays([0], [0], [1], torch.tensor([2 if dtype == torch.uint8 else -2]).to(dtype))


def test_pixels_beyond_int16_are_refused():
    for x in (np.array([1 << 15], np.int32), torch.tensor([-(1 << 15) - 1]), [70_000]):
        with pytest.raises(ValueError, match="int16 range"):
            EventStream.from_arrays(x, [0], [1], [1])
    edge = EventStream.from_arrays(np.array([(1 << 15) - 1, -(1 << 15)], np.int64), [0, 0], [1, 2], [1, 1],
                                   validate=False)  # (a negative pixel is the validation's to refuse)
    assert edge.x.tolist() == [(1 << 15) - 1, -(1 << 15)]


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


def _window(n=6):
    return (torch.tensor([1, 2, 3, 4, 5, 6][:n]), torch.tensor([0, 1, 2, 3, 0, 1][:n]),
            torch.tensor([10, 10, 20, 30, 40, 50][:n]), torch.tensor([1, 0, 1, 1, 0, 0][:n]))


def test_check_window_returns_the_kernels_dtypes():
    from torchevtrack.events import check_window

    x, y, t, p = (v.to(torch.int32) for v in _window())
    b = torch.zeros(6, dtype=torch.int32)
    out = check_window(x, y, t, p, b, width=8, height=4)
    assert [v.dtype for v in out] == [torch.int16, torch.int16, torch.int64, torch.int8, torch.int64]
    assert all(torch.equal(a.long(), c.long()) for a, c in zip(out, (x, y, t, p, b)))
    ev = EventStream.from_arrays(*_window())
    same = check_window(ev.x, ev.y, ev.t, ev.p, width=8, height=4)
    assert all(a is c for a, c in zip(same[:4], (ev.x, ev.y, ev.t, ev.p)))  # no copies on the usual path


@pytest.mark.parametrize("change, message", [
    (lambda w: {"t": w["t"].double() / 1e6}, "t must be an integer tensor microseconds"),
    (lambda w: {"t": w["t"].flip(0)}, "t goes back in time at event 1: 40 us after 50 us"),
    (lambda w: {"t": w["t"] - 15}, "event 0 has t=-5, negative"),
    (lambda w: {"p": w["p"] * 257}, "event 0 has p=257, a polarity not in"),
    (lambda w: {"x": w["x"] + 2}, r"event 5 has x=8, outside \[0, 8\) \(the width\)"),
    (lambda w: {"y": w["y"] - 1}, r"event 0 has y=-1, outside \[0, 4\)"),
    (lambda w: {"x": w["x"][:5]}, "x has 5 events, t has 6"),
    (lambda w: {"b": torch.zeros(5, dtype=torch.long)}, "b has 5 events, t has 6: x, y, t, p, b"),
    (lambda w: {"b": torch.tensor([0, 0, 1, 2, 1, 1])}, r"event 3 has b=2, outside \[0, 2\) \(the batch size\)"),
    (lambda w: {"x": w["x"].numpy()}, "x must be a torch.Tensor"),
    (lambda w: {"x": w["x"][None]}, r"x must be 1-D \(N,\)"),
])
def test_check_window_names_the_tensor_and_event(change, message):
    from torchevtrack.events import check_window

    w = dict(zip("xytp", _window())) | {"b": None}
    w.update(change(w))
    with pytest.raises(ValueError, match=message) as e:
        check_window(w["x"], w["y"], w["t"], w["p"], w["b"], width=8, height=4, batch=2)
    assert "\n" not in str(e.value)


def test_check_window_orders_time_per_batch_element():
    """Time may go back between elements of a packed window, not within one."""
    from torchevtrack.events import check_window

    x, y, _, p = _window()
    b = torch.tensor([1, 0, 1, 0, 1, 0])
    t = torch.tensor([100, 5, 200, 6, 300, 7])
    check_window(x, y, t, p, b, width=8, height=4, batch=2)
    t_bad = torch.tensor([100, 5, 200, 6, 150, 7])
    with pytest.raises(ValueError, match="t goes back in time at event 4 of batch element 1: 150 us after 200 us"):
        check_window(x, y, t_bad, p, b, width=8, height=4, batch=2)
