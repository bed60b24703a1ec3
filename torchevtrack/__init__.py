"""torchevtrack: learning-free 6D object pose tracking from events, as batched PyTorch stages.

Pose convention (everywhere): object in camera frame, OpenCV axes, metres, tensor layout
``[tx, ty, tz, qw, qx, qy, qz]``. Timestamps: int64 microseconds. See ``torchevtrack.geometry``.
"""

from torchevtrack.camera import Camera
from torchevtrack.config import TrackerConfig
from torchevtrack.events import EventStream
from torchevtrack.online import OnlineTracker
from torchevtrack.stages.eros import EROS
from torchevtrack.tracker import EventPoseTracker

__all__ = ["Camera", "EROS", "EventPoseTracker", "EventStream", "OnlineTracker", "TrackerConfig"]
__version__ = "0.1.0"
