"""Streaming tracking: feed events as they arrive, get poses at the tracker's fixed rate.

:class:`OnlineTracker` wraps an :class:`~torchevtrack.tracker.EventPoseTracker` and cuts the incoming
events into the same fixed windows as the offline :meth:`~torchevtrack.tracker.EventPoseTracker.track`:
window ``k`` (``k = 0, 1, ...``) holds the events with ``t0 + k P <= t < t0 + (k + 1) P`` (``P`` the
update period, 2000 us by default) and its pose is stamped with the window end ``t0 + (k + 1) P``.
Events before ``t0`` are ignored, as offline.

**When a window is complete.** Every event stream is assumed time-sorted, so once an event with
``t >= t_end`` has been received, no further event of ``[.., t_end)`` can come: the rule is that a window
closes as soon as an event at or after its end has been pushed (for ``B > 1``: on every stream, the
streams advance in lockstep), or when :meth:`OnlineTracker.flush` declares the sensor quiet up to a time.
Flushing is how a stream with a gap, or its end, still yields poses at the fixed rate.

Given the same events, the poses are those of the offline ``track`` with ``t_start_us = t0``, for any
way of cutting the events into chunks (one event, part of a window, many windows at once).

Only the events of the current, incomplete window are buffered (with ``B > 1``, also those of a stream
that is ahead of the slowest one), never the recording.

Tracking loss: with ``config.loss.enabled`` each update is stamped with its window end for the tracker's
loss detector (and its ``on_lost`` callback, :meth:`OnlineTracker.build`), :attr:`OnlineTracker.lost`
collects the per-update flags, and :meth:`OnlineTracker.reset` re-initialises chosen elements at any time
without breaking the window sequence.

Example:
    >>> import torch
    >>> from torchevtrack.camera import Camera
    >>> from torchevtrack.tracker import EventPoseTracker
    >>> from torchevtrack.events import EventStream
    >>> from torchevtrack.online import OnlineTracker
    >>> online = OnlineTracker(EventPoseTracker(Camera(64, 48, 60.0, 60.0, 31.5, 23.5), "can"))
    >>> online.start(torch.tensor([0.0, 0.0, 0.4, 1.0, 0.0, 0.0, 0.0]), t0_us=0)
    >>> online.push(EventStream.from_arrays(x=[3], y=[4], t=[1500], p=[1]))  # window [0, 2000) still open
    []
    >>> [t for t, pose in online.push(EventStream.from_arrays(x=[5], y=[4], t=[4100], p=[0]))]
    [2000, 4000]
    >>> [t for t, pose in online.flush(8000)]  # nothing more before 8000 us
    [6000, 8000]
"""

from __future__ import annotations

import operator
import time
from collections import deque
from typing import Sequence

import numpy as np
import torch

from torchevtrack.camera import Camera
from torchevtrack.config import TrackerConfig
from torchevtrack.events import EventStream, pack_streams
from torchevtrack.loss import OnLost
from torchevtrack.tracker import EventPoseTracker, MeshLike

__all__ = ["OnlineTracker"]


