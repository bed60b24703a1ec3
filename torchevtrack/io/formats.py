"""Event files of any supported format: detection, streamed reading with validation, writing.

Readers never hold a whole file: ``iter_events`` yields time-sorted :class:`EventStream` chunks of
exactly ``chunk_events`` events (the last one shorter). Formats (``format=`` names):

==============  =============================================================  =======  ===========
name            layout                                                         write    needs
==============  =============================================================  =======  ===========
``events_h5``   our HDF5 (root ``x, y, t, p``; :mod:`torchevtrack.io.events_h5`)  yes
``npz``         numpy ``.npz`` with 1-D arrays ``x, y, t, p`` (``t`` int us)    yes
``text``        one event a line, ``t x y p`` (``#`` comments)                  yes
``dsec``        DSEC HDF5: ``events/{x,y,t,p}``, optional ``t_offset``          no
``aedat4``      iniVation AEDAT 4.0                                             no       ``aedat``
``evt3``        Prophesee EVT 3.0 ``.raw``                                      no       ``evt3``
``yarp``        event-driven/EDOPT ``binaryevents.log`` (uint32 word pairs)     no
``yarp_text``   YARP ``data.log`` bottles ``N T AE (ts ae ts ae ...)``          no
``ycbev``       YCB-Ev zstd int32 pairs ``[t_us, x | y << 14 | p << 28]``       no       ``zstandard``
==============  =============================================================  =======  ===========

Optional packages are in the ``io`` extra: ``pip install "torchevtrack[io]"``.

Validation (always, on every chunk): timestamps non-negative and sorted (error names the event
index unless ``sort=True``, which reads the whole file into memory and sorts stably); duplicates
are kept; polarity in {0, 1}, {-1, 1} or bool; pixels non-negative and, when the sensor size is
known (``width``/``height`` arguments, else the file's own), inside it -- or dropped with
``drop_out_of_bounds=True``. Broken files raise :class:`EventFileError` naming the file and,
where known, the byte offset.

A reader (per format) is an object with ``width``/``height`` (``int | None``, from the file),
``bytes_read`` (``int | None``: progress through the file) and ``chunks(n)`` yielding numpy
``(x, y, t, p)`` blocks in file order with ``t`` int64 microseconds.

Example:
    >>> import tempfile
    >>> from torchevtrack.events import EventStream
    >>> ev = EventStream.from_arrays(x=[1, 2, 3], y=[0, 0, 1], t=[0, 1500, 2500], p=[1, 0, 1])
    >>> path = tempfile.mkdtemp() + "/ev.txt"
    >>> write_events(path, ev)
    3
    >>> [c.t.tolist() for c in iter_events(path, chunk_events=2)]
    [[0, 1500], [2500]]
"""

from __future__ import annotations

import importlib
from collections.abc import Iterable, Iterator
from contextlib import contextmanager
from pathlib import Path

import numpy as np
import torch

from torchevtrack.events import EventStream

__all__ = [
    "EventFileError",
    "EventFile",
    "FORMATS",
    "WRITABLE",
    "detect_format",
    "open_events",
    "iter_events",
    "read_events",
    "write_events",
]

_INSTALL_HINT = 'pip install "torchevtrack[io]"'

# name -> (module, reader class); writers: name -> (module, writer class)
_READERS = {
    "events_h5": ("torchevtrack.io.formats", "_EventsH5Reader"),
    "npz": ("torchevtrack.io.npz_events", "NpzReader"),
    "text": ("torchevtrack.io.text_events", "TextReader"),
    "dsec": ("torchevtrack.io.foreign", "DsecReader"),
    "aedat4": ("torchevtrack.io.foreign", "Aedat4Reader"),
    "evt3": ("torchevtrack.io.foreign", "Evt3Reader"),
    "yarp": ("torchevtrack.io.foreign", "YarpReader"),
    "yarp_text": ("torchevtrack.io.foreign", "YarpTextReader"),
    "ycbev": ("torchevtrack.io.foreign", "YcbEvReader"),
}
_WRITERS = {
    "events_h5": ("torchevtrack.io.events_h5", "EventsH5Writer"),
    "npz": ("torchevtrack.io.npz_events", "NpzWriter"),
    "text": ("torchevtrack.io.text_events", "TextWriter"),
}
FORMATS = tuple(_READERS)
WRITABLE = tuple(_WRITERS)

