"""Readers of event files written by other tools: DSEC HDF5, AEDAT4, EVT3, YARP (EDOPT) and YCB-Ev.

Each reader yields numpy ``(x, y, t, p)`` blocks in file order (``t`` int64 microseconds); the
front end :mod:`torchevtrack.io.formats` validates and re-chunks them.

* DSEC HDF5: datasets ``events/x``, ``events/y``, ``events/t``, ``events/p``; optional scalar
  ``t_offset`` (microseconds, ``t_us = t + t_offset``). ``ms_to_idx`` is not needed for streaming.
* AEDAT4 (iniVation): decoded by the ``aedat`` package; one event stream (``stream_id`` picks one
  when the file has several). Timestamps are absolute microseconds.
* EVT3 (Prophesee ``.raw``): decoded by the ``evt3`` package after checking the ``%`` header declares
  EVT 3.0. The sensor size comes from the header.
* YARP, as in the event-driven library and the EDOPT datasets. Every event is two little-endian
  32-bit words: a timestamp word (counter in bits 0-30, ``clock_period_ns`` per tick, 80 ns by
  default as written by bimvee's ``encodeEvents24Bit``; the counter wraps every ``2**timer_bits``
  ticks and is unwrapped) and an address word ``ev::AE``: bit 0 polarity, bits 1-10 ``x``, bits
  12-20 ``y``, bit 21 corner flag, bit 22 channel (stereo left 0 / right 1), bits 23-31 zero for
  vision events (others, e.g. IMU samples, are skipped). ``binaryevents.log`` (format ``yarp``) is
  the bare word pairs; ``data.log`` (format ``yarp_text``) holds one bottle a line,
  ``<count> <seconds> AE (<ts> <ae> <ts> <ae> ...)`` with decimal words; other bottles are skipped.
  bimvee's encoder stores the complement of the polarity: ``invert_polarity=True`` undoes it.
* YCB-Ev: a zstd stream (one or more frames) of int32 pairs ``[t_us, x | y << 14 | p << 28]``.
"""

from __future__ import annotations

import re
from pathlib import Path
from typing import Iterator

import numpy as np

from torchevtrack.io.formats import (ZSTD_MAGIC, EventFileError, head_lines, open_hdf5, require,
                                     times_to_int64)

__all__ = ["DsecReader", "Aedat4Reader", "Evt3Reader", "YarpReader", "YarpTextReader", "YcbEvReader",
           "looks_like_yarp_text"]

_I64_MAX = np.iinfo(np.int64).max


class DsecReader:
    """DSEC-style HDF5 events (``events/{x,y,t,p}``, optional ``t_offset``), read in slices."""

    def __init__(self, path: Path) -> None:
        self.path = path
        with open_hdf5(path) as f:
            if "events" not in f or not all(k in f["events"] for k in "xytp"):
                raise EventFileError(path, None, "no events/x, events/y, events/t, events/p datasets")
            shapes = {k: f["events"][k].shape for k in "xytp"}
            for k in "xytp":
                d = f["events"][k]
                if d.ndim != 1 or d.dtype.kind not in ("b" if k == "p" else "") + "iu":
                    raise EventFileError(path, None, f"events/{k} must be 1-D integer, got shape {d.shape} "
                                                     f"dtype {d.dtype}")
            if len(set(shapes.values())) != 1:
                raise EventFileError(path, None, f"events/x, y, t, p differ in length: {shapes}")
            self.t_offset = 0
            if "t_offset" in f:
                off = np.asarray(f["t_offset"][()])
                if off.ndim != 0 or off.dtype.kind not in "iu":
                    raise EventFileError(path, None, f"t_offset must be an integer scalar, got {off!r}")
                self.t_offset = int(off)
        self.n = shapes["t"][0]
        self.width = self.height = None
        self._size = path.stat().st_size
        self.bytes_read: int | None = 0

    def chunks(self, n: int) -> Iterator[tuple[np.ndarray, ...]]:
        import h5py

        n = max(n, 1 << 16)  # slicing compressed HDF5 datasets finely re-inflates their chunks
        with h5py.File(self.path, "r") as f:
            ev = f["events"]
            for i in range(0, self.n, n):
                j = min(i + n, self.n)
                t = times_to_int64(ev["t"][i:j], self.path, i)
                if t.size and int(t.max()) > _I64_MAX - max(self.t_offset, 0):
                    raise EventFileError(self.path, None, f"t + t_offset overflows int64 in events {i}..{j - 1}")
                self.bytes_read = self._size * j // max(self.n, 1)
                yield ev["x"][i:j], ev["y"][i:j], t + self.t_offset, ev["p"][i:j]


