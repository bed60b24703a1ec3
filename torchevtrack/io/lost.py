"""The lost flags of a tracked trajectory, in a side file beside its pose file.

``torchevtrack track --recover`` (or any run with ``loss.enabled``) writes, beside the TUM pose file ``OUT``, the file
:func:`lost_path` ``(OUT)`` (``poses.txt`` -> ``poses.lost.txt``): one line per pose of ``OUT``, in the same order and
with the same time, ``t lost`` (``t`` in seconds as in the TUM file, ``lost`` 1 when the tracker held the object lost
after that update, else 0); ``#`` starts a comment. The TUM file stays a plain TUM file. While an element is lost its
pose line holds the tracker's own estimate (:mod:`torchevtrack.recover`).

Example:
    >>> import tempfile, torch
    >>> from torchevtrack.io.lost import lost_path, read_lost, write_lost
    >>> path = lost_path(tempfile.mkdtemp() + "/poses.txt")
    >>> path.name
    'poses.lost.txt'
    >>> write_lost(path, torch.tensor([2000, 4000]), torch.tensor([False, True]))
    >>> read_lost(path)[1].tolist()
    [False, True]
"""

from __future__ import annotations

from pathlib import Path

import torch

from torchevtrack.io.atomic import write_text

__all__ = ["lost_beside", "lost_path", "read_lost", "write_lost"]


def lost_path(pose_path: str | Path) -> Path:
    """The side file of the pose file ``pose_path``: its suffix replaced by ``.lost.txt`` (added if it has none)."""
    p = Path(pose_path)
    return p.with_name(p.stem + ".lost.txt") if p.suffix else p.with_name(p.name + ".lost.txt")


def write_lost(path: str | Path, t_us: torch.Tensor, lost: torch.Tensor) -> None:
    """Write ``t lost`` lines: ``t_us`` ``(N,)`` int64 microseconds, ``lost`` ``(N,)`` bool (atomic replace)."""
    t_us, lost = torch.as_tensor(t_us), torch.as_tensor(lost)
    if t_us.ndim != 1 or lost.shape != t_us.shape or lost.dtype != torch.bool or t_us.is_floating_point():
        raise ValueError(f"expected t_us (N,) integer microseconds and lost (N,) bool, got {t_us.dtype} "
                         f"{tuple(t_us.shape)} and {lost.dtype} {tuple(lost.shape)}")
    lines = ["# t lost (1: the tracker held the object lost after this update; one line per pose of the pose file)"]
    lines += [f"{'-' if t < 0 else ''}{abs(t) // 1_000_000}.{abs(t) % 1_000_000:06d} {int(f)}"
              for t, f in zip(t_us.tolist(), lost.tolist())]
    write_text(path, "\n".join(lines) + "\n")


def read_lost(path: str | Path) -> tuple[torch.Tensor, torch.Tensor]:
    """Read a lost-flag file: ``t_us`` ``(N,)`` int64 and ``lost`` ``(N,)`` bool. Raises ``ValueError`` with the line
    on a malformed one."""
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"lost-flag file not found: {path}")
    t, flags = [], []
    for lineno, raw in enumerate(path.read_text().splitlines(), start=1):
        line = raw.split("#", 1)[0].strip()
        if not line:
            continue
        fields = line.split()
        if len(fields) != 2 or fields[1] not in ("0", "1"):
            raise ValueError(f"{path}:{lineno}: expected 't lost' (seconds, 0 or 1), got {line!r}")
        try:
            t.append(round(float(fields[0]) * 1e6))
        except ValueError:
            raise ValueError(f"{path}:{lineno}: expected 't lost' (seconds, 0 or 1), got {line!r}") from None
        flags.append(fields[1] == "1")
    return torch.tensor(t, dtype=torch.int64), torch.tensor(flags, dtype=torch.bool)


def lost_beside(pose_path: str | Path, t_us: torch.Tensor, retime=None) -> torch.Tensor | None:
    """The lost flags ``(N,)`` bool of the pose file ``pose_path`` read from its side file (:func:`lost_path`), or
    ``None`` when it has none. ``t_us`` ``(N,)``: the pose file's times as the caller holds them, after ``retime``
    (a function of the side file's ``(N,)`` int64 us, e.g. a unit change; default none); raises ``ValueError`` (one
    line) when the side file's times are not those."""
    side = lost_path(pose_path)
    if not side.is_file():
        return None
    lost_t, lost = read_lost(side)
    if not torch.equal(lost_t if retime is None else retime(lost_t), torch.as_tensor(t_us)):
        raise ValueError(f"{side}: its times are not those of {pose_path} (one line per pose, same order)")
    return lost