_EXTENSIONS = {
    ".h5": "events_h5", ".hdf5": "events_h5", ".npz": "npz", ".txt": "text", ".csv": "text",
    ".aedat4": "aedat4", ".raw": "evt3", ".log": "yarp", ".zst": "ycbev", ".zstd": "ycbev",
}
_HDF5_MAGIC = b"\x89HDF\r\n\x1a\n"
ZSTD_MAGIC = b"\x28\xb5\x2f\xfd"
_I64_MAX = np.iinfo(np.int64).max


class EventFileError(ValueError):
    """A broken, truncated or unsupported event file.

    Attributes:
        path: the file.
        offset: byte offset of the problem, or ``None`` when the format cannot tell.
        msg: what is wrong.
    """

    def __init__(self, path: str | Path, offset: int | None, msg: str) -> None:
        self.path = Path(path)
        self.offset = offset
        self.msg = msg
        where = "" if offset is None else f" (byte offset {offset})"
        super().__init__(f"{self.path}{where}: {msg}")


def require(module: str, fmt: str):
    """Import an optional dependency of format ``fmt`` or raise ImportError with the install hint."""
    try:
        return importlib.import_module(module)
    except ImportError:
        raise ImportError(f"reading {fmt} files needs the package {module!r}: {_INSTALL_HINT}") from None


def times_to_int64(t: np.ndarray, path: Path, first_index: int) -> np.ndarray:
    """Integer timestamps (any integer dtype, microseconds) as int64; overflow is an EventFileError."""
    if t.dtype.kind not in "iu":
        raise EventFileError(path, None, f"timestamps must be integers, got dtype {t.dtype}")
    if t.dtype.kind == "u" and t.dtype.itemsize == 8 and t.size and int(t.max()) > _I64_MAX:
        i = int(np.argmax(t > _I64_MAX))
        raise EventFileError(path, None, f"timestamp {int(t[i])} us at event {first_index + i} "
                                         "overflows int64")
    return t.astype(np.int64, copy=False)


def open_hdf5(path: Path):
    """``path`` opened read-only as an ``h5py.File``; :class:`EventFileError` if HDF5 cannot read it."""
    import h5py

    try:
        return h5py.File(path, "r")
    except OSError as e:
        raise EventFileError(path, None, f"unreadable HDF5 file ({e})") from None


def head_lines(path: Path) -> list[bytes]:
    """The whole lines of the first 64 KiB of ``path`` (a line cut at the 64 KiB mark is left out)."""
    with open(path, "rb") as f:
        head = f.read(1 << 16)
    pieces = head.split(b"\n")
    return pieces[:-1] if len(head) == 1 << 16 else pieces


def _magic(path: Path, n: int = 64) -> bytes:
    with open(path, "rb") as f:
        return f.read(n)


def detect_format(path: str | Path) -> str:
    """Format name of an event file, from its first bytes and then its name.

    Raises:
        FileNotFoundError: no such file.
        EventFileError: a known container of an unsupported kind, or nothing recognisable.
    """
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"event file not found: {path}")
    head = _magic(path)
    name = path.name.lower()
    if head.startswith(_HDF5_MAGIC):
        with open_hdf5(path) as f:
            if all(k in f for k in "xytp"):
                return "events_h5"
            if "events" in f and all(k in f["events"] for k in "xytp"):
                return "dsec"
            keys = sorted(f.keys())
        raise EventFileError(path, None, f"HDF5 file with groups/datasets {keys}: neither our layout "
                                         "(root x, y, t, p) nor DSEC (events/x, events/y, events/t, events/p)")
    if head.startswith(b"#!AER-DAT4"):
        return "aedat4"
    if head.startswith(b"#!AER-DAT"):
        version = head[9:12].decode("ascii", "replace")
        raise EventFileError(path, 0, f"AEDAT version {version} is not supported (only AEDAT 4)")
    if head.startswith(ZSTD_MAGIC):
        return "ycbev"
    if head.startswith(b"PK\x03\x04"):
        return "npz"
    if head.startswith(b"% "):
        return "evt3"  # the EVT3 reader checks the header version
    if name == "binaryevents.log":
        return "yarp"
    from torchevtrack.io.foreign import looks_like_yarp_text
    from torchevtrack.io.text_events import looks_like_text

    if looks_like_yarp_text(path):
        return "yarp_text"
    ext = path.suffix.lower()
    if ext in _EXTENSIONS and _EXTENSIONS[ext] not in ("events_h5", "npz"):
        return _EXTENSIONS[ext]
    if looks_like_text(path):
        return "text"
    raise EventFileError(path, 0, f"unrecognised event file (first bytes {head[:8]!r}); "
                                  f"pass format= one of {', '.join(FORMATS)}")


