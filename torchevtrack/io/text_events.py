"""Plain-text events: one event a line, ``t x y p`` by default, ``#`` starts a comment.

Values are separated by whitespace or commas (detected from the first data line). ``t`` is either
integer microseconds or float seconds: ``time_unit="us"|"s"``, default detected from the first
block of lines (a ``.`` anywhere in it means seconds; a later ``.`` in a microsecond file is an
error asking for ``time_unit``). ``columns`` gives the column order (a permutation of ``"txyp"``,
``_`` for a column to skip, e.g. ``"txyp_"``). Lines are parsed in blocks (``numpy.loadtxt``), so
files larger than memory stream.

The writer writes ``t x y p`` lines with ``t`` in integer microseconds, or exact seconds with six
decimals (``time_unit="s"``), after a ``#`` header.
"""

from __future__ import annotations

import io
import warnings
from itertools import islice
from pathlib import Path
from typing import Iterator

import numpy as np

from torchevtrack.events import EventStream
from torchevtrack.io.atomic import ReplacingWriter, replacing
from torchevtrack.io.formats import EventFileError, head_lines

__all__ = ["TextReader", "TextWriter", "looks_like_text"]

_I64_MAX_S = (2**63 - 1) / 1e6


def looks_like_text(path: Path) -> bool:
    """True if the first data line of ``path`` (within 64 KiB) is 4 or more numbers."""
    for raw in head_lines(path):
        line = raw.split(b"#", 1)[0].strip()
        if line:
            fields = line.replace(b",", b" ").split()
            return len(fields) >= 4 and all(_is_number(v) for v in fields)
    return False


def _is_number(v: bytes) -> bool:
    try:
        float(v)
    except ValueError:
        return False
    return True


class TextReader:
    """Streamed reader of text event files (see the module docstring)."""

    def __init__(self, path: Path, *, time_unit: str | None = None, columns: str = "txyp",
                 delimiter: str | None = None) -> None:
        if time_unit not in (None, "s", "us"):
            raise ValueError(f"time_unit must be 's', 'us' or None (detect), got {time_unit!r}")
        if sorted(columns.replace("_", "")) != sorted("txyp"):
            raise ValueError(f"columns must hold each of t, x, y, p once (and '_' for skipped columns), "
                             f"got {columns!r}")
        if delimiter not in (None, ",", " ", "\t"):
            raise ValueError(f"delimiter must be ',', ' ', '\\t' or None (detect), got {delimiter!r}")
        self.path = path
        self.time_unit = time_unit
        self.columns = columns
        self.delimiter = delimiter
        self.width = self.height = None
        self.bytes_read: int | None = 0

    def chunks(self, n: int) -> Iterator[tuple[np.ndarray, ...]]:
        unit, delimiter = self.time_unit, self.delimiter
        col = {c: i for i, c in enumerate(self.columns) if c != "_"}
        line_no, offset = 0, 0
        self.bytes_read = 0
        with open(self.path, "rb") as f:
            while True:
                lines = list(islice(f, n))
                if not lines:
                    return
                block = b"".join(lines)
                try:
                    text = block.decode("utf-8")
                except UnicodeDecodeError as e:
                    raise EventFileError(self.path, offset + e.start, "not a text file (invalid UTF-8)") from None
                data = "\n".join(ln.split("#", 1)[0] for ln in text.splitlines()) if "#" in text else text
                if delimiter is None and data.strip():
                    first = next(ln for ln in data.splitlines() if ln.strip())
                    delimiter = "," if "," in first else ""
                if unit is None and data.strip():
                    unit = "s" if "." in data else "us"
                if data.strip():
                    rows = self._parse(data, unit, delimiter or None, lines, line_no, offset)
                    if unit == "s":
                        t = self._seconds_to_us(rows, col, lines, line_no, offset)
                        rows = rows.astype(np.int64)
                    else:
                        t = rows[:, col["t"]]
                    yield rows[:, col["x"]], rows[:, col["y"]], t, rows[:, col["p"]]
                line_no += len(lines)
                offset += len(block)
                self.bytes_read = offset

    def _parse(self, data: str, unit: str, delimiter: str | None, lines: list[bytes], line_no: int,
               offset: int) -> np.ndarray:
        dtype = np.float64 if unit == "s" else np.int64
        try:
            with warnings.catch_warnings():
                warnings.simplefilter("ignore")
                rows = np.loadtxt(io.StringIO(data), dtype=dtype, delimiter=delimiter, ndmin=2)
        except ValueError:
            i, why = self._first_bad_line(lines, unit, delimiter)
            hint = " (values are read as integers: pass time_unit='s' for seconds)" if "." in why else ""
            raise EventFileError(self.path, offset + sum(len(ln) for ln in lines[:i]),
                                 f"line {line_no + i + 1}: {why}{hint}") from None
        if rows.shape[1] != len(self.columns):
            i, _ = self._first_bad_line(lines, unit, delimiter)
            raise EventFileError(self.path, offset + sum(len(ln) for ln in lines[:i]),
                                 f"line {line_no + i + 1}: expected {len(self.columns)} values "
                                 f"({self.columns}), got {rows.shape[1]}")
        return rows

    def _first_bad_line(self, lines: list[bytes], unit: str, delimiter: str | None) -> tuple[int, str]:
        """Index in ``lines`` of the first malformed line and why it is malformed."""
        cast = float if unit == "s" else int
        for i, raw in enumerate(lines):
            line = raw.decode("utf-8").split("#", 1)[0].strip()
            if not line:
                continue
            fields = line.split(delimiter) if delimiter else line.split()
            if len(fields) != len(self.columns):
                return i, f"expected {len(self.columns)} values ({self.columns}), got {len(fields)}: {line!r}"
            for v in fields:
                try:
                    cast(v)
                except ValueError:
                    return i, f"cannot read {v.strip()!r} as {'a number' if unit == 's' else 'an integer'}"
        return 0, "unreadable block"

    def _seconds_to_us(self, rows: np.ndarray, col: dict, lines: list[bytes], line_no: int,
                       offset: int) -> np.ndarray:
        """Float seconds to int64 microseconds; x, y, p must be integers."""
        t = rows[:, col["t"]]
        problems = [(~np.isfinite(t) | (np.abs(t) > _I64_MAX_S), "timestamp is not finite or overflows int64 us")]
        problems += [(rows[:, col[c]] != np.round(rows[:, col[c]]), f"{c} is not an integer") for c in "xyp"]
        for bad, why in problems:
            if bad.any():
                row = int(np.argmax(bad))
                i = [k for k, ln in enumerate(lines) if ln.split(b"#", 1)[0].strip()][row]
                raise EventFileError(self.path, offset + sum(len(ln) for ln in lines[:i]),
                                     f"line {line_no + i + 1}: {why}")
        return np.rint(t * 1e6).astype(np.int64)


