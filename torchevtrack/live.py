"""Live tracking: events from a network stream, a camera or a recording played at its own pace, into the
streaming tracker (:class:`~torchevtrack.online.OnlineTracker`).

Sources (:func:`open_source`) yield time-sorted :class:`~torchevtrack.events.EventStream` chunks as they arrive,
or ``None`` while nothing arrived (so the caller can report and stop in time):

* ``tcp://HOST:PORT``: an AEDAT4 event stream over TCP, as DV software and dv-processing's ``NetworkWriter``
  serve it (``dv.io.NetworkReader``); it ends when the server closes the connection.
* ``camera`` or ``camera:NAME``: an iniVation camera through dv-processing (the first one found, or the named one).
* a recording file in any format :func:`torchevtrack.io.formats.open_events` reads, as fast as it can be read, or
  with ``realtime=True`` at the pace of its time stamps (its first :data:`AHEAD_EVENTS` decoded before its clock starts:
  decoding shares the tracking thread).

:class:`LiveRunner` pushes the chunks into the tracker from the first event's time on and keeps the poses. It
drops late events (older than an event already received: a stream must not go back in time) and events outside
the sensor, and counts both. Its status gives the update rate and the lag: how far the newest pose is behind real
time, i.e. the wall-clock time since the first event minus the stream time the poses have reached (meaningful for
sources that deliver in real time: network, camera, ``realtime`` playback). dv-processing is needed for network
streams and cameras (``pip install 'torchevtrack[live]'``).

Example (with a server at that address)::

    from torchevtrack.live import LiveRunner, open_source
    runner = LiveRunner(OnlineTracker(tracker), pose0)
    for chunk in open_source("tcp://127.0.0.1:7777"):
        runner.feed(chunk)
    t_us, poses = runner.trajectory()
"""

from __future__ import annotations

import itertools
import time
from collections import deque
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch

from torchevtrack.events import EventStream
from torchevtrack.online import OnlineTracker

__all__ = ["AHEAD_EVENTS", "parse_source", "open_source", "LiveStatus", "LiveRunner"]

_IDLE_S = 0.0005  # wait between polls of a source that has nothing new
_REALTIME_CHUNK_US = 1000  # a paced recording is delivered in chunks of this many microseconds
# A paced recording is decoded this many events ahead of its clock before the clock starts (13 bytes each in memory):
# decoding shares the tracking thread (an HDF5 file's gzip: ~0.3 s per second of a 3.5 M events/s recording here)
AHEAD_EVENTS = 50_000_000


def _dv():
    try:
        import dv_processing
    except ImportError:
        raise ValueError("network streams and cameras need dv-processing: pip install 'torchevtrack[live]'") from None
    return dv_processing


def _from_store(store) -> EventStream:
    """A dv-processing ``EventStore`` as an EventStream (int64 microseconds)."""
    a = store.numpy()
    return EventStream.from_arrays(x=a["x"].astype(np.int64), y=a["y"].astype(np.int64),
                                   t=a["timestamp"].astype(np.int64), p=a["polarity"].astype(np.int64),
                                   validate=False)


class _DvSource:
    """Event batches of a dv-processing reader (``NetworkReader`` or a camera)."""

    def __init__(self, reader, what: str) -> None:
        if not reader.isEventStreamAvailable():
            raise ValueError(f"{what} has no event stream")
        self.reader, self.what = reader, what
        self.width, self.height = (int(v) for v in reader.getEventResolution())

    def __iter__(self) -> Iterator[EventStream | None]:
        while True:
            store = self.reader.getNextEventBatch()
            if store is not None and store.size() > 0:
                yield _from_store(store)
            elif not self.reader.isRunning():
                return
            else:
                time.sleep(_IDLE_S)
                yield None


