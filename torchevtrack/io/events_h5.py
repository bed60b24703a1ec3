"""Event streams in HDF5 (DSEC-like flat layout).

File layout: four 1-D datasets of equal length at the root, chunked and compressed:
``x`` int16, ``y`` int16, ``t`` int64 microseconds, ``p`` int8 in ``{0, 1}``. Optional root attributes
``width`` and ``height`` (sensor size). Nothing time-dependent is stored (no HDF5 object timestamps),
so the same events always give the same dataset bytes.

Example:
    >>> import tempfile, os
    >>> from torchevtrack.events import EventStream
    >>> ev = EventStream.from_arrays(x=[1, 2], y=[0, 3], t=[5, 9], p=[1, 0])
    >>> path = os.path.join(tempfile.mkdtemp(), "events.h5")
    >>> write_events_h5(path, ev)
    >>> read_events_h5(path).t.tolist()
    [5, 9]
"""

from __future__ import annotations

from pathlib import Path
from typing import Iterator

import h5py
import numpy as np
import torch

from torchevtrack.events import EventStream, check_window
from torchevtrack.io.atomic import ReplacingWriter, replacing

__all__ = ["EventsH5Writer", "write_events_h5", "read_events_h5", "iter_events_h5", "events_h5_summary"]

_FIELDS = {"x": np.int16, "y": np.int16, "t": np.int64, "p": np.int8}
_CHUNK = 1 << 16


class EventsH5Writer(ReplacingWriter):
    """Append time-sorted event batches to a new HDF5 file (use as a context manager).

    Args:
        path: output file (replaced when the writer closes without an error; untouched otherwise).
        width, height: optional sensor size, stored as root attributes.
        compression: ``"gzip"`` (default, level 4) or ``"lzf"``.
    """

    def __init__(self, path: str | Path, *, width: int | None = None, height: int | None = None,
                 compression: str = "gzip") -> None:
        if compression not in ("gzip", "lzf"):
            raise ValueError(f"compression must be 'gzip' or 'lzf', got {compression!r}")
        self.path = Path(path)
        self._out = replacing(self.path)  # written to a temporary file, renamed over ``path`` at a successful close
        self._f = h5py.File(self._out.tmp, "w", track_order=False)
        opts = {"compression_opts": 4} if compression == "gzip" else {}
        self._d = {
            k: self._f.create_dataset(k, shape=(0,), maxshape=(None,), dtype=dt, chunks=(_CHUNK,),
                                      compression=compression, shuffle=True, track_times=False, **opts)
            for k, dt in _FIELDS.items()
        }
        if width is not None:
            self._f.attrs["width"] = np.int64(width)
        if height is not None:
            self._f.attrs["height"] = np.int64(height)
        self._n = 0
        self._t_last = None

    def append(self, events: EventStream) -> None:
        """Append a batch; its times must not precede the last written event."""
        n = len(events)
        if n == 0:
            return
        if self._t_last is not None and int(events.t[0]) < self._t_last:
            raise ValueError(f"batch starts at t={int(events.t[0])} us, before the last written event "
                             f"({self._t_last} us)")
        if int(events.x.min()) < 0 or int(events.y.min()) < 0:
            raise ValueError("negative pixel coordinates cannot be stored")
        for k, dt in _FIELDS.items():
            d = self._d[k]
            d.resize((self._n + n,))
            d[self._n:] = getattr(events, k).numpy().astype(dt)
        self._n += n
        self._t_last = int(events.t[-1])


def write_events_h5(path: str | Path, events: EventStream, *, width: int | None = None,
                    height: int | None = None, compression: str = "gzip") -> None:
    """Write an event stream to ``path`` (see the module docstring for the layout)."""
    events.validate(width, height)
    with EventsH5Writer(path, width=width, height=height, compression=compression) as w:
        for i in range(0, len(events), 1 << 22):
            w.append(events[i:i + (1 << 22)])