class _EventsH5Reader:
    """Our events.h5 through :mod:`torchevtrack.io.events_h5` (sorted and validated there)."""

    def __init__(self, path: Path) -> None:
        from torchevtrack.io.events_h5 import events_h5_summary

        self.path = path
        with _file_errors(path):
            s = events_h5_summary(path)
        self.width, self.height, self._n = s["width"], s["height"], s["n"]
        self._size = path.stat().st_size
        self.bytes_read: int | None = 0

    def chunks(self, n: int) -> Iterator[tuple[np.ndarray, ...]]:
        from torchevtrack.io.events_h5 import iter_events_h5

        done = 0
        with _file_errors(self.path):  # whole HDF5 storage chunks (64 Ki events): slicing less re-inflates them
            for ev in iter_events_h5(self.path, max(n, 1 << 16)):
                done += len(ev)
                self.bytes_read = self._size * done // max(self._n, 1)
                yield ev.x.numpy(), ev.y.numpy(), ev.t.numpy(), ev.p.numpy()


@contextmanager
def _file_errors(path: Path) -> Iterator[None]:
    """Turn the events_h5 module's ValueError/TypeError into EventFileError."""
    try:
        yield
    except EventFileError:
        raise
    except (ValueError, TypeError) as e:
        msg, prefix = str(e), f"{path}: "
        raise EventFileError(path, None, msg[len(prefix):] if msg.startswith(prefix) else msg) from None


