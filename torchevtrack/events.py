"""Event streams: storage, validation, time slicing and fixed-window iteration.

An event is ``(x, y, t, p)``: integer pixel column ``x`` and row ``y``, timestamp ``t`` in
**int64 microseconds** (never float32 seconds: at 1e9 us a float32 resolves only 64 us), and
polarity ``p`` in ``{0, 1}`` (1 = brightness increase).

Slicing and window iteration return views into the same storage, never copies.

Example:
    >>> import torch
    >>> from torchevtrack.events import EventStream
    >>> ev = EventStream.from_arrays(x=[1, 2, 3], y=[0, 0, 1], t=[0, 1500, 2500], p=[1, 0, 1])
    >>> [len(w) for _, w in ev.windows(2000)]
    [2, 1]
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Iterator, Sequence

import numpy as np
import torch

from torchevtrack.kernels import kernel

__all__ = ["EventStream", "US_PER_S", "check_window", "first_invalid", "pack_streams"]

US_PER_S = 1_000_000


def _as_tensor(a, name: str) -> torch.Tensor:
    """``a`` as a 1-D integer (or bool) tensor of its own dtype (a tensor or a contiguous numpy array is not copied)."""
    if isinstance(a, torch.Tensor):
        t = a
    else:
        arr = np.asarray(a)
        if arr.dtype.kind not in "iub" and arr.size:
            raise TypeError(f"event field {name!r} must be integer, got dtype {arr.dtype}")
        t = torch.from_numpy(np.ascontiguousarray(arr))
    if t.is_floating_point() or t.is_complex():
        raise TypeError(f"event field {name!r} must be an integer tensor, got {t.dtype}")
    if t.ndim != 1:
        raise ValueError(f"event field {name!r} must be 1-D, got shape {tuple(t.shape)}")
    return t


def _pixels(a, name: str) -> torch.Tensor:
    """Pixel coordinates as int16 (checked to fit unless they are int16 already)."""
    t = _as_tensor(a, name)
    if t.dtype != torch.int16 and t.numel():
        lo, hi = (int(v) for v in torch.aminmax(t.to(torch.int64) if t.dtype == torch.bool else t))
        if lo < -(1 << 15) or hi >= (1 << 15):
            raise ValueError(f"event field {name!r} has pixel coordinates beyond the int16 range")
    return t.to(torch.int16)


def _polarity(a) -> torch.Tensor:
    """Polarity {0, 1}, {-1, 1} or bool as int8 {0, 1} (int8 {0, 1} is kept as it is)."""
    t = _as_tensor(a, "p")
    if t.dtype == torch.bool or not t.numel():
        return t.to(torch.int8)
    lo, hi = (int(v) for v in torch.aminmax(t))
    if lo < -1 or hi > 1:
        raise ValueError("polarity must be in {0, 1} or {-1, 1}")
    return t if lo >= 0 and t.dtype == torch.int8 else (t > 0).to(torch.int8)


@dataclass(frozen=True)
class EventStream:
    """A time-sorted sequence of events held as four 1-D tensors of equal length ``N``.

    Attributes:
        x: ``(N,)`` int16 pixel columns.
        y: ``(N,)`` int16 pixel rows.
        t: ``(N,)`` int64 timestamps, microseconds.
        p: ``(N,)`` int8 polarity in ``{0, 1}``.
    """

    x: torch.Tensor
    y: torch.Tensor
    t: torch.Tensor
    p: torch.Tensor

    @classmethod
    def from_arrays(cls, x, y, t, p, *, validate: bool = True, width: int | None = None,
                    height: int | None = None) -> "EventStream":
        """Build from array-likes; polarity may be {0, 1}, {-1, 1} or bool (all map to {0, 1})."""
        ev = cls(_pixels(x, "x"), _pixels(y, "y"), _as_tensor(t, "t").to(torch.int64), _polarity(p))
        if validate:
            ev.validate(width, height)
        return ev

    @classmethod
    def empty(cls) -> "EventStream":
        z16 = torch.zeros(0, dtype=torch.int16)
        return cls(z16, z16.clone(), torch.zeros(0, dtype=torch.int64), torch.zeros(0, dtype=torch.int8))

    @classmethod
    def concat(cls, streams: list["EventStream"]) -> "EventStream":
        """Concatenate streams in order (the result must still be time-sorted to validate)."""
        if not streams:
            return cls.empty()
        return cls(*(torch.cat([getattr(s, f) for s in streams]) for f in ("x", "y", "t", "p")))

    def __len__(self) -> int:
        return int(self.t.shape[0])

    def __getitem__(self, index: slice) -> "EventStream":
        if not isinstance(index, slice):
            raise TypeError("EventStream supports slicing only (views); use .select(mask) for masks")
        return EventStream(self.x[index], self.y[index], self.t[index], self.p[index])

    def select(self, mask: torch.Tensor) -> "EventStream":
        """Events where ``mask`` is true (a copy)."""
        return EventStream(self.x[mask], self.y[mask], self.t[mask], self.p[mask])

    @property
    def t_start(self) -> int:
        return int(self.t[0]) if len(self) else 0

    @property
    def t_end(self) -> int:
        return int(self.t[-1]) if len(self) else 0

    @property
    def duration_s(self) -> float:
        return (self.t_end - self.t_start) / US_PER_S

    def validate(self, width: int | None = None, height: int | None = None) -> "EventStream":
        """Check shapes, dtypes, sorted non-negative time and sensor bounds; raise ``ValueError``."""
        n = len(self)
        for name in ("x", "y", "p"):
            f = getattr(self, name)
            if f.ndim != 1 or f.shape[0] != n:
                raise ValueError(f"event field {name!r} has shape {tuple(f.shape)}, expected ({n},)")
        if self.t.dtype != torch.int64:
            raise TypeError(f"timestamps must be int64 microseconds, got {self.t.dtype}")
        if n == 0:
            return self
        no_limit = 1 << 62
        kind, i = first_invalid(self.x.numpy(), self.y.numpy(), self.t.numpy(),
                                no_limit if width is None else width, no_limit if height is None else height)
        if kind == 1:
            raise ValueError(f"negative timestamp {int(self.t[0])} us at event 0")
        if kind == 2:
            raise ValueError(
                f"timestamps are not sorted: event {i} at t={int(self.t[i])} us follows t={int(self.t[i - 1])} us"
            )
        if kind:
            name, size = ("x", width) if kind == 3 else ("y", height)
            raise ValueError(
                f"pixel out of bounds: event {i} has {name}={int(getattr(self, name)[i])}"
                + (f", sensor {name}-size is {size}" if size is not None else "")
            )
        return self

    def slice_time(self, t0: int, t1: int) -> "EventStream":
        """Events with ``t0 <= t < t1`` (microseconds), as a view."""
        i0, i1 = np.searchsorted(self.t.numpy(), (t0, t1)).tolist()  # numpy: ~10x less call overhead than torch's
        return self[i0:i1]

    def windows(self, dt_us: int, t_start: int | None = None,
                t_end: int | None = None) -> Iterator[tuple[int, "EventStream"]]:
        """Iterate consecutive windows ``[t_k - dt_us, t_k)`` and yield ``(t_k, view)``.

        ``t_k = t_start + k * dt_us`` for ``k = 1, 2, ...`` until the window holding ``t_end`` (default:
        the first and last timestamps, so every event is in exactly one window). Empty windows are
        yielded too, so the caller keeps a fixed rate.
        """
        if dt_us <= 0:
            raise ValueError(f"window length must be positive, got {dt_us} us")
        t_start = self.t_start if t_start is None else int(t_start)
        t_end = self.t_end if t_end is None else int(t_end)
        n = -(-(t_end - t_start + 1) // dt_us)
        if n <= 0:
            return
        bounds = t_start + dt_us * torch.arange(n + 1, dtype=torch.int64)
        idx = torch.searchsorted(self.t, bounds).tolist()
        for k in range(n):
            yield int(bounds[k + 1]), self[idx[k]: idx[k + 1]]

    def event_rate(self) -> float:
        """Mean events per second."""
        return len(self) / self.duration_s if self.duration_s > 0 else 0.0


def check_window(x, y, t, p, b=None, *, width: int | None = None, height: int | None = None,
                 batch: int = 1) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor | None]:
    """Check one window of packed events and return it in the kernels' dtypes; raise a one-line ``ValueError``
    that names the tensor and the first bad event.

    Args:
        x, y: ``(N,)`` integer pixel columns / rows, ``0 <= x < width``, ``0 <= y < height`` (without a size:
            ``< 32768``, the int16 storage).
        t: ``(N,)`` integer microseconds (not float seconds), ``>= 0``, non-decreasing within each batch element
            (whether time goes back across windows is the caller's business).
        p: ``(N,)`` polarity in ``{0, 1}`` (or bool).
        b: ``(N,)`` integer batch index in ``[0, batch)``, or ``None`` (all element 0).

    Returns:
        ``(x, y, t, p, b)``: int16, int16, int64, int8 and int64 (or ``None``) tensors, the inputs themselves when
        they already have these dtypes. One set of dtypes means one compiled signature per kernel (an int32
        ``x`` would otherwise compile every kernel again).

    Cost: a few vectorised passes over ``N`` (tens of microseconds for a window of thousands of events).

    Example:
        >>> import torch
        >>> x, y, t, p, b = check_window(torch.tensor([3, 4]), torch.tensor([1, 1]), torch.tensor([10, 20]),
        ...                              torch.tensor([1, 0]), width=8, height=4)
        >>> x.dtype, t.dtype, p.dtype, b
        (torch.int16, torch.int64, torch.int8, None)
        >>> check_window(x, y, torch.tensor([20, 10]), p, width=8, height=4)
        Traceback (most recent call last):
        ...
        ValueError: t goes back in time at event 1: 10 us after 20 us
    """
    fields = {"x": x, "y": y, "t": t, "p": p} | ({} if b is None else {"b": b})
    for name, v in fields.items():
        if not isinstance(v, torch.Tensor):
            raise ValueError(f"{name} must be a torch.Tensor, got {type(v).__name__}")
        if v.ndim != 1:
            raise ValueError(f"{name} must be 1-D (N,), got shape {tuple(v.shape)}")
        if v.is_floating_point() or v.is_complex():
            unit = " microseconds (seconds? use (t * 1e6).round().long())" if name == "t" else ""
            raise ValueError(f"{name} must be an integer tensor{unit}, got {v.dtype}")
    n = t.shape[0]
    for name, v in fields.items():
        if v.shape[0] != n:
            raise ValueError(f"{name} has {v.shape[0]} events, t has {n}: x, y, t, p{', b' if b is not None else ''} "
                             "must have one entry per event")
    if n:
        limits = {"x": (0, width if width is not None else 1 << 15, "width"),
                  "y": (0, height if height is not None else 1 << 15, "height"),
                  "p": (0, 2, None), "t": (0, None, None)}
        if b is not None:
            limits["b"] = (0, int(batch), "batch size")
        for name, (lo, hi, what) in limits.items():
            v = fields[name]
            if v.dtype == torch.bool:
                continue
            bad = (v < lo) if hi is None else ((v < lo) | (v >= hi))
            if bool(bad.any()):
                i = int(bad.nonzero()[0, 0])
                rule = "negative" if hi is None else f"outside [{lo}, {hi})" + (f" (the {what})" if what else "")
                if name == "p":
                    rule = "a polarity not in {0, 1}"
                raise ValueError(f"event {i} has {name}={int(v[i])}, {rule}")
        tt = t.to(torch.int64)
        if b is None:
            back = tt[1:] < tt[:-1]
        else:
            bb = b.to(torch.int64)
            order = torch.argsort(bb, stable=True) if bool((bb[1:] < bb[:-1]).any()) else None
            ts, bs = (tt, bb) if order is None else (tt[order], bb[order])
            back = (ts[1:] < ts[:-1]) & (bs[1:] == bs[:-1])
        if bool(back.any()):
            k = int(back.nonzero()[0, 0]) + 1
            if b is None or order is None:
                i, j = k, k - 1
            else:
                i, j = int(order[k]), int(order[k - 1])
            where = "" if b is None else f" of batch element {int(b[i])}"
            raise ValueError(f"t goes back in time at event {i}{where}: {int(t[i])} us after {int(t[j])} us")
    return (x.to(torch.int16), y.to(torch.int16), t.to(torch.int64), p.to(torch.int8),
            None if b is None else b.to(torch.int64))


def pack_streams(parts: Sequence[EventStream]) -> tuple:
    """Concatenate per-element windows into packed events ``(x, y, t, p, b)`` with a batch index ``b`` (``None`` for
    one element), in the streams' own integer types (the kernels take them as they are: no int64 copies).

    Shape: ``B`` streams of ``N_i`` events -> five ``(sum N_i,)`` tensors (``b`` int64 in ``[0, B)``).

    Example:
        >>> a = EventStream.from_arrays([1], [2], [10], [1])
        >>> b = EventStream.from_arrays([3, 4], [5, 6], [11, 12], [0, 1])
        >>> pack_streams([a, b])[4].tolist()
        [0, 1, 1]
    """
    if len(parts) == 1:
        q = parts[0]
        return q.x, q.y, q.t, q.p, None
    sizes = torch.tensor([len(q) for q in parts])
    b = torch.repeat_interleave(torch.arange(len(parts)), sizes)
    cat = lambda f: torch.cat([getattr(q, f) for q in parts])  # noqa: E731
    return cat("x"), cat("y"), cat("t"), cat("p"), b


@kernel
def first_invalid(x, y, t, width, height):
    """The first problem of non-empty events (numpy ``(N,)`` arrays ``x, y, t``, ``N > 0``), in
    :meth:`EventStream.validate`'s order of checks, as ``(kind, index)``: 1 a negative first time, 2 time going back
    at ``index``, 3 / 4 the first ``x`` / ``y`` outside ``[0, width)`` / ``[0, height)``; ``(0, 0)`` if none. One
    compiled pass for the time, one for the pixels."""
    if t[0] < 0:
        return 1, 0
    for i in range(1, t.shape[0]):
        if t[i] < t[i - 1]:
            return 2, i
    i = _first_outside(x, width)
    if i >= 0:
        return 3, i
    i = _first_outside(y, height)
    return (4, i) if i >= 0 else (0, 0)


@kernel
def _first_outside(f, size):
    """Index of the first value of ``f`` outside ``[0, size)``, or -1."""
    for i in range(f.shape[0]):
        if f[i] < 0 or f[i] >= size:
            return i
    return -1
