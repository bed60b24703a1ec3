"""Streaming tracker: same poses as the offline ``track`` for any chunking, window rule, flush, errors."""

import numpy as np
import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st
from torch import nn

from torchevtrack.camera import Camera
from torchevtrack.config import TrackerConfig
from torchevtrack.events import EventStream
from torchevtrack.online import OnlineTracker
from torchevtrack.synth.generate import generate_sequence
from torchevtrack.tracker import EventPoseTracker

CAM = Camera(160, 120, 125.6, 125.6, 79.5, 59.5)
GAP_US = (10_000, 30_000)  # relative to the start


@pytest.fixture(scope="module")
def seq():
    return generate_sequence("box", "regular", 0.05, seed=1, camera=CAM, progress=False)


@pytest.fixture(scope="module")
def tracker(seq):
    tr = EventPoseTracker(CAM, seq.mesh)
    yield tr
    tr.close()


def _t0(seq) -> int:
    return int(seq.gt_t_us[0])


def _gapped(seq) -> EventStream:
    t = seq.events.t - _t0(seq)
    return seq.events.select((t < GAP_US[0]) | (t >= GAP_US[1]))


def _chunks(ev: EventStream, sizes):
    i = 0
    for n in sizes:
        yield ev[i:i + n]
        i += n
    if i < len(ev):
        yield ev[i:]


def _collect(out):
    return torch.tensor([t for t, _ in out]), torch.stack([p for _, p in out], 1)


