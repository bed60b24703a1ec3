"""Pose trajectory files.

In memory a trajectory is ``(t_us, poses)``: int64 microseconds ``(N,)`` and float64 poses ``(N, 7)``
in the package convention ``[tx, ty, tz, qw, qx, qy, qz]`` (object in camera frame, metres).
Files use their own layouts and are converted here, at the boundary.

* TUM text (``.txt``): one pose a line, ``t tx ty tz qx qy qz qw`` with ``t`` in seconds; ``#`` starts
  a comment.
* CSV (``.csv``, as in the EDOPT datasets): header ``t,x,y,z,qx,qy,qz,qw``, ``t`` in seconds, metres.
  When reading, the header may list these columns in any order (``time``/``timestamp`` also name
  ``t``) or be absent (then the columns are in that order).
* BOP ``scene_gt.json`` (``.json``): ``{"<frame id>": [{"obj_id": k, "cam_R_m2c": [9 floats,
  row-major], "cam_t_m2c": [3 floats, millimetres]}, ...], ...}``. The file holds no times: they come
  from a frame rate (``t = frame_id / fps``) or from explicit per-frame times.

Example:
    >>> import tempfile, torch
    >>> from torchevtrack.io.poses import read_poses, write_poses
    >>> t = torch.tensor([0, 33_333, 66_667])
    >>> p = torch.tensor([[0.0, 0.0, 0.5, 1.0, 0.0, 0.0, 0.0]], dtype=torch.float64).repeat(3, 1)
    >>> path = tempfile.mkdtemp() + "/gt.csv"
    >>> write_poses(path, t, p)
    >>> t2, p2 = read_poses(path)
    >>> bool((t2 == t).all())
    True
"""

from __future__ import annotations

import json
from collections.abc import Mapping, Sequence
from pathlib import Path

import numpy as np
import torch

from torchevtrack.geometry import matrix_to_quat, quat_canonical, quat_to_matrix
from torchevtrack.io.atomic import write_text

__all__ = [
    "read_tum",
    "write_tum",
    "tum_lines",
    "TUM_HEADER",
    "read_csv",
    "write_csv",
    "read_bop_scene_gt",
    "write_bop_scene_gt",
    "read_poses",
    "write_poses",
    "detect_format",
    "FORMATS",
]

FORMATS = ("tum", "csv", "bop")
_EXTENSIONS = {".txt": "tum", ".tum": "tum", ".csv": "csv", ".json": "bop"}
_CSV_COLUMNS = ("t", "x", "y", "z", "qx", "qy", "qz", "qw")
_CSV_ALIASES = {"time": "t", "timestamp": "t", "tx": "x", "ty": "y", "tz": "z"}


def _seconds_to_us(seconds: np.ndarray) -> torch.Tensor:
    return torch.from_numpy(np.round(seconds * 1e6).astype(np.int64))


def _us_to_seconds_str(t_us: int) -> str:
    sign = "-" if t_us < 0 else ""
    a = abs(t_us)
    return f"{sign}{a // 1_000_000}.{a % 1_000_000:06d}"


def _existing(path: str | Path) -> Path:
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"pose file not found: {path}")
    return path


