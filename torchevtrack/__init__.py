"""torchevtrack: learning-free 6D object pose tracking from events, as batched PyTorch stages.

Pose convention (everywhere): object in camera frame, OpenCV axes, metres, tensor layout
``[tx, ty, tz, qw, qx, qy, qz]``. Timestamps: int64 microseconds. See ``torchevtrack.geometry``.
"""

from torchevtrack.camera import Camera
from torchevtrack.events import EventStream

__all__ = ["Camera", "EventStream"]
__version__ = "0.1.0"