@pytest.mark.parametrize("chunking", [1, 7, 1000, "random"])
def test_online_equals_offline_for_any_chunking(seq, tracker, chunking):
    ev = seq.events
    times, poses = tracker.track(ev, seq.gt_poses[0], t_start_us=_t0(seq), progress=False)
    if chunking == "random":
        sizes = np.random.default_rng(0).integers(0, 900, size=len(ev)).tolist()  # 0: empty pushes
    else:
        sizes = [chunking] * (len(ev) // chunking + 1)
    online = OnlineTracker(tracker)
    online.start(seq.gt_poses[0], _t0(seq))
    out = []
    for c in _chunks(ev, sizes):
        out += online.push(c)
    t_on, p_on = _collect(out)
    assert torch.equal(t_on, times[0])
    torch.testing.assert_close(p_on, poses, atol=1e-9, rtol=0)
    assert len(online.latencies_ms) == len(out) == len(online.stage_ms)
    assert all(ms >= 0 for ms in online.latencies_ms)
    assert set(online.stage_ms[0]) == {"eros", "flow", "velocity", "render", "correction", "ukf"}


def test_flush_keeps_the_fixed_rate_through_a_gap_and_at_the_end(seq, tracker):
    ev, t0, P = _gapped(seq), _t0(seq), tracker.period_us
    t_end = t0 + 60_000  # beyond the last event (50 ms)
    times, poses = tracker.track(ev, seq.gt_poses[0], t_start_us=t0, t_end_us=t_end, progress=False)
    online = OnlineTracker(tracker)
    online.start(seq.gt_poses[0], t0)
    before = ev.slice_time(0, t0 + GAP_US[0])
    out = []
    for c in _chunks(before, [500] * len(before)):
        out += online.push(c)
    assert online.t_next_us == t0 + GAP_US[0]  # no event at or after its end yet: the window stays open
    flushed = online.flush(t0 + GAP_US[1])  # the sensor was quiet: windows up to the gap end close now
    assert [t for t, _ in flushed] == list(range(t0 + GAP_US[0], t0 + GAP_US[1] + 1, P))
    out += flushed
    for c in _chunks(ev.slice_time(t0 + GAP_US[1], t_end), [500] * len(ev)):
        out += online.push(c)
    out += online.flush(t_end)
    t_on, p_on = _collect(out)
    assert torch.equal(t_on, times[0])
    torch.testing.assert_close(p_on, poses, atol=1e-9, rtol=0)


def test_batched_streams_with_empty_pushes_equal_offline(seq):
    t0 = _t0(seq)
    streams = [seq.events, _gapped(seq)]
    t_end = t0 + 50_000
    tr = EventPoseTracker(CAM, [seq.mesh, seq.mesh])
    times, poses = tr.track(streams, seq.gt_poses[0], t_start_us=t0, t_end_us=t_end, progress=False)
    online = OnlineTracker(tr)
    online.start(seq.gt_poses[0], t0)
    out = []
    # Push 1 ms of each stream at a time; during the gap the second stream's chunks are empty.
    for a in range(t0 - 1000, t_end, 1000):
        out += online.push([s.slice_time(a, a + 1000) for s in streams])
    out += online.flush(t_end)
    tr.close()
    t_on, p_on = _collect(out)
    assert torch.equal(t_on, times[0]) and torch.equal(times[0], times[1])
    torch.testing.assert_close(p_on, poses, atol=1e-9, rtol=0)


# -- the window rule, checked on a recording stand-in for the tracker ---------------------------

class Recorder(EventPoseTracker):
    """Records the packed events of each update; its pose holds the running event count per element."""

    lost = None  # no loss detector

    def __init__(self, batch_size: int, period_us: int) -> None:
        nn.Module.__init__(self)
        self.camera, self.batch_size, self.period_us = CAM, batch_size, period_us
        self.windows: list[list[tuple]] = []
        self.stage_ms = {}

    def reset(self, initial_pose, twist=None, mask=None) -> None:
        self.windows = []
        self.count = torch.zeros(self.batch_size, dtype=torch.float64)

    def forward(self, x, y, t, p, b=None, t_us=None, next_window=None):
        # the streams' own types (EventStream: int16 pixels, int64 us, int8 polarity), no int64 copies
        assert (x.dtype, y.dtype, t.dtype, p.dtype) == (torch.int16, torch.int16, torch.int64, torch.int8)
        b = torch.zeros_like(t) if b is None else b  # one element's events come without a batch index
        self.windows.append([list(zip(*(v[b == i].tolist() for v in (x, y, t, p)))) for i in range(self.batch_size)])
        self.count += torch.bincount(b, minlength=self.batch_size)
        pose = torch.zeros(self.batch_size, 7, dtype=torch.float64)
        pose[:, 0] = self.count
        return pose

    def drop_ahead(self) -> None:  # nothing is taken in ahead
        pass


def _reference_windows(events: list[list[tuple]], t0: int, P: int, n: int):
    """Sequential oracle: window k of element i holds its events with t0 + k P <= t < t0 + (k + 1) P."""
    out = [[[] for _ in events] for _ in range(n)]
    for i, evs in enumerate(events):
        for e in evs:
            k = (e[2] - t0) // P if e[2] >= t0 else -1
            if 0 <= k < n:
                out[k][i].append(e)
    return out


def _events(draw_times, seed: int):
    rng = np.random.default_rng(seed)
    t = np.sort(np.asarray(draw_times, dtype=np.int64))
    n = len(t)
    return EventStream.from_arrays(rng.integers(0, CAM.width, n), rng.integers(0, CAM.height, n), t,
                                   rng.integers(0, 2, n))


def _tuples(ev: EventStream) -> list[tuple]:
    return list(zip(*(getattr(ev, f).long().tolist() for f in ("x", "y", "t", "p"))))


@settings(max_examples=40, deadline=None)
@given(times=st.lists(st.lists(st.integers(0, 20_000), max_size=60), min_size=2, max_size=2),
       cuts=st.lists(st.integers(0, 15), max_size=30), t0=st.integers(0, 3000), P=st.integers(300, 3000),
       packed=st.booleans())
def test_windows_match_the_sequential_rule(times, cuts, t0, P, packed):
    B = 2
    streams = [_events(ts, seed=i) for i, ts in enumerate(times)]
    rec = Recorder(B, P)
    online = OnlineTracker(rec)
    online.start(torch.tensor([0.0, 0, 1, 1, 0, 0, 0]), t0)
    pos = [0, 0]
    got = []
    k = 0
    while pos[0] < len(streams[0]) or pos[1] < len(streams[1]):
        n = cuts[k % len(cuts)] + (k % len(cuts) == 0) if cuts else 5  # 0: an empty push; >= 1 per cycle
        k += 1
        parts = [s[p:p + n] for s, p in zip(streams, pos)]
        pos = [p + n for p in pos]
        if packed:
            b = torch.repeat_interleave(torch.arange(B), torch.tensor([len(q) for q in parts]))
            cat = EventStream.concat(parts)
            got += online.push((cat.x, cat.y, cat.t, cat.p), b=b)
        else:
            got += online.push(parts)
        open_start = online.t_next_us - P  # only pushed events of the open window (or later) are held
        assert online.buffered_events == sum(int((s.t[:p] >= open_start).sum()) for s, p in zip(streams, pos))
    t_end = 20_000 + 2 * P
    got += online.flush(t_end)
    n = (t_end - t0) // P
    assert [t for t, _ in got] == [t0 + (j + 1) * P for j in range(n)]
    assert rec.windows == _reference_windows([_tuples(s) for s in streams], t0, P, n)
    inside = torch.tensor([float(sum(len(w[i]) for w in rec.windows)) for i in range(B)])
    torch.testing.assert_close(got[-1][1][:, 0], inside.double())


def test_window_closes_on_the_first_event_at_or_after_its_end():
    online = OnlineTracker(Recorder(1, 2000))
    online.start(torch.zeros(7), 1000)
    ev = lambda *t: EventStream.from_arrays(x=[1] * len(t), y=[2] * len(t), t=list(t), p=[1] * len(t))  # noqa: E731
    assert online.push(ev(500, 1000, 2999)) == []  # 500 < t0 is ignored
    assert [t for t, _ in online.push(ev(2999, 3000))] == [3000]  # equal times may continue across pushes
    assert online.push(ev(4999)) == []
    assert [t for t, _ in online.push(ev(9000))] == [5000, 7000, 9000]
    assert online.tracker.windows == [[[(1, 2, 1000, 1), (1, 2, 2999, 1), (1, 2, 2999, 1)]],
                                      [[(1, 2, 3000, 1), (1, 2, 4999, 1)]], [[]], [[]]]
    assert online.buffered_events == 1
    assert len(online.latencies_ms) == 4


def test_only_the_open_window_is_kept():
    online = OnlineTracker(Recorder(1, 2000))
    online.start(torch.zeros(7), 0)
    t = torch.arange(0, 1_000_000, 10)
    online.push((t % 160, t % 120, t, t % 2))  # 500 windows in one push
    assert len(online.tracker.windows) == 499  # the event at 999990 us does not close [998000, 1000000)
    assert online.buffered_events == 200
    # The remainder is a copy, not a view that would keep the whole chunk alive.
    held_t = online._pending[0][0][2]
    assert held_t.base is None and held_t.nbytes == 200 * 8


def test_bad_input_is_rejected():
    online = OnlineTracker(Recorder(2, 2000))
    ev = EventStream.from_arrays(x=[1, 2], y=[1, 2], t=[100, 200], p=[0, 1])
    with pytest.raises(RuntimeError, match="start"):
        online.push([ev, ev])
    online.start(torch.zeros(7), 0)
    with pytest.raises(ValueError, match="B=2"):
        online.push(ev)
    with pytest.raises(ValueError, match="2 EventStreams"):
        online.push([ev])
    with pytest.raises(ValueError, match="not sorted"):
        online.push(([1, 2], [1, 2], [300, 250], [0, 1]), b=[0, 0])
    with pytest.raises(ValueError, match=r"b must be in \[0, 2\)"):
        online.push(([1, 2], [1, 2], [300, 350], [0, 1]), b=[0, 2])
    with pytest.raises(TypeError, match="integer"):
        online.push(([1, 2], [1, 2], [300.0, 350.0], [0, 1]), b=[0, 1])
    with pytest.raises(ValueError, match="out of bounds"):
        online.push([ev, EventStream.from_arrays(x=[170], y=[1], t=[5], p=[0])])
    online.push([ev, EventStream.empty()])
    with pytest.raises(ValueError, match="out of order: stream 0"):
        online.push([EventStream.from_arrays(x=[1], y=[1], t=[150], p=[0]), EventStream.empty()])
    online.flush(5000)
    with pytest.raises(ValueError, match="out of order: stream 1 .* t=4000"):
        online.push([EventStream.empty(), EventStream.from_arrays(x=[1], y=[1], t=[4000], p=[0])])
    with pytest.raises(TypeError, match="t_us"):
        online.flush(6000.5)
    with pytest.raises(TypeError, match="EventPoseTracker"):
        OnlineTracker(object())


@pytest.mark.parametrize("render_ahead", [False, True])
def test_pushes_of_several_windows_run_the_pipeline_with_the_serial_poses(seq, render_ahead):
    """A push that completes several windows lets the tracker take each next one in ahead (with render.ahead, one
    stream's windows go into the EROS side on the pipeline's thread instead): same poses."""
    t0 = _t0(seq)
    ev = seq.events.slice_time(t0, t0 + 30_000)
    cfg = TrackerConfig().replace(render={"ahead": render_ahead})
    out = {}
    for pipeline in (False, True):
        tracker = EventPoseTracker(CAM, seq.mesh, cfg, workers=1, pipeline=pipeline)
        online = OnlineTracker(tracker)
        online.start(seq.gt_poses[0], t0)
        got = []
        for a in range(t0, t0 + 30_000, 7000):  # 3-4 windows per push
            got += online.push(ev.slice_time(a, a + 7000))
        got += online.flush(t0 + 30_000)
        tracker.close()
        out[pipeline] = _collect(got)
        assert tracker._run.ahead is None and len(online.stage_ms) == 15
    assert torch.equal(out[True][0], out[False][0]) and torch.equal(out[True][1], out[False][1])


class _Constant(EventPoseTracker):
    """A stand-in tracker that answers at once (its pose: zero) and reports stage times and lost flags."""

    def __init__(self, period_us: int) -> None:
        nn.Module.__init__(self)
        self.camera, self.batch_size, self.period_us = CAM, 1, period_us
        self.stage_ms = {"eros": 0.1, "flow": 0.2}

    @property
    def lost(self) -> torch.Tensor:
        return torch.zeros(1, dtype=torch.bool)

    def reset(self, initial_pose, twist=None, mask=None) -> None:
        pass

    def forward(self, x, y, t, p, b=None, t_us=None, next_window=None):
        return torch.zeros(1, 7, dtype=torch.float64)

    def drop_ahead(self) -> None:
        pass


def test_streaming_keeps_memory_flat():
    """500 Hz for 20 s (10000 updates): the statistics keep the last `history` updates and the traced memory after
    20 s is that after 4 s (unbounded lists grew ~470 bytes per update: 3.8 MB over the last 16 s)."""
    import tracemalloc

    online = OnlineTracker(_Constant(2000), history=200)
    online.start(torch.tensor([0.0, 0.0, 0.5, 1.0, 0.0, 0.0, 0.0]), 0)
    rng = np.random.default_rng(0)

    def stream(seconds: int, t_from: int) -> int:
        for k in range(seconds * 500):
            t = np.sort(rng.integers(t_from + 2000 * k, t_from + 2000 * (k + 1), 20))
            online.push(EventStream.from_arrays(rng.integers(0, 160, 20), rng.integers(0, 120, 20), t,
                                                rng.integers(0, 2, 20), validate=False))
        return t_from + seconds * 1_000_000

    tracemalloc.start()
    try:
        t = stream(4, 0)
        after_4s = tracemalloc.get_traced_memory()[0]
        stream(16, t)
        after_20s = tracemalloc.get_traced_memory()[0]
    finally:
        tracemalloc.stop()
    assert online.updates == 10_000 - 1  # the last window is still open
    assert len(online.latencies_ms) == len(online.stage_ms) == len(online.lost) == 200
    assert after_20s - after_4s < 100_000, f"grew {after_20s - after_4s} bytes in 16 s"


def test_history_must_be_positive():
    with pytest.raises(ValueError, match="history must be a positive number of updates"):
        OnlineTracker(_Constant(2000), history=0)
