"""torchevtrack: learning-free 6D object pose tracking from events, as batched PyTorch stages.

Pose convention (everywhere): object in camera frame, OpenCV axes, metres, tensor layout
``[tx, ty, tz, qw, qx, qy, qz]``. Timestamps: int64 microseconds. See ``torchevtrack.geometry``.

The names below are imported on first use (``torchevtrack.EventPoseTracker`` loads the tracker and its
kernels), so ``import torchevtrack`` is quick and loads neither OpenGL nor numba.
"""

from __future__ import annotations

import importlib
from typing import TYPE_CHECKING

__all__ = ["Camera", "EROS", "EventPoseTracker", "EventStream", "OnlineTracker", "TrackerConfig"]
__version__ = "0.1.0"

_MODULE_OF = {
    "Camera": "torchevtrack.camera",
    "EROS": "torchevtrack.stages.eros",
    "EventPoseTracker": "torchevtrack.tracker",
    "EventStream": "torchevtrack.events",
    "OnlineTracker": "torchevtrack.online",
    "TrackerConfig": "torchevtrack.config",
}

if TYPE_CHECKING:
    from torchevtrack.camera import Camera
    from torchevtrack.config import TrackerConfig
    from torchevtrack.events import EventStream
    from torchevtrack.online import OnlineTracker
    from torchevtrack.stages.eros import EROS
    from torchevtrack.tracker import EventPoseTracker


def _drop_stale_callers() -> None:
    """Numba's cache misses edits to a kernel's callees in other modules: drop their callers' code
    (:func:`torchevtrack.kernels.drop_stale_callers`) before any kernel loads."""
    from torchevtrack.kernels import drop_stale_callers

    try:
        drop_stale_callers()
    except OSError:  # never fail an import on the cache: numba uses what it has
        pass


_drop_stale_callers()


def __getattr__(name: str):
    if name not in _MODULE_OF:
        raise AttributeError(f"module 'torchevtrack' has no attribute {name!r}")
    value = getattr(importlib.import_module(_MODULE_OF[name]), name)
    globals()[name] = value
    return value


def __dir__() -> list[str]:
    return sorted(set(globals()) | set(__all__))