class Aedat4Reader:
    """iniVation AEDAT 4.0 through the ``aedat`` package (polarity events of one stream)."""

    def __init__(self, path: Path, *, stream_id: int | None = None) -> None:
        self._aedat = require("aedat", "aedat4")
        self.path = path
        with open(path, "rb") as f:
            head = f.read(14)
        if not head.startswith(b"#!AER-DAT4"):
            raise EventFileError(path, 0, f"not an AEDAT 4 file (first bytes {head!r})")
        streams = {k: v for k, v in self._decoder().id_to_stream().items() if v.get("type") == "events"}
        if stream_id is None:
            if len(streams) != 1:
                raise EventFileError(path, None, f"{len(streams)} event streams {sorted(streams)}; pass stream_id")
            stream_id = next(iter(streams))
        if stream_id not in streams:
            raise EventFileError(path, None, f"no event stream {stream_id}; event streams: {sorted(streams)}")
        self.stream_id = stream_id
        self.width, self.height = streams[stream_id].get("width"), streams[stream_id].get("height")
        self.bytes_read: int | None = None

    def _decoder(self):
        try:
            return self._aedat.Decoder(str(self.path))
        except RuntimeError as e:
            raise EventFileError(self.path, None, f"AEDAT4 decoding failed: {e}") from None

    def chunks(self, n: int) -> Iterator[tuple[np.ndarray, ...]]:
        parts, count, index = [], 0, 0
        try:
            for packet in self._decoder():
                if packet["stream_id"] != self.stream_id or "events" not in packet:
                    continue
                ev = packet["events"]
                parts.append((ev["x"], ev["y"], times_to_int64(ev["t"], self.path, index + count), ev["on"]))
                count += len(ev)
                if count >= n:
                    yield tuple(np.concatenate(f) for f in zip(*parts))
                    parts, index, count = [], index + count, 0
        except RuntimeError as e:
            raise EventFileError(self.path, None, f"AEDAT4 decoding failed after {index + count} events: {e}") \
                from None
        if parts:
            yield tuple(np.concatenate(f) for f in zip(*parts))


class Evt3Reader:
    """Prophesee EVT 3.0 ``.raw`` through the ``evt3`` package."""

    def __init__(self, path: Path) -> None:
        self._evt3 = require("evt3", "evt3")
        self.path = path
        with open(path, "rb") as f:
            head = f.read(1 << 16)
        if not head.startswith(b"%"):
            raise EventFileError(path, 0, f"not an EVT 3.0 raw file: no '%' header (first bytes {head[:8]!r})")
        header = b"\n".join(ln for ln in head.split(b"\n") if ln.startswith(b"%")).decode("ascii", "replace")
        low = header.lower()
        if "evt 3.0" not in low and "format evt3" not in low:
            version = re.search(r"evt ?(\d(?:\.\d)?)", low)
            what = f"EVT {version.group(1)}" if version else "no EVT 3.0 declaration"
            raise EventFileError(path, 0, f"unsupported raw encoding ({what}); only EVT 3.0 is read")
        try:
            self.width, self.height = self._evt3.decode_file_batches(str(path)).sensor_size
        except OSError as e:
            raise EventFileError(path, None, f"EVT3 decoding failed: {e}") from None
        self._size = path.stat().st_size
        self.bytes_read: int | None = 0

    def chunks(self, n: int) -> Iterator[tuple[np.ndarray, ...]]:
        batch = max(1 << 16, 2 * n)
        index = 0
        self.bytes_read = 0
        try:
            for k, ev in enumerate(self._evt3.decode_file_batches(str(self.path), batch_bytes=batch)):
                self.bytes_read = min(self._size, (k + 1) * batch)
                yield ev.x, ev.y, times_to_int64(ev.t, self.path, index), ev.p
                index += len(ev)
        except OSError as e:
            raise EventFileError(self.path, None, f"EVT3 decoding failed after {index} events: {e}") from None
        self.bytes_read = self._size