class EventFile:
    """An event file opened for streamed, validated reading (see the module docstring).

    Args:
        path: the file.
        format: a name from ``FORMATS``; default detected by :func:`detect_format`.
        chunk_events: events per yielded chunk.
        width, height: sensor size for the bounds check (default: the file's, if it has one).
        sort: sort by time (stable) instead of failing on unsorted timestamps; loads the whole file.
        drop_out_of_bounds: drop events outside the sensor instead of failing.
        **opts: format options (text: ``time_unit``, ``columns``, ``delimiter``; aedat4:
            ``stream_id``; yarp/yarp_text: ``clock_period_ns``, ``timer_bits``, ``channel``,
            ``invert_polarity``).

    Attributes:
        format, width, height, size_bytes; ``bytes_read`` (``None`` when the format cannot tell).
    """

    def __init__(self, path: str | Path, format: str | None = None, *, chunk_events: int = 1_000_000,
                 width: int | None = None, height: int | None = None, sort: bool = False,
                 drop_out_of_bounds: bool = False, **opts) -> None:
        self.path = Path(path)
        if not self.path.is_file():
            raise FileNotFoundError(f"event file not found: {self.path}")
        self.format = detect_format(self.path) if format is None else format
        if self.format not in _READERS:
            raise ValueError(f"unknown event file format {self.format!r}; expected one of {', '.join(FORMATS)}")
        if int(chunk_events) <= 0:
            raise ValueError(f"chunk_events must be positive, got {chunk_events}")
        for name, v in (("width", width), ("height", height)):
            if v is not None and int(v) <= 0:
                raise ValueError(f"{name} must be positive, got {v}")
        module, cls = _READERS[self.format]
        self._reader = getattr(importlib.import_module(module), cls)(self.path, **opts)
        self.chunk_events = int(chunk_events)
        self.width = int(width) if width is not None else self._reader.width
        self.height = int(height) if height is not None else self._reader.height
        self.sort = sort
        self.drop_out_of_bounds = drop_out_of_bounds
        self.size_bytes = self.path.stat().st_size

    @property
    def bytes_read(self) -> int | None:
        return self._reader.bytes_read

    def __iter__(self) -> Iterator[EventStream]:
        blocks: Iterable[tuple[np.ndarray, ...]] = self._reader.chunks(self.chunk_events)
        if self.sort:
            blocks = [_sorted_all(blocks)]
        pending: list[tuple[np.ndarray, ...]] = []
        n_pending = 0
        index = 0
        t_prev: int | None = None
        for block in blocks:
            n = len(block[2])
            if n == 0:
                continue
            last = block[2][-1]
            block = self._validate(*block, index, t_prev)
            t_prev = int(last)
            index += n
            pending.append(block)
            n_pending += len(block[2])
            while n_pending >= self.chunk_events:
                cat = [np.concatenate(f) for f in zip(*pending)]
                yield _stream(*(f[: self.chunk_events] for f in cat))
                pending = [tuple(f[self.chunk_events:] for f in cat)]
                n_pending -= self.chunk_events
        if n_pending:
            yield _stream(*(np.concatenate(f) for f in zip(*pending)))

    def _validate(self, x, y, t, p, index: int, t_prev: int | None) -> tuple[np.ndarray, ...]:
        """Check one block whose first event has file index ``index``; returns the kept events."""
        path = self.path
        t = times_to_int64(np.asarray(t), path, index)
        if int(t.min()) < 0:
            i = int(np.argmax(t < 0))
            raise EventFileError(path, None, f"negative timestamp {int(t[i])} us at event {index + i}")
        back = np.flatnonzero(t[1:] < t[:-1])
        if t_prev is not None and int(t[0]) < t_prev:
            back = np.concatenate(([-1], back))
        if back.size:
            i = int(back[0]) + 1
            before = t_prev if i == 0 else int(t[i - 1])
            raise EventFileError(path, None, f"timestamps are not sorted: event {index + i} at t={int(t[i])} us "
                                             f"follows t={before} us (pass sort=True to sort)")
        p = np.asarray(p)
        if p.dtype != np.bool_:
            if p.dtype.kind not in "iu":
                raise EventFileError(path, None, f"polarity must be integer or bool, got dtype {p.dtype}")
            bad = (p < -1) | (p > 1)
            if bad.any():
                i = int(np.argmax(bad))
                raise EventFileError(path, None, f"polarity {int(p[i])} at event {index + i}; expected "
                                                 "{0, 1}, {-1, 1} or bool")
        keep = None
        for name, f, size in (("x", np.asarray(x), self.width), ("y", np.asarray(y), self.height)):
            if f.dtype.kind not in "iu":
                raise EventFileError(path, None, f"pixel {name} must be integer, got dtype {f.dtype}")
            limit = min(size, 1 << 15) if size is not None else 1 << 15
            bad = (f < 0) | (f >= limit)
            if not bad.any():
                continue
            if self.drop_out_of_bounds and size is not None:
                keep = ~bad if keep is None else keep & ~bad
                continue
            i = int(np.argmax(bad))
            what = f"sensor {name}-size is {size}" if size is not None else "pixels must be in [0, 32767]"
            hint = "; pass drop_out_of_bounds=True to drop such events" if size is not None else ""
            raise EventFileError(path, None, f"pixel out of bounds: event {index + i} has {name}={int(f[i])}, "
                                             f"{what}{hint}")
        out = (np.asarray(x), np.asarray(y), t, p)
        return out if keep is None else tuple(f[keep] for f in out)

    def summary(self) -> dict:
        """Stream the file once: format, count, time span (us), rate, sensor size, pixel ranges, ON share."""
        n = n_on = 0
        t_first = t_last = None
        lo = np.array([np.iinfo(np.int64).max] * 2)
        hi = np.array([-1, -1])
        for ev in self:
            if t_first is None:
                t_first = int(ev.t[0])
            t_last = int(ev.t[-1])
            n += len(ev)
            n_on += int(ev.p.sum())
            lo = np.minimum(lo, [int(ev.x.min()), int(ev.y.min())])
            hi = np.maximum(hi, [int(ev.x.max()), int(ev.y.max())])
        duration = ((t_last - t_first) / 1e6) if n else 0.0
        return {
            "path": str(self.path),
            "format": self.format,
            "events": n,
            "t_first_us": t_first if n else 0,
            "t_last_us": t_last if n else 0,
            "duration_s": duration,
            "events_per_s": n / duration if duration > 0 else 0.0,
            "width": self.width,
            "height": self.height,
            "x_range": [int(lo[0]), int(hi[0])] if n else None,
            "y_range": [int(lo[1]), int(hi[1])] if n else None,
            "on_fraction": n_on / n if n else 0.0,
        }


