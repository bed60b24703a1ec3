"""Pose trajectory files.

In memory a trajectory is ``(t_us, poses)``: int64 microseconds ``(N,)`` and float64 poses ``(N, 7)``
in the package convention ``[tx, ty, tz, qw, qx, qy, qz]`` (object in camera frame, metres).
Files use their own layouts and are converted here, at the boundary.

TUM text: one pose a line, ``t tx ty tz qx qy qz qw`` with ``t`` in seconds; ``#`` starts a comment.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import torch

from torchevtrack.geometry import quat_canonical

__all__ = ["read_tum", "write_tum"]


def _seconds_to_us(seconds: np.ndarray) -> torch.Tensor:
    return torch.from_numpy(np.round(seconds * 1e6).astype(np.int64))


def read_tum(path: str | Path) -> tuple[torch.Tensor, torch.Tensor]:
    """Read a TUM trajectory. Returns ``t_us (N,) int64`` and ``poses (N, 7) float64``."""
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"pose file not found: {path}")
    rows = []
    for lineno, line in enumerate(path.read_text().splitlines(), start=1):
        line = line.split("#", 1)[0].strip()
        if not line:
            continue
        fields = line.replace(",", " ").split()
        if len(fields) != 8:
            raise ValueError(f"{path}:{lineno}: expected 8 values 't tx ty tz qx qy qz qw', got {len(fields)}")
        try:
            rows.append([float(f) for f in fields])
        except ValueError:
            raise ValueError(f"{path}:{lineno}: not a number in {line!r}") from None
    a = np.asarray(rows, dtype=np.float64).reshape(-1, 8)
    if not np.isfinite(a).all():
        raise ValueError(f"{path}: NaN or infinite values")
    t_us = _seconds_to_us(a[:, 0])
    if (t_us[1:] < t_us[:-1]).any():
        raise ValueError(f"{path}: timestamps are not sorted")
    q = torch.from_numpy(a[:, [7, 4, 5, 6]])
    if ((q.norm(dim=-1) - 1).abs() > 1e-3).any():
        raise ValueError(f"{path}: quaternions are not unit norm")
    return t_us, torch.cat((torch.from_numpy(a[:, 1:4]), quat_canonical(q)), dim=-1)


def write_tum(path: str | Path, t_us: torch.Tensor, poses: torch.Tensor) -> None:
    """Write a TUM trajectory (seconds with microsecond resolution, 9 decimals for poses)."""
    t_us = torch.as_tensor(t_us)
    poses = torch.as_tensor(poses, dtype=torch.float64)
    if t_us.ndim != 1 or poses.shape != (t_us.shape[0], 7):
        raise ValueError(f"expected t (N,) and poses (N, 7), got {tuple(t_us.shape)} and {tuple(poses.shape)}")
    p = poses.numpy()
    lines = ["# t tx ty tz qx qy qz qw (object in camera frame, OpenCV axes, metres)"]
    for ti, row in zip(t_us.tolist(), p):
        tx, ty, tz, qw, qx, qy, qz = row
        lines.append(
            f"{ti // 1_000_000}.{ti % 1_000_000:06d} {tx:.9f} {ty:.9f} {tz:.9f} {qx:.9f} {qy:.9f} {qz:.9f} {qw:.9f}"
        )
    Path(path).write_text("\n".join(lines) + "\n")
