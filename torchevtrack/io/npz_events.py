"""Events in numpy ``.npz`` archives: 1-D arrays ``x``, ``y``, ``t`` (integer microseconds), ``p``.

Optional 0-d arrays ``width`` and ``height`` give the sensor size. Reading streams each array from
its archive member (stored or deflated) without loading it; writing streams chunks to temporary
files beside the output and assembles the archive at close, so neither side holds all events.
"""

from __future__ import annotations

import shutil
import tempfile
import zipfile
import zlib
from pathlib import Path
from typing import Iterator

import numpy as np

from torchevtrack.events import EventStream
from torchevtrack.io.atomic import ReplacingWriter, replacing
from torchevtrack.io.formats import EventFileError

__all__ = ["NpzReader", "NpzWriter"]

_FIELDS = ("x", "y", "t", "p")
_DTYPES = {"x": np.int16, "y": np.int16, "t": np.int64, "p": np.int8}


def _read_header(member, path: Path, name: str) -> tuple[tuple[int, ...], bool, np.dtype]:
    try:
        version = np.lib.format.read_magic(member)
        if version == (1, 0):
            return np.lib.format.read_array_header_1_0(member)
        if version == (2, 0):
            return np.lib.format.read_array_header_2_0(member)
    except ValueError as e:
        raise EventFileError(path, None, f"member {name}.npy is not a valid .npy array ({e})") from None
    raise EventFileError(path, None, f"member {name}.npy has unsupported .npy version {version}")


class NpzReader:
    """Streamed reader of ``.npz`` event archives."""

    def __init__(self, path: Path) -> None:
        self.path = path
        try:
            with zipfile.ZipFile(path) as z:
                names = set(z.namelist())
                missing = [k for k in _FIELDS if f"{k}.npy" not in names]
                if missing:
                    raise EventFileError(path, None, f"npz archive lacks array(s) {missing}; expected x, y, t, p")
                shapes = {}
                for k in _FIELDS:
                    with z.open(f"{k}.npy") as m:
                        shape, fortran, dtype = _read_header(m, path, k)
                    if len(shape) != 1 or dtype.kind not in ("b" if k == "p" else "") + "iu":
                        raise EventFileError(path, None, f"array {k!r} must be 1-D integer, got shape {shape} "
                                                         f"dtype {dtype}")
                    shapes[k] = shape[0]
                size = {}
                for k in ("width", "height"):
                    size[k] = None
                    if f"{k}.npy" in names:
                        with z.open(f"{k}.npy") as m:
                            size[k] = int(np.lib.format.read_array(m))
        except (zipfile.BadZipFile, zlib.error, EOFError) as e:
            raise EventFileError(path, None, f"not a readable npz (zip) archive: {e}") from None
        if len(set(shapes.values())) != 1:
            raise EventFileError(path, None, f"arrays x, y, t, p differ in length: {shapes}")
        self.n = shapes["t"]
        self.width, self.height = size["width"], size["height"]
        self._size = path.stat().st_size
        self.bytes_read: int | None = 0

    def chunks(self, n: int) -> Iterator[tuple[np.ndarray, ...]]:
        self.bytes_read = 0
        try:
            with zipfile.ZipFile(self.path) as z:
                members = {k: z.open(f"{k}.npy") for k in _FIELDS}
                dtypes = {k: _read_header(m, self.path, k)[2] for k, m in members.items()}
                for i in range(0, self.n, n):
                    m = min(n, self.n - i)
                    out = []
                    for k in _FIELDS:
                        buf = members[k].read(m * dtypes[k].itemsize)
                        if len(buf) != m * dtypes[k].itemsize:
                            raise EventFileError(self.path, None, f"array {k!r} is truncated at element "
                                                                  f"{i + len(buf) // dtypes[k].itemsize}")
                        out.append(np.frombuffer(buf, dtype=dtypes[k]))
                    self.bytes_read = self._size * (i + m) // self.n
                    yield tuple(out)
                for member in members.values():
                    member.read()  # the member checks its CRC once read to the end
                    member.close()
        except (zipfile.BadZipFile, zlib.error, EOFError) as e:
            raise EventFileError(self.path, None, f"corrupt npz archive: {e}") from None


class NpzWriter(ReplacingWriter):
    """Write events to an ``.npz`` archive (context manager; ``append`` time-ordered chunks).

    Args:
        path: output file, replaced at a successful close (on an error it stays as it was).
        width, height: optional sensor size, stored as 0-d arrays.
        compress: deflate the members (like ``numpy.savez_compressed``).
    """

    def __init__(self, path: str | Path, *, width: int | None = None, height: int | None = None,
                 compress: bool = False) -> None:
        self.path = Path(path)
        self.size = {"width": width, "height": height}
        self.compress = compress
        self._tmp = tempfile.TemporaryDirectory(dir=self.path.parent, prefix=".npz-")
        self._files = {k: open(Path(self._tmp.name) / k, "wb") for k in _FIELDS}
        self._n = 0

    def append(self, events: EventStream) -> None:
        for k in _FIELDS:
            self._files[k].write(getattr(events, k).numpy().astype(_DTYPES[k]).tobytes())
        self._n += len(events)

    def close(self) -> None:
        """Write the archive from the staged members: it replaces ``path`` now."""
        for f in self._files.values():
            f.close()
        try:
            mode = zipfile.ZIP_DEFLATED if self.compress else zipfile.ZIP_STORED
            with replacing(self.path) as tmp, zipfile.ZipFile(tmp, "w", compression=mode) as z:
                for k in _FIELDS:
                    with z.open(f"{k}.npy", "w", force_zip64=True) as m:
                        header = {"descr": np.lib.format.dtype_to_descr(np.dtype(_DTYPES[k])),
                                  "fortran_order": False, "shape": (self._n,)}
                        np.lib.format.write_array_header_1_0(m, header)
                        with open(Path(self._tmp.name) / k, "rb") as src:
                            shutil.copyfileobj(src, m, 1 << 22)
                for k, v in self.size.items():
                    if v is not None:
                        with z.open(f"{k}.npy", "w") as m:
                            np.lib.format.write_array(m, np.asarray(int(v), dtype=np.int64))
        finally:
            self._tmp.cleanup()

    def discard(self) -> None:
        """Drop the staged members: ``path`` stays as it was."""
        for f in self._files.values():
            f.close()
        self._tmp.cleanup()