class _FileSource:
    """The chunks of a recording, as fast as read, or paced by their time stamps (``realtime``): then its first
    :data:`AHEAD_EVENTS` events are decoded before the clock starts, so that decoding them does not slow the tracker
    down during the playback (the rest, of a longer recording, is decoded as it comes)."""

    def __init__(self, path: Path, realtime: bool) -> None:
        from torchevtrack.io.formats import open_events

        self.file = open_events(path, chunk_events=100_000)
        self.width, self.height = self.file.width, self.file.height
        self.realtime = realtime

    def __iter__(self) -> Iterator[EventStream | None]:
        if not self.realtime:
            yield from self.file
            return
        chunks = iter(self.file)
        ahead: deque[EventStream] = deque()  # decoded before the clock starts
        n = 0
        for chunk in chunks:
            ahead.append(chunk)
            n += len(chunk)
            if n >= AHEAD_EVENTS:
                break
        start_wall = start_t = None
        for chunk in itertools.chain(_drain(ahead), chunks):
            if start_t is None:
                start_wall, start_t = time.perf_counter(), int(chunk.t[0])
            t = chunk.t.numpy()
            edges = np.arange(int(t[0]) - (int(t[0]) - start_t) % _REALTIME_CHUNK_US + _REALTIME_CHUNK_US,
                              int(t[-1]) + _REALTIME_CHUNK_US + 1, _REALTIME_CHUNK_US)
            cuts = [0, *np.searchsorted(t, edges).tolist()]
            for a, b, end in zip(cuts[:-1], cuts[1:], edges):
                while (wait := start_wall + (int(end) - start_t) * 1e-6 - time.perf_counter()) > 0:
                    time.sleep(min(wait, 0.05))
                    yield None
                if b > a:
                    yield chunk[a:b]


def _drain(queue: deque) -> Iterator:
    """The items of ``queue``, each removed as it is given (so that it is freed once used)."""
    while queue:
        yield queue.popleft()


def parse_source(source: str, *, realtime: bool = False) -> tuple[str, object]:
    """Check a source string without opening it: ``("tcp", (host, port))``, ``("camera", name)`` (``""``: the
    first found) or ``("file", path)``. Raises ``ValueError`` / ``FileNotFoundError`` with a one-line message."""
    if source.startswith("tcp://"):
        host, sep, port = source[len("tcp://"):].rpartition(":")
        if not sep or not host or not port.isdigit():
            raise ValueError(f"network source must be tcp://HOST:PORT, got {source!r}")
        if realtime:
            raise ValueError("--realtime is for recording files: a network stream comes at its own pace")
        return "tcp", (host, int(port))
    if source == "camera" or source.startswith("camera:"):
        if realtime:
            raise ValueError("--realtime is for recording files: a camera comes at its own pace")
        return "camera", source.partition(":")[2]
    path = Path(source)
    if not path.is_file():
        raise FileNotFoundError(f"event source is not tcp://HOST:PORT, camera[:NAME] or an existing file: {source}")
    return "file", path


def open_source(source: str, *, realtime: bool = False):
    """An iterable event source (see the module docstring and :func:`parse_source`) with ``width`` and ``height``
    (pixels, ``None`` when a recording does not say)."""
    kind, where = parse_source(source, realtime=realtime)
    if kind == "file":
        return _FileSource(where, realtime)
    dv = _dv()
    if kind == "tcp":
        try:
            reader = dv.io.NetworkReader(*where)
        except RuntimeError as e:
            raise ValueError(f"cannot connect to {source}: {e}") from None
        return _DvSource(reader, source)
    try:
        reader = dv.io.camera.open(where) if where else dv.io.camera.open()
    except RuntimeError as e:
        raise ValueError(f"cannot open camera {where or '(first found)'}: {e}") from None
    return _DvSource(reader, f"camera {where}".strip())


@dataclass
class LiveStatus:
    """Counters of a :class:`LiveRunner`.

    Attributes:
        poses: poses produced; events: events pushed into the tracker; late: events dropped because they were
        older than one already received; dropped: events dropped outside the sensor (or by undistortion);
        stream_s: stream time the poses have reached, seconds since the first event; rate_hz: updates per
        second of wall-clock time over the last status period; lag_ms: wall-clock time since the first event minus
        ``stream_s`` (ms; how far the poses are behind a source that delivers in real time).
    """

    poses: int = 0
    events: int = 0
    late: int = 0
    dropped: int = 0
    stream_s: float = 0.0
    rate_hz: float = 0.0
    lag_ms: float = 0.0

    def line(self) -> str:
        return (f"live: {self.poses} poses, {self.rate_hz:.0f} updates/s, stream {self.stream_s:.3f} s, "
                f"lag {self.lag_ms:.1f} ms, late {self.late}, dropped {self.dropped}")