class _YarpDecoder:
    """Stateful decoding of ``(ts, ae)`` word pairs with timestamp unwrapping across blocks."""

    def __init__(self, clock_period_ns: float, timer_bits: int, channel: int | None, invert_polarity: bool):
        if clock_period_ns <= 0:
            raise ValueError(f"clock_period_ns must be positive, got {clock_period_ns}")
        if not 1 <= timer_bits <= 31:
            raise ValueError(f"timer_bits must be in 1..31, got {timer_bits}")
        if channel not in (None, 0, 1):
            raise ValueError(f"channel must be 0, 1 or None (both), got {channel!r}")
        self.period_ps = round(clock_period_ns * 1000)
        self.bits = timer_bits
        self.channel = channel
        self.invert = invert_polarity
        self.last: int | None = None
        self.wraps = 0

    def __call__(self, words: np.ndarray) -> tuple[np.ndarray, ...]:
        if not len(words):
            return tuple(np.zeros(0, np.int64) for _ in range(4))
        ts = (words[:, 0] & np.uint32((1 << self.bits) - 1)).astype(np.int64)
        ae = words[:, 1]
        prev = np.concatenate(([ts[0] if self.last is None else self.last], ts[:-1]))
        wrapped = np.cumsum(ts - prev < -(1 << (self.bits - 1))) + self.wraps
        self.last, self.wraps = int(ts[-1]), int(wrapped[-1])
        ticks = ts + wrapped * (1 << self.bits)
        t = (ticks * self.period_ps + 500_000) // 1_000_000  # nearest microsecond
        keep = (ae & np.uint32(0xFF800000)) == 0
        if self.channel is not None:
            keep &= ((ae >> np.uint32(22)) & np.uint32(1)) == self.channel
        ae, t = ae[keep], t[keep]
        p = (ae & np.uint32(1)).astype(np.int8)
        if self.invert:
            p = 1 - p
        x = ((ae >> np.uint32(1)) & np.uint32(0x3FF)).astype(np.int64)
        y = ((ae >> np.uint32(12)) & np.uint32(0x1FF)).astype(np.int64)
        return x, y, t, p


class YarpReader:
    """EDOPT/event-driven ``binaryevents.log``: little-endian uint32 pairs ``(ts, ae)``."""

    def __init__(self, path: Path, *, clock_period_ns: float = 80.0, timer_bits: int = 31,
                 channel: int | None = None, invert_polarity: bool = False) -> None:
        self.path = path
        self._opts = (clock_period_ns, timer_bits, channel, invert_polarity)
        _YarpDecoder(*self._opts)  # check the options now
        self._size = path.stat().st_size
        if self._size % 8:
            raise EventFileError(path, self._size - self._size % 8,
                                 f"truncated: {self._size % 8} trailing byte(s) after the last 8-byte event")
        self.width = self.height = None
        self.bytes_read: int | None = 0

    def chunks(self, n: int) -> Iterator[tuple[np.ndarray, ...]]:
        decode = _YarpDecoder(*self._opts)
        self.bytes_read = 0
        with open(self.path, "rb") as f:
            while True:
                offset = f.tell()
                buf = f.read(8 * n)
                if not buf:
                    return
                if len(buf) % 8:
                    raise EventFileError(self.path, offset + len(buf) - len(buf) % 8, "truncated event (file changed?)")
                self.bytes_read = offset + len(buf)
                yield decode(np.frombuffer(buf, dtype="<u4").reshape(-1, 2))


_BOTTLE = re.compile(rb"^\s*(\d+)\s+([-+0-9.eE]+)\s+([A-Za-z_]\w*)\s+\((.*)\)\s*$")


def looks_like_yarp_text(path: Path) -> bool:
    """True if the first non-empty line of ``path`` (within 64 KiB) is a YARP bottle ``N T TAG (...)``."""
    lines = [ln for ln in head_lines(path) if ln.strip()]
    return bool(lines) and _BOTTLE.match(lines[0]) is not None