class TextWriter(ReplacingWriter):
    """Write ``t x y p`` lines (use as a context manager; ``append`` time-ordered chunks).

    Args:
        path: output file, replaced at a successful close (on an error it stays as it was).
        time_unit: ``"us"`` (integer microseconds, default) or ``"s"`` (seconds, six decimals, exact).
        width, height: accepted for symmetry with the other writers (a text file stores no size).
    """

    def __init__(self, path: str | Path, *, time_unit: str = "us", width: int | None = None,
                 height: int | None = None) -> None:
        if time_unit not in ("s", "us"):
            raise ValueError(f"time_unit must be 's' or 'us', got {time_unit!r}")
        self.time_unit = time_unit
        self._out = replacing(path)  # written to a temporary file, renamed over ``path`` at a successful close
        self._f = open(self._out.tmp, "w")
        unit = "seconds" if time_unit == "s" else "microseconds"
        self._f.write(f"# t x y p  (t in {unit}, p in {{0, 1}})\n")

    def append(self, events: EventStream) -> None:
        t = events.t.numpy()
        xyp = [events.x.numpy().astype(np.int64), events.y.numpy().astype(np.int64),
               events.p.numpy().astype(np.int64)]
        if self.time_unit == "s":
            cols, fmt = [t // 1_000_000, t % 1_000_000, *xyp], "%d.%06d %d %d %d\n"
        else:
            cols, fmt = [t, *xyp], "%d %d %d %d\n"
        rows = np.stack(cols, axis=1)
        for i in range(0, len(rows), 100_000):  # one %-format per block: ~6x faster than numpy.savetxt
            block = rows[i:i + 100_000]
            self._f.write((fmt * len(block)) % tuple(block.ravel().tolist()))
