"""Writing files so that a failure never loses data: every writer of the package writes to a hidden
temporary file in the destination's directory and renames it over the destination only when the write
succeeded (``os.replace``: atomic on POSIX). A failing input, an exception or a killed process leaves an
existing file as it was (a killed process may leave a hidden ``.NAME.*.tmp.EXT`` file beside it).

Example:
    >>> import os, tempfile
    >>> d = tempfile.mkdtemp()
    >>> write_text(os.path.join(d, "a.txt"), "one\\n")
    >>> try:
    ...     with replacing(os.path.join(d, "a.txt")) as tmp:
    ...         _ = tmp.write_text("half")
    ...         raise RuntimeError("input failed")
    ... except RuntimeError:
    ...     pass
    >>> open(os.path.join(d, "a.txt")).read(), sorted(os.listdir(d))
    ('one\\n', ['a.txt'])
"""

from __future__ import annotations

import os
import tempfile
from pathlib import Path
from typing import IO, TypeVar

__all__ = ["ReplacingWriter", "replacing", "write_text"]

_W = TypeVar("_W", bound="ReplacingWriter")


class replacing:
    """A temporary path ``tmp`` beside ``path``: :meth:`commit` replaces ``path`` with it (synced to disk first,
    with ``path``'s permissions if it exists), :meth:`discard` deletes it and leaves ``path`` untouched. As a
    context manager it yields ``tmp`` and commits on a normal exit, discards on an exception. Raises
    ``ValueError`` if ``path`` is a directory (before anything is written)."""

    def __init__(self, path: str | Path) -> None:
        self.path = Path(path)
        if self.path.is_dir():
            raise ValueError(f"{self.path} is a directory: give a file name")
        # the same extension at the end: writers that choose the format by it (images, videos, meshes) still can
        fd, name = tempfile.mkstemp(prefix=f".{self.path.name}.", suffix=f".tmp{self.path.suffix}", dir=self.path.parent)
        os.close(fd)
        self.tmp = Path(name)

    def commit(self) -> None:
        try:
            with open(self.tmp, "rb+") as f:
                os.fsync(f.fileno())
            if self.path.exists():
                os.chmod(self.tmp, self.path.stat().st_mode & 0o7777)
            else:  # mkstemp makes it 0600: give it the permissions of a newly created file
                umask = os.umask(0)
                os.umask(umask)
                os.chmod(self.tmp, 0o666 & ~umask)
            os.replace(self.tmp, self.path)
        except BaseException:
            self.discard()
            raise

    def discard(self) -> None:
        self.tmp.unlink(missing_ok=True)

    def __enter__(self) -> Path:
        return self.tmp

    def __exit__(self, typ, exc, tb) -> None:
        if typ is None:
            self.commit()
        else:
            self.discard()


class ReplacingWriter:
    """Base of the streaming writers: a subclass writes the open file ``self._f`` at the temporary path of
    ``self._out`` (a :class:`replacing` of its destination). :meth:`close` finishes the file and replaces the
    destination with it; :meth:`discard` drops it. As a context manager it closes on a normal exit and discards
    on an exception, so a writer that fails mid-way leaves the destination as it was. A writer that stages its
    data elsewhere overrides both methods."""

    _f: IO
    _out: replacing

    def close(self) -> None:
        """Finish the file: it replaces ``path`` now."""
        self._f.close()
        self._out.commit()

    def discard(self) -> None:
        """Drop what was written: ``path`` stays as it was."""
        self._f.close()
        self._out.discard()

    def __enter__(self: _W) -> _W:
        return self

    def __exit__(self, typ, exc, tb) -> None:
        if typ is None:
            self.close()
        else:
            self.discard()


def write_text(path: str | Path, text: str) -> None:
    """``Path(path).write_text(text)`` through :func:`replacing`."""
    with replacing(path) as tmp:
        tmp.write_text(text)