class LiveRunner:
    """Feeds source chunks into an :class:`OnlineTracker` started at ``initial_pose`` on the first event's time.

    Args:
        online: the streaming tracker (one batch element).
        initial_pose: ``(7,)`` pose at the first event's time.
        undistort: optional callable ``EventStream -> EventStream`` applied to each chunk (e.g. a
            :class:`~torchevtrack.distortion.Undistorter`); its ``dropped`` counter, if any, is added to ``dropped``.
    """

    def __init__(self, online: OnlineTracker, initial_pose: torch.Tensor, undistort=None) -> None:
        if online.batch_size != 1:
            raise ValueError(f"live tracking runs one object (batch size 1), got {online.batch_size}")
        self.online, self.initial_pose, self.undistort = online, initial_pose, undistort
        self.status = LiveStatus()
        self._t_us: list[int] = []
        self._poses: list[torch.Tensor] = []
        self._t_first: int | None = None
        self._t_max: int | None = None
        self._wall_first: float | None = None
        self._rate_mark = (time.perf_counter(), 0)
        cam = online.tracker.camera
        self._size = (cam.width, cam.height)

    def feed(self, chunk: EventStream | None) -> list[tuple[int, torch.Tensor]]:
        """Push one chunk (``None``: nothing arrived); returns the new ``(t_us, pose (7,))``."""
        if chunk is None or len(chunk) == 0:
            return []
        x, y, t = chunk.x.numpy(), chunk.y.numpy(), chunk.t.numpy()
        floor = np.maximum.accumulate(t)
        if self._t_max is not None:
            floor = np.maximum(floor, self._t_max)
        in_order = t >= floor
        inside = (x >= 0) & (x < self._size[0]) & (y >= 0) & (y < self._size[1])
        self.status.late += int((~in_order).sum())
        self.status.dropped += int((in_order & ~inside).sum())
        keep = in_order & inside
        if not keep.all():
            chunk = chunk.select(torch.from_numpy(keep))
        if len(chunk) == 0:
            return []
        self._t_max = int(chunk.t[-1])
        if self.undistort is not None:
            before = int(getattr(self.undistort, "dropped", 0))
            chunk = self.undistort(chunk)
            self.status.dropped += int(getattr(self.undistort, "dropped", 0)) - before
            if len(chunk) == 0:
                return []
        if self._t_first is None:
            self._t_first, self._wall_first = int(chunk.t[0]), time.perf_counter()
            self.online.start(self.initial_pose, self._t_first)
        self.status.events += len(chunk)
        out = [(t_us, pose[0]) for t_us, pose in self.online.push(chunk)]
        for t_us, pose in out:
            self._t_us.append(t_us)
            self._poses.append(pose)
        self.status.poses = len(self._t_us)
        return out

    def report(self) -> LiveStatus:
        """The counters now, with the rate since the last call."""
        now = time.perf_counter()
        mark_wall, mark_n = self._rate_mark
        if now > mark_wall:
            self.status.rate_hz = (self.status.poses - mark_n) / (now - mark_wall)
        self._rate_mark = (now, self.status.poses)
        if self._t_first is not None:
            reached = (self._t_us[-1] if self._t_us else self._t_first) - self._t_first
            self.status.stream_s = reached / 1e6
            self.status.lag_ms = (now - self._wall_first) * 1e3 - reached / 1e3
        return self.status

    def trajectory(self, since: int = 0) -> tuple[torch.Tensor, torch.Tensor]:
        """The poses so far from the ``since``-th on (default every one): ``t_us (N,)`` int64 (window ends) and
        ``poses (N, 7)`` float64 (a caller that saves as it goes asks for the new ones only)."""
        if since >= len(self._t_us):
            return torch.zeros(0, dtype=torch.int64), torch.zeros(0, 7, dtype=torch.float64)
        return torch.tensor(self._t_us[since:], dtype=torch.int64), torch.stack(self._poses[since:])