class OnlineTracker:
    """Push-based front end of an :class:`EventPoseTracker` (``B`` streams in lockstep).

    Args:
        tracker: the tracker to drive (its ``batch_size`` is ``B``, its ``period_us`` the window length).
        history: how many of the latest updates the statistics below keep (default 10000: 20 s at 500 Hz),
            so that memory stays flat however long the stream runs.

    Attributes:
        updates: updates run since :meth:`start`.
        latencies_ms: for each of the last ``history`` updates, milliseconds from the call of the :meth:`push` (or
            :meth:`flush`) that completed its window to that call returning the pose. When one call completes
            several windows, all their poses are returned together and share that call's latency.
        stage_ms: for each of the last ``history`` updates, the tracker's ``stage_ms`` (milliseconds per stage).
        lost: for each of the last ``history`` updates, the tracker's ``lost`` flags ``(B,)`` bool (only with a
            loss detector, else empty).

    The three are lists, copied from bounded buffers at each access.
    """

    def __init__(self, tracker: EventPoseTracker, history: int = 10_000) -> None:
        if not isinstance(tracker, EventPoseTracker):
            raise TypeError(f"tracker must be an EventPoseTracker, got {type(tracker).__name__}")
        if isinstance(history, bool) or not isinstance(history, int) or history < 1:
            raise ValueError(f"history must be a positive number of updates, got {history!r}")
        self.history = history
        self.tracker = tracker
        self.batch_size: int = tracker.batch_size
        self.period_us: int = int(tracker.period_us)
        self._latencies_ms: deque[float] = deque(maxlen=history)
        self._stage_ms: deque[dict[str, float]] = deque(maxlen=history)
        self._lost: deque[torch.Tensor] = deque(maxlen=history)
        self._t0: int | None = None
        self._done = 0  # windows emitted since start()
        self._received: list[int] = []  # per stream: every event before this time has been received
        self._pending: list[list[tuple[np.ndarray, ...]]] = []  # per stream: (x, y, t, p) chunks of the open window

    @classmethod
    def build(cls, camera: Camera, meshes: MeshLike | Sequence[MeshLike], config: TrackerConfig | None = None,
              batch_size: int | None = None, on_lost: OnLost | None = None) -> "OnlineTracker":
        """Create the :class:`EventPoseTracker` (same arguments) and wrap it."""
        return cls(EventPoseTracker(camera, meshes, config, batch_size, on_lost))

    # -- state -------------------------------------------------------------------------------
    def start(self, initial_pose: torch.Tensor, t0_us: int, twist: torch.Tensor | None = None) -> None:
        """Reset the tracker at ``initial_pose`` ``(B, 7)`` or ``(7,)`` (optional twist ``(B, 6)``) at time
        ``t0_us`` (int microseconds, >= 0): the first window is ``[t0_us, t0_us + P)``."""
        t0 = _as_time(t0_us, "t0_us")
        self.tracker.reset(initial_pose, twist)
        self._t0 = t0
        self._done = 0
        self._received = [0] * self.batch_size
        self._pending = [[] for _ in range(self.batch_size)]
        self._latencies_ms.clear()
        self._stage_ms.clear()
        self._lost.clear()

    def reset(self, pose: torch.Tensor, twist: torch.Tensor | None = None, mask: torch.Tensor | None = None) -> None:
        """Re-initialise tracker elements at ``pose`` ``(B, 7)`` or ``(7,)`` (optional twist ``(B, 6)``) now:
        the next window continues the sequence. ``mask`` (``(B,)`` bool or ``(K,)`` indices) restarts only
        those elements (:meth:`EventPoseTracker.reset`), e.g. the ones the tracker reported lost."""
        self._check_started()
        self.tracker.reset(pose, twist, mask)

    @property
    def updates(self) -> int:
        return self._done

    @property
    def latencies_ms(self) -> list[float]:
        return list(self._latencies_ms)

    @property
    def stage_ms(self) -> list[dict[str, float]]:
        return list(self._stage_ms)

    @property
    def lost(self) -> list[torch.Tensor]:
        return list(self._lost)

    @property
    def t_next_us(self) -> int:
        """End of the window currently being filled (the time stamp of the next pose)."""
        self._check_started()
        return self._t0 + (self._done + 1) * self.period_us

    @property
    def buffered_events(self) -> int:
        """Events held for windows that are not complete yet (all streams)."""
        return sum(len(c[2]) for chunks in self._pending for c in chunks)

    # -- input -------------------------------------------------------------------------------
    def push(self, events, b=None) -> list[tuple[int, torch.Tensor]]:
        """Add newly received events; run one tracker update per window they complete.

        Args:
            events: for ``B = 1`` an :class:`EventStream` or a tuple ``(x, y, t, p)`` of ``(N,)`` integer
                arrays (``t`` in microseconds); for any ``B`` a list of ``B`` EventStreams (each may be
                empty), or the packed tuple with ``b``. Each stream must be time-sorted and continue
                where its previous push (or :meth:`flush`) ended.
            b: ``(N,)`` batch index in ``[0, B)`` of packed events (order is kept within each stream).

        Returns:
            ``[(t_us, pose), ...]``: one entry per completed window, ``t_us`` its end (int microseconds)
            and ``pose`` ``(B, 7)`` float64.

        Raises:
            RuntimeError: :meth:`start` was not called.
            ValueError / TypeError: malformed events, unsorted time, or time going back across pushes.
        """
        t_call = time.perf_counter()
        self._check_started()
        streams = self._split(events, b)
        # numpy views: the buffering below is a few small array operations per push, cheaper in numpy than in torch
        chunks = [_arrays(s) for s in streams]
        for i, (_, _, t, _) in enumerate(chunks):
            if len(t) and int(t[0]) < self._received[i]:
                raise ValueError(
                    f"events out of order: stream {i} got an event at t={int(t[0])} us, but events up to "
                    f"t={self._received[i]} us were already received (pushed or flushed)"
                )
        for i, c in enumerate(chunks):
            t = c[2]
            if len(t):
                self._received[i] = int(t[-1])
                first = int(np.searchsorted(t, self._t0)) if int(t[0]) < self._t0 else 0
                if first < len(t):
                    self._pending[i].append(tuple(f[first:] for f in c))
        return self._run(t_call)

    def flush(self, t_us: int) -> list[tuple[int, torch.Tensor]]:
        """Declare that every event before ``t_us`` has been pushed (the sensor was quiet until then) and
        close every window ending at or before ``t_us``. Later pushes must not go before ``t_us``.

        Returns:
            the completed windows, as for :meth:`push`.
        """
        t_call = time.perf_counter()
        self._check_started()
        t = _as_time(t_us, "t_us")
        self._received = [max(r, t) for r in self._received]
        return self._run(t_call)

    # -- internals ---------------------------------------------------------------------------
    def _check_started(self) -> None:
        if self._t0 is None:
            raise RuntimeError("OnlineTracker: call start(initial_pose, t0_us) before pushing events")

    def _run(self, t_call: float) -> list[tuple[int, torch.Tensor]]:
        """Run the tracker on every complete window; keep only the events of the open one."""
        P, t0 = self.period_us, self._t0
        n = min((r - t0) // P for r in self._received) - self._done
        if n <= 0:
            return []
        ends = [t0 + (self._done + 1 + k) * P for k in range(n)]
        # one pushed chunk is the buffer itself (its remainder is copied below: a view would keep the chunk alive)
        buffers = [_concat(chunks) for chunks in self._pending]
        cuts = [[0] + np.searchsorted(s[2], ends).tolist() for s in buffers]
        windows = [pack_streams([_window(s, c[k], c[k + 1]) for s, c in zip(buffers, cuts)]) for k in range(n)]
        out = []
        try:
            for k in range(n):  # the tracker's pipeline takes in the window after it meanwhile
                ahead = windows[k + 1] if k + 1 < n else None
                out.append((ends[k], self.tracker(*windows[k], t_us=ends[k], next_window=ahead)))
                self._stage_ms.append(dict(self.tracker.stage_ms))
                if self.tracker.lost is not None:
                    self._lost.append(self.tracker.lost.clone())
        finally:
            self.tracker.drop_ahead()
        # Copy the remainders: a view would keep the whole pushed chunk alive.
        self._pending = [[] if c[-1] == len(s[2]) else [tuple(f[c[-1]:].copy() if len(chunks) == 1 else f[c[-1]:]
                                                              for f in s)]
                         for s, c, chunks in zip(buffers, cuts, self._pending)]
        self._done += n
        latency = (time.perf_counter() - t_call) * 1e3
        self._latencies_ms.extend([latency] * n)
        return out

    def _split(self, events, b) -> list[EventStream]:
        """Validated per-stream events from any accepted input form."""
        B = self.batch_size
        cam = self.tracker.camera
        if isinstance(events, (list, tuple)) and events and all(isinstance(e, EventStream) for e in events):
            if b is not None:
                raise ValueError("b is only for packed (x, y, t, p) arrays, not for a list of EventStreams")
            if len(events) != B:
                raise ValueError(f"events: expected a list of {B} EventStreams (one per batch element), "
                                 f"got {len(events)}")
            return [e.validate(cam.width, cam.height) for e in events]
        if isinstance(events, EventStream):
            packed = events.validate(cam.width, cam.height) if b is None else events
        elif isinstance(events, (list, tuple)) and len(events) == 4:
            x, y, t, p = events
            packed = EventStream.from_arrays(x, y, t, p, validate=b is None, width=cam.width, height=cam.height)
        else:
            raise TypeError("events must be an EventStream, a tuple (x, y, t, p) of arrays, or a list of "
                            f"{B} EventStreams, got {type(events).__name__}")
        if b is None:
            if B != 1:
                raise ValueError(f"the tracker has B={B} batch elements: pass a list of {B} EventStreams, or "
                                 "packed events with their batch index b")
            return [packed]
        bi = torch.as_tensor(b)
        if bi.is_floating_point() or bi.is_complex() or bi.dtype == torch.bool:
            raise TypeError(f"b must be an integer array, got {bi.dtype}")
        if bi.shape != (len(packed),):
            raise ValueError(f"b must have shape ({len(packed)},) like the events, got {tuple(bi.shape)}")
        if bi.numel() and (int(bi.min()) < 0 or int(bi.max()) >= B):
            raise ValueError(f"b must be in [0, {B}), got values in [{int(bi.min())}, {int(bi.max())}]")
        return [packed.select(bi == i).validate(cam.width, cam.height) for i in range(B)]


def _as_time(value, name: str) -> int:
    try:
        t = operator.index(value)
    except TypeError:
        raise TypeError(f"{name} must be an integer number of microseconds, got {value!r}") from None
    if t < 0:
        raise ValueError(f"{name} must be >= 0 microseconds, got {t}")
    return t


def _concat(chunks: list[tuple[np.ndarray, ...]]) -> tuple[np.ndarray, ...]:
    """One stream's pending ``(x, y, t, p)`` chunks as one (the chunk itself if there is one)."""
    if len(chunks) == 1:
        return chunks[0]
    if not chunks:
        return _arrays(EventStream.empty())
    return tuple(np.concatenate(f) for f in zip(*chunks))


def _arrays(s: EventStream) -> tuple[np.ndarray, ...]:
    """The ``(x, y, t, p)`` of an EventStream as numpy views."""
    return s.x.numpy(), s.y.numpy(), s.t.numpy(), s.p.numpy()


def _window(fields: tuple[np.ndarray, ...], a: int, b: int) -> EventStream:
    """Events ``a:b`` of ``(x, y, t, p)`` arrays as an EventStream of views."""
    return EventStream(*(torch.from_numpy(f[a:b]) for f in fields))