def _open(path: str | Path) -> h5py.File:
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"event file not found: {path}")
    try:
        f = h5py.File(path, "r")
    except OSError as e:
        raise ValueError(f"{path}: not a readable HDF5 file ({e})") from None
    missing = [k for k in _FIELDS if k not in f]
    if missing:
        f.close()
        raise ValueError(f"{path}: missing event dataset(s) {missing}; expected x, y, t, p")
    n = f["t"].shape
    for k in _FIELDS:
        d = f[k]
        if d.ndim != 1 or d.shape != n:
            f.close()
            raise ValueError(f"{path}: dataset {k!r} has shape {d.shape}, expected {n} like 't'")
        if d.dtype.kind not in "iu":
            f.close()
            hint = " microseconds (seconds? store round(t * 1e6) as int64)" if k == "t" else ""
            raise ValueError(f"{path}: dataset {k!r} has dtype {d.dtype}, expected integers{hint}")
    return f


def _read(f: h5py.File, path: Path, i0: int, i1: int, width, height, t_prev: int | None) -> EventStream:
    """Events ``i0 .. i1`` checked (:func:`~torchevtrack.events.check_window`, on the stored values before they
    become int16 / int8, so an x of 40000 or a polarity of 257 is an error, not another pixel or polarity)."""
    x, y, p = (torch.from_numpy(f[k][i0:i1].astype(np.int64)) for k in ("x", "y", "p"))
    t = f["t"][i0:i1]
    if t.dtype == np.uint64 and t.size and int(t.max()) >= 1 << 63:
        raise ValueError(f"{path}: timestamp beyond the int64 range in events {i0} .. {i1 - 1}")
    t = torch.from_numpy(t.astype(np.int64))
    try:
        x, y, t, p, _ = check_window(x, y, t, p, width=width, height=height)
    except ValueError as e:
        where = "" if i0 == 0 else f" (in the events from index {i0})"
        raise ValueError(f"{path}: {e}{where}") from None
    if t_prev is not None and len(t) and int(t[0]) < t_prev:
        raise ValueError(f"{path}: timestamps are not sorted: event {i0} at t={int(t[0])} us follows t={t_prev} us")
    return EventStream(x, y, t, p)


def read_events_h5(path: str | Path, *, width: int | None = None, height: int | None = None) -> EventStream:
    """Read and validate a whole event file (sorted time, polarity, sensor bounds if known).

    ``width``/``height`` default to the file's attributes. Errors name the offending event index.
    """
    with _open(path) as f:
        width = width if width is not None else f.attrs.get("width")
        height = height if height is not None else f.attrs.get("height")
        return _read(f, Path(path), 0, f["t"].shape[0], None if width is None else int(width),
                     None if height is None else int(height), None)


def iter_events_h5(path: str | Path, chunk: int = 1_000_000, *, width: int | None = None,
                   height: int | None = None) -> Iterator[EventStream]:
    """Yield consecutive validated chunks of at most ``chunk`` events (files larger than memory)."""
    if chunk <= 0:
        raise ValueError(f"chunk must be positive, got {chunk}")
    with _open(path) as f:
        width = width if width is not None else f.attrs.get("width")
        height = height if height is not None else f.attrs.get("height")
        n = f["t"].shape[0]
        t_prev = None
        for i in range(0, n, chunk):
            ev = _read(f, Path(path), i, min(i + chunk, n), None if width is None else int(width),
                       None if height is None else int(height), t_prev)
            t_prev = int(ev.t[-1])
            yield ev


def events_h5_summary(path: str | Path) -> dict:
    """Event count, first and last timestamps (us) and stored sensor size, without reading everything."""
    with _open(path) as f:
        n = int(f["t"].shape[0])
        return {
            "n": n,
            "t_first_us": int(f["t"][0]) if n else 0,
            "t_last_us": int(f["t"][n - 1]) if n else 0,
            "width": int(f.attrs["width"]) if "width" in f.attrs else None,
            "height": int(f.attrs["height"]) if "height" in f.attrs else None,
        }