def _check_trajectory(t_us: torch.Tensor, poses: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    t_us = torch.as_tensor(t_us)
    poses = torch.as_tensor(poses, dtype=torch.float64)
    if t_us.dtype not in (torch.int64, torch.int32):
        raise TypeError(f"t_us must be integer microseconds (int64), got {t_us.dtype}")
    if t_us.ndim != 1 or poses.shape != (t_us.shape[0], 7):
        raise ValueError(f"expected t (N,) and poses (N, 7), got {tuple(t_us.shape)} and {tuple(poses.shape)}")
    if not torch.isfinite(poses).all():
        raise ValueError("poses contain NaN or infinite values")
    return t_us.to(torch.int64), poses


def _finish(path: Path, t_us: torch.Tensor, t_xyz: np.ndarray, q_wxyz: np.ndarray) -> tuple[torch.Tensor, torch.Tensor]:
    """Validate parsed rows (finite, sorted, unit quaternions) and build the in-memory trajectory."""
    if not (np.isfinite(t_xyz).all() and np.isfinite(q_wxyz).all()):
        raise ValueError(f"{path}: NaN or infinite values")
    if (t_us[1:] < t_us[:-1]).any():
        k = int((t_us[1:] < t_us[:-1]).nonzero()[0, 0])
        raise ValueError(f"{path}: timestamps are not sorted (pose {k + 2} is earlier than pose {k + 1})")
    q = torch.from_numpy(np.ascontiguousarray(q_wxyz))
    bad = ((q.norm(dim=-1) - 1).abs() > 1e-3).nonzero()
    if bad.numel():
        raise ValueError(f"{path}: quaternion of pose {int(bad[0, 0]) + 1} is not unit norm")
    return t_us, torch.cat((torch.from_numpy(np.ascontiguousarray(t_xyz)), quat_canonical(q)), dim=-1)


def _parse_numbers(path: Path, lineno: int, fields: list[str], line: str) -> list[float]:
    try:
        return [float(f) for f in fields]
    except ValueError:
        raise ValueError(f"{path}:{lineno}: not a number in {line!r}") from None


def _all_numbers(fields: list[str]) -> bool:
    try:
        [float(f) for f in fields]
    except ValueError:
        return False
    return True


def read_tum(path: str | Path) -> tuple[torch.Tensor, torch.Tensor]:
    """Read a TUM trajectory. Returns ``t_us (N,) int64`` and ``poses (N, 7) float64``."""
    path = _existing(path)
    rows = []
    for lineno, line in enumerate(path.read_text().splitlines(), start=1):
        line = line.split("#", 1)[0].strip()
        if not line:
            continue
        fields = line.replace(",", " ").split()
        if len(fields) != 8:
            raise ValueError(f"{path}:{lineno}: expected 8 values 't tx ty tz qx qy qz qw', got {len(fields)}")
        rows.append(_parse_numbers(path, lineno, fields, line))
    a = np.asarray(rows, dtype=np.float64).reshape(-1, 8)
    return _finish(path, _seconds_to_us(a[:, 0]), a[:, 1:4], a[:, [7, 4, 5, 6]])


TUM_HEADER = "# t tx ty tz qx qy qz qw (object in camera frame, OpenCV axes, metres)"


def tum_lines(t_us: torch.Tensor, poses: torch.Tensor) -> list[str]:
    """The TUM lines (no header, no newlines) of ``t_us`` ``(N,)`` int64 us and ``poses`` ``(N, 7)`` (validated):
    seconds with microsecond resolution, 9 decimals for the pose. ``[TUM_HEADER, *lines]`` joined by newlines is
    :func:`write_tum`'s file, so a caller that keeps a growing trajectory formats each pose once.

    Example:
        >>> import torch
        >>> tum_lines(torch.tensor([1500]), torch.tensor([[0.0, 0.0, 0.5, 1.0, 0.0, 0.0, 0.0]]))
        ['0.001500 0.000000000 0.000000000 0.500000000 0.000000000 0.000000000 0.000000000 1.000000000']
    """
    t_us, poses = _check_trajectory(t_us, poses)
    lines = []
    for ti, row in zip(t_us.tolist(), poses.numpy()):
        tx, ty, tz, qw, qx, qy, qz = row
        lines.append(f"{_us_to_seconds_str(ti)} {tx:.9f} {ty:.9f} {tz:.9f} {qx:.9f} {qy:.9f} {qz:.9f} {qw:.9f}")
    return lines


def write_tum(path: str | Path, t_us: torch.Tensor, poses: torch.Tensor) -> None:
    """Write a TUM trajectory (seconds with microsecond resolution, 9 decimals for poses), atomically."""
    write_text(path, "\n".join([TUM_HEADER, *tum_lines(t_us, poses)]) + "\n")


def read_csv(path: str | Path) -> tuple[torch.Tensor, torch.Tensor]:
    """Read a CSV trajectory (``t,x,y,z,qx,qy,qz,qw``, seconds and metres; see the module docstring).

    Returns ``t_us (N,) int64`` and ``poses (N, 7) float64``.
    """
    path = _existing(path)
    order, ncols = list(range(8)), 8
    rows = []
    first = True
    for lineno, raw in enumerate(path.read_text().splitlines(), start=1):
        line = raw.split("#", 1)[0].strip()
        if not line:
            continue
        fields = [f.strip() for f in line.split(",")]
        if first and not _all_numbers(fields):
            names = [_CSV_ALIASES.get(f.lower(), f.lower()) for f in fields]
            missing = [c for c in _CSV_COLUMNS if c not in names]
            if missing:
                raise ValueError(f"{path}:{lineno}: CSV header {fields} lacks columns {missing}")
            order, ncols = [names.index(c) for c in _CSV_COLUMNS], len(fields)
            first = False
            continue
        first = False
        if len(fields) != ncols:
            raise ValueError(f"{path}:{lineno}: expected {ncols} comma-separated values, got {len(fields)}")
        values = _parse_numbers(path, lineno, fields, line)
        rows.append([values[i] for i in order])
    a = np.asarray(rows, dtype=np.float64).reshape(-1, 8)
    return _finish(path, _seconds_to_us(a[:, 0]), a[:, 1:4], a[:, [7, 4, 5, 6]])


def write_csv(path: str | Path, t_us: torch.Tensor, poses: torch.Tensor) -> None:
    """Write a CSV trajectory with header ``t,x,y,z,qx,qy,qz,qw`` (seconds, metres, 9 decimals)."""
    t_us, poses = _check_trajectory(t_us, poses)
    lines = [",".join(_CSV_COLUMNS)]
    for ti, row in zip(t_us.tolist(), poses.numpy()):
        tx, ty, tz, qw, qx, qy, qz = row
        lines.append(f"{_us_to_seconds_str(ti)},{tx:.9f},{ty:.9f},{tz:.9f},{qx:.9f},{qy:.9f},{qz:.9f},{qw:.9f}")
    write_text(path, "\n".join(lines) + "\n")


def _frame_times(
    path: Path, frame_ids: list[int], fps: float | None, times: Mapping | Sequence | torch.Tensor | np.ndarray | None
) -> dict[int, int]:
    if (fps is None) == (times is None):
        raise ValueError(f"{path}: BOP scene_gt has no timestamps; pass exactly one of fps= or times=")
    if fps is not None:
        if not fps > 0:
            raise ValueError(f"fps must be > 0, got {fps}")
        return {f: round(f * 1e6 / fps) for f in frame_ids}
    if isinstance(times, Mapping):
        out = {}
        for k, v in times.items():
            if isinstance(v, bool) or not isinstance(v, (int, np.integer)) or not str(k).lstrip("-").isdigit():
                raise TypeError(f"times: expected frame id -> integer microseconds, got {k!r}: {v!r}")
            out[int(k)] = int(v)
        missing = [f for f in frame_ids if f not in out]
        if missing:
            raise ValueError(f"{path}: times has no entry for frame ids {missing[:5]}")
        return out
    arr = torch.as_tensor(np.asarray(times))
    if arr.dtype not in (torch.int64, torch.int32) or arr.ndim != 1:
        raise TypeError(f"times must be a mapping or an integer microsecond array (F,), got {arr.dtype} {tuple(arr.shape)}")
    if arr.shape[0] != len(frame_ids):
        raise ValueError(f"{path}: times has {arr.shape[0]} entries but the file has {len(frame_ids)} frames")
    return dict(zip(frame_ids, arr.tolist()))


def read_bop_scene_gt(
    path: str | Path,
    obj_id: int | None = None,
    fps: float | None = None,
    times: Mapping | Sequence | torch.Tensor | np.ndarray | None = None,
) -> tuple[torch.Tensor, torch.Tensor]:
    """Read one object's trajectory from a BOP ``scene_gt.json``.

    Args:
        path: the JSON file.
        obj_id: the object to read; ``None`` requires the file to hold a single object id.
            Frames without that object are skipped; more than one instance in a frame is an error.
        fps: frame rate: frame ``f`` is at ``round(f * 1e6 / fps)`` microseconds.
        times: instead of ``fps``, per-frame times in integer microseconds: a mapping
            ``{frame id: t_us}``, or an array ``(F,)`` over the file's frame ids in increasing order.

    Returns ``t_us (N,) int64`` and ``poses (N, 7) float64`` (metres), sorted by time.
    """
    path = _existing(path)
    try:
        data = json.loads(path.read_text())
    except json.JSONDecodeError as e:
        raise ValueError(f"{path}:{e.lineno}: invalid JSON: {e.msg}") from None
    if not isinstance(data, dict):
        raise ValueError(f"{path}: expected a JSON object {{frame id: [annotations]}}, got {type(data).__name__}")
    frames: dict[int, list] = {}
    for key, anns in data.items():
        try:
            fid = int(key)
        except ValueError:
            raise ValueError(f"{path}: frame key {key!r} is not an integer frame id") from None
        if not isinstance(anns, list):
            raise ValueError(f"{path}: frame {key}: expected a list of annotations")
        frames[fid] = anns
    frame_ids = sorted(frames)
    ids_present = sorted({a.get("obj_id") for f in frame_ids for a in frames[f] if isinstance(a, dict)})
    if obj_id is None:
        if len(ids_present) != 1:
            raise ValueError(f"{path}: holds object ids {ids_present}; pass obj_id= to choose one")
        obj_id = ids_present[0]
    elif obj_id not in ids_present:
        raise ValueError(f"{path}: no annotation of obj_id {obj_id} (present: {ids_present})")
    t_of = _frame_times(path, frame_ids, fps, times)
    used, t_list, R_list, tr_list = [], [], [], []
    for fid in frame_ids:
        mine = [a for a in frames[fid] if isinstance(a, dict) and a.get("obj_id") == obj_id]
        if not mine:
            continue
        if len(mine) > 1:
            raise ValueError(f"{path}: frame {fid} has {len(mine)} instances of obj_id {obj_id}; expected one")
        a = mine[0]
        R, t = a.get("cam_R_m2c"), a.get("cam_t_m2c")
        if not (isinstance(R, list) and len(R) == 9 and isinstance(t, list) and len(t) == 3):
            raise ValueError(f"{path}: frame {fid}: expected cam_R_m2c (9 numbers) and cam_t_m2c (3 numbers)")
        try:
            R_list.append([float(v) for v in R])
            tr_list.append([float(v) for v in t])
        except (TypeError, ValueError):
            raise ValueError(f"{path}: frame {fid}: cam_R_m2c / cam_t_m2c hold a non-number") from None
        t_list.append(t_of[fid])
        used.append(fid)
    R = torch.tensor(R_list, dtype=torch.float64).reshape(-1, 3, 3)
    tr = np.asarray(tr_list, dtype=np.float64).reshape(-1, 3) / 1000.0
    if not torch.isfinite(R).all():
        raise ValueError(f"{path}: NaN or infinite values in cam_R_m2c")
    err = (R @ R.transpose(-1, -2) - torch.eye(3, dtype=torch.float64)).abs().amax(dim=(-1, -2))
    bad = ((err > 1e-3) | (torch.linalg.det(R) <= 0)).nonzero()
    if bad.numel():
        raise ValueError(f"{path}: frame {used[int(bad[0, 0])]}: cam_R_m2c is not a rotation matrix")
    t_us = torch.tensor(t_list, dtype=torch.int64)
    order = torch.argsort(t_us, stable=True)
    return _finish(path, t_us[order], tr[order.numpy()], matrix_to_quat(R).numpy()[order.numpy()])


def write_bop_scene_gt(path: str | Path, t_us: torch.Tensor, poses: torch.Tensor, *, fps: float, obj_id: int = 1) -> None:
    """Write a trajectory as a BOP ``scene_gt.json`` of one object (translation in millimetres).

    The frame id of a pose is ``round(t * fps)``; every timestamp must be exactly the reader's time of
    its frame, ``round(frame_id * 1e6 / fps)`` us, with distinct frames, so that
    :func:`read_bop_scene_gt` with the same ``fps`` restores the trajectory.
    """
    t_us, poses = _check_trajectory(t_us, poses)
    if not fps > 0:
        raise ValueError(f"fps must be > 0, got {fps}")
    ids = []
    for ti in t_us.tolist():
        fid = round(ti * fps / 1e6)
        if round(fid * 1e6 / fps) != ti:
            raise ValueError(f"t_us {ti} is not on the {fps} fps frame grid (nearest frame {fid})")
        ids.append(fid)
    if len(set(ids)) != len(ids):
        raise ValueError(f"two poses fall on the same frame at {fps} fps")
    R = quat_to_matrix(poses[:, 3:]).reshape(-1, 9).tolist()
    t_mm = (poses[:, :3] * 1000.0).tolist()
    data = {str(f): [{"cam_R_m2c": r, "cam_t_m2c": t, "obj_id": int(obj_id)}] for f, r, t in zip(ids, R, t_mm)}
    write_text(path, json.dumps(data, indent=1) + "\n")


def detect_format(path: str | Path) -> str:
    """Format of a pose file: by extension (``.txt``/``.tum`` TUM, ``.csv`` CSV, ``.json`` BOP), else by its
    content (a JSON object -> BOP, commas or a ``t,`` header -> CSV, else TUM); ``FileNotFoundError`` when a file
    without such an extension does not exist."""
    path = Path(path)
    fmt = _EXTENSIONS.get(path.suffix.lower())
    if fmt is not None:
        return fmt
    for line in _existing(path).read_text().splitlines():
        line = line.split("#", 1)[0].strip()
        if not line:
            continue
        if line.startswith("{"):
            return "bop"
        return "csv" if "," in line else "tum"
    raise ValueError(f"{path}: empty file, cannot tell its pose format; pass format=")


def _check_format(fmt: str) -> str:
    if fmt not in FORMATS:
        raise ValueError(f"format must be one of {FORMATS}, got {fmt!r}")
    return fmt


def read_poses(path: str | Path, format: str | None = None, **kwargs) -> tuple[torch.Tensor, torch.Tensor]:
    """Read a trajectory in any supported format (see :func:`detect_format`).

    ``kwargs`` go to the BOP reader (``obj_id``, ``fps``, ``times``) and are refused for the others.
    Returns ``t_us (N,) int64`` and ``poses (N, 7) float64``.
    """
    fmt = _check_format(format) if format is not None else detect_format(_existing(path))
    if fmt == "bop":
        return read_bop_scene_gt(path, **kwargs)
    if kwargs:
        raise TypeError(f"options {sorted(kwargs)} only apply to BOP files, not {fmt}")
    return read_tum(path) if fmt == "tum" else read_csv(path)


def write_poses(path: str | Path, t_us: torch.Tensor, poses: torch.Tensor, format: str | None = None, **kwargs) -> None:
    """Write a trajectory; the format comes from ``format`` or the extension (default TUM).

    ``kwargs`` go to the BOP writer (``fps`` required, ``obj_id``).
    """
    fmt = _check_format(format) if format is not None else _EXTENSIONS.get(Path(path).suffix.lower(), "tum")
    if fmt == "bop":
        write_bop_scene_gt(path, t_us, poses, **kwargs)
        return
    if kwargs:
        raise TypeError(f"options {sorted(kwargs)} only apply to BOP files, not {fmt}")
    (write_tum if fmt == "tum" else write_csv)(path, t_us, poses)