def _sorted_all(blocks: Iterable[tuple[np.ndarray, ...]]) -> tuple[np.ndarray, ...]:
    blocks = list(blocks)
    if not blocks:
        return tuple(np.zeros(0, np.int64) for _ in range(4))
    cat = [np.concatenate(f) for f in zip(*blocks)]
    order = np.argsort(cat[2], kind="stable")
    return tuple(f[order] for f in cat)


def _stream(x, y, t, p) -> EventStream:
    return EventStream(torch.from_numpy(x.astype(np.int16)), torch.from_numpy(y.astype(np.int16)),
                       torch.from_numpy(np.ascontiguousarray(t, dtype=np.int64)),
                       torch.from_numpy((p > 0).astype(np.int8)))


def open_events(path: str | Path, format: str | None = None, **kwargs) -> EventFile:
    """Open an event file for streamed reading; see :class:`EventFile` for the arguments."""
    return EventFile(path, format, **kwargs)


def iter_events(path: str | Path, format: str | None = None, chunk_events: int = 1_000_000,
                **opts) -> Iterator[EventStream]:
    """Yield validated, time-sorted chunks of ``chunk_events`` events (see :class:`EventFile`)."""
    return iter(EventFile(path, format, chunk_events=chunk_events, **opts))


def read_events(path: str | Path, format: str | None = None, **opts) -> EventStream:
    """Read a whole event file into one :class:`EventStream` (see :class:`EventFile`)."""
    return EventStream.concat(list(EventFile(path, format, **opts)))


def write_events(path: str | Path, events: EventStream | Iterable[EventStream], format: str | None = None,
                 **opts) -> int:
    """Write events (one stream or an iterable of time-ordered chunks) and return the count written.

    Args:
        path: output file, replaced only once every chunk is written (on an error it stays as it was).
        events: an :class:`EventStream` or any iterable of them (streamed: nothing is accumulated).
        format: one of ``WRITABLE``; default from the extension (``.h5``/``.hdf5``, ``.npz``,
            ``.txt``/``.csv``).
        **opts: ``width``/``height`` (checked, and stored by events_h5 and npz); events_h5:
            ``compression``; npz: ``compress``; text: ``time_unit`` (``"us"`` or ``"s"``).
    """
    path = Path(path)
    if format is None:
        format = _EXTENSIONS.get(path.suffix.lower())
        if format not in _WRITERS:
            raise ValueError(f"cannot tell the output format from {path.name!r}; pass format= one of "
                             f"{', '.join(WRITABLE)}")
    if format not in _WRITERS:
        raise ValueError(f"format {format!r} cannot be written; writable formats: {', '.join(WRITABLE)}")
    if isinstance(events, EventStream):
        events = [events]
    width, height = opts.get("width"), opts.get("height")
    module, cls = _WRITERS[format]
    n = 0
    t_last: int | None = None
    with getattr(importlib.import_module(module), cls)(path, **opts) as writer:
        for chunk in events:
            if not isinstance(chunk, EventStream):
                raise TypeError(f"write_events expects EventStream chunks, got {type(chunk).__name__}")
            if len(chunk) == 0:
                continue
            chunk.validate(width, height)
            if t_last is not None and int(chunk.t[0]) < t_last:
                raise ValueError(f"chunk starting at event {n} (t={int(chunk.t[0])} us) precedes the previous "
                                 f"chunk's last event (t={t_last} us)")
            writer.append(chunk)
            n += len(chunk)
            t_last = int(chunk.t[-1])
    return n