class YarpTextReader:
    """YARP ``data.log``: one bottle a line; ``AE`` bottles hold decimal ``(ts, ae)`` word pairs."""

    def __init__(self, path: Path, *, clock_period_ns: float = 80.0, timer_bits: int = 31,
                 channel: int | None = None, invert_polarity: bool = False, tag: str = "AE") -> None:
        self.path = path
        self._opts = (clock_period_ns, timer_bits, channel, invert_polarity)
        _YarpDecoder(*self._opts)
        self.tag = tag.encode()
        self.width = self.height = None
        self.bytes_read: int | None = 0

    def chunks(self, n: int) -> Iterator[tuple[np.ndarray, ...]]:
        decode = _YarpDecoder(*self._opts)
        parts, count, offset = [], 0, 0
        self.bytes_read = 0
        with open(self.path, "rb") as f:
            for line_no, line in enumerate(f, 1):
                start, offset = offset, offset + len(line)
                if not line.strip():
                    continue
                m = _BOTTLE.match(line)
                if m is None:
                    raise EventFileError(self.path, start, f"line {line_no}: not a YARP bottle "
                                                           f"'<count> <time> <TAG> (...)': {line[:60]!r}")
                if m.group(3) != self.tag:
                    continue
                try:
                    words = np.array(m.group(4).split(), dtype=np.int64)
                except ValueError:
                    raise EventFileError(self.path, start, f"line {line_no}: non-integer word in the "
                                                           f"{self.tag.decode()} bottle") from None
                if words.size % 2 or (words.size and (words.min() < 0 or words.max() >= 1 << 32)):
                    raise EventFileError(self.path, start, f"line {line_no}: expected pairs of unsigned 32-bit "
                                                           f"words, got {words.size} value(s)")
                parts.append(words.astype(np.uint32).reshape(-1, 2))
                count += words.size // 2
                if count >= n:
                    self.bytes_read = offset
                    yield decode(np.concatenate(parts))
                    parts, count = [], 0
        self.bytes_read = offset
        if count:
            yield decode(np.concatenate(parts))


class YcbEvReader:
    """YCB-Ev events: zstd-compressed little-endian int32 pairs ``[t_us, x | y << 14 | p << 28]``."""

    def __init__(self, path: Path) -> None:
        self._zstd = require("zstandard", "ycbev")
        self.path = path
        with open(path, "rb") as f:
            head = f.read(4)
        if head != ZSTD_MAGIC:
            raise EventFileError(path, 0, f"not a zstd stream (first bytes {head!r})")
        self.width = self.height = None
        self.bytes_read: int | None = 0

    def chunks(self, n: int) -> Iterator[tuple[np.ndarray, ...]]:
        dctx = self._zstd.ZstdDecompressor()
        dobj, pending = dctx.decompressobj(), False
        buf = bytearray()
        out_offset = 0  # decompressed bytes already decoded
        self.bytes_read = 0
        with open(self.path, "rb") as f:
            while True:
                start = f.tell()
                data = f.read(1 << 20)
                if not data:
                    break
                while data:
                    try:
                        buf += dobj.decompress(data)
                    except self._zstd.ZstdError as e:
                        raise EventFileError(self.path, start, f"corrupt zstd data: {e}") from None
                    pending = not dobj.eof
                    if dobj.eof:  # next frame, if any, starts in unused_data
                        data, dobj = dobj.unused_data, dctx.decompressobj()
                        pending = bool(data)
                    else:
                        data = b""
                self.bytes_read = f.tell()
                while len(buf) >= 8 * n:
                    yield self._decode(bytes(buf[: 8 * n]), out_offset)
                    del buf[: 8 * n]
                    out_offset += 8 * n
        if pending:
            raise EventFileError(self.path, self.bytes_read, "truncated zstd stream (incomplete frame at end)")
        if len(buf) % 8:
            raise EventFileError(self.path, None, f"decompressed data ends with {len(buf) % 8} byte(s) of a "
                                                  f"partial event (after event {(out_offset + len(buf)) // 8})")
        if buf:
            yield self._decode(bytes(buf), out_offset)

    def _decode(self, raw: bytes, out_offset: int) -> tuple[np.ndarray, ...]:
        a = np.frombuffer(raw, dtype="<i4").reshape(-1, 2)
        w = a[:, 1].view("<u4")
        extra = w >> np.uint32(29)
        if extra.any():
            i = int(np.argmax(extra != 0))
            raise EventFileError(self.path, None, f"event {out_offset // 8 + i}: address word 0x{int(w[i]):08x} "
                                                  "has bits above the polarity (bit 28) set")
        x = (w & np.uint32(0x3FFF)).astype(np.int64)
        y = ((w >> np.uint32(14)) & np.uint32(0x3FFF)).astype(np.int64)
        p = ((w >> np.uint32(28)) & np.uint32(1)).astype(np.int8)
        return x, y, a[:, 0].astype(np.int64), p
