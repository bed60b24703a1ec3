"""Pinhole camera: intrinsics, image size, projection and the interaction matrix.

Pixel coordinates are ``(u, v)`` = (column, row); the centre of pixel ``(i, j)`` is at
``u = i, v = j`` (OpenCV). Camera axes are OpenCV's (x right, y down, z forward), metres.

Example:
    >>> import torch
    >>> from torchevtrack.camera import Camera
    >>> cam = Camera(640, 480, 502.3, 502.3, 320.0, 240.0)
    >>> cam.project(torch.tensor([[0.0, 0.0, 0.5]]))
    tensor([[320., 240.]])
"""

from __future__ import annotations

import json
import math
from dataclasses import asdict, dataclass
from pathlib import Path

import torch

__all__ = ["Camera", "MAX_PIXELS", "MAX_SIDE", "interaction_matrix"]

MAX_SIDE = 1 << 15  # pixel coordinates are stored as int16
MAX_PIXELS = 4096 * 4096  # a sensor of 16 Mpx: the tracker's per-pixel images then take ~64 MB each


@dataclass(frozen=True)
class Camera:
    """Pinhole intrinsics (pixels) and sensor size.

    Attributes:
        width, height: sensor size in pixels: integers, each at most :data:`MAX_SIDE` and together at most
            :data:`MAX_PIXELS` (every image of the tracker has this size).
        fx, fy: focal lengths in pixels, finite and positive.
        cx, cy: principal point in pixels, finite.
        distortion: OpenCV lens distortion ``(k1, k2, p1, p2, k3)`` of the sensor, or ``None``. Every
            method here stays pinhole; events are undistorted into the pinhole image of the same ``K``
            with :mod:`torchevtrack.distortion`.
    """

    width: int
    height: int
    fx: float
    fy: float
    cx: float
    cy: float
    distortion: tuple[float, ...] | None = None

    def __post_init__(self) -> None:
        for k in ("width", "height"):
            v = self.__dict__[k]
            if isinstance(v, (str, bytes, bool)) or v is None or not float(v).is_integer() or not 0 < v < MAX_SIDE:
                raise ValueError(f"camera {k} must be a positive whole number of pixels below {MAX_SIDE}, "
                                 f"got {v!r}")
            object.__setattr__(self, k, int(v))
        if self.width * self.height > MAX_PIXELS:
            raise ValueError(f"camera size {self.width}x{self.height} is over {MAX_PIXELS // 1_000_000} Mpx "
                             f"({self.width * self.height * 4 / 1e9:.1f} GB per image): check camera.json")
        for k in ("fx", "fy", "cx", "cy"):
            v = self.__dict__[k]
            try:
                if isinstance(v, (str, bytes, bool)) or v is None:
                    raise TypeError
                f = float(v)
            except (TypeError, ValueError):
                raise ValueError(f"camera {k} must be a number of pixels, got {v!r}") from None
            if not math.isfinite(f) or (k in ("fx", "fy") and f <= 0):
                rule = "finite and positive" if k in ("fx", "fy") else "finite"
                raise ValueError(f"camera {k} must be {rule}, got {v!r}")
            object.__setattr__(self, k, f)
        if self.distortion is not None:
            d = tuple(float(c) for c in self.distortion)
            if len(d) not in (4, 5) or not all(math.isfinite(c) for c in d):
                raise ValueError(f"distortion must be 4 or 5 finite numbers (k1, k2, p1, p2[, k3]), got {d}")
            object.__setattr__(self, "distortion", d + (0.0,) * (5 - len(d)))

    @classmethod
    def default(cls) -> "Camera":
        """The benchmark camera: 640x480, fx = fy = 502.3, principal point at the centre."""
        return cls(640, 480, 502.3, 502.3, 320.0, 240.0)

    # -- serialisation -------------------------------------------------------------------------
    def to_dict(self) -> dict:
        d = asdict(self)
        if self.distortion is None:  # pinhole cameras keep the original keys
            del d["distortion"]
        else:
            d["distortion"] = list(self.distortion)
        return d

    @classmethod
    def from_dict(cls, d: dict) -> "Camera":
        missing = {"width", "height", "fx", "fy", "cx", "cy"} - set(d)
        if missing:
            raise ValueError(f"camera description lacks {sorted(missing)}")
        return cls(d["width"], d["height"], d["fx"], d["fy"], d["cx"], d["cy"], d.get("distortion"))

    def save(self, path: str | Path) -> None:
        from torchevtrack.io.atomic import write_text

        write_text(path, json.dumps(self.to_dict(), indent=2) + "\n")

    @classmethod
    def load(cls, path: str | Path) -> "Camera":
        path = Path(path)
        if not path.is_file():
            raise FileNotFoundError(f"camera file not found: {path}")
        try:
            d = json.loads(path.read_text())
        except json.JSONDecodeError as e:
            raise ValueError(f"{path}: not valid JSON ({e})") from None
        return cls.from_dict(d)

    # -- matrices and derived cameras ----------------------------------------------------------
    def K(self, dtype: torch.dtype = torch.float64) -> torch.Tensor:
        """3x3 intrinsic matrix."""
        return torch.tensor([[self.fx, 0.0, self.cx], [0.0, self.fy, self.cy], [0.0, 0.0, 1.0]], dtype=dtype)

    def crop(self, u0: int, v0: int, width: int, height: int) -> "Camera":
        """Camera seeing only the window whose top-left pixel is ``(u0, v0)``."""
        return Camera(width, height, self.fx, self.fy, self.cx - u0, self.cy - v0, self.distortion)

    def scale(self, s: float) -> "Camera":
        """Camera of an image resized by ``s`` (pixel centres kept consistent)."""
        return Camera(
            round(self.width * s), round(self.height * s),
            self.fx * s, self.fy * s, (self.cx + 0.5) * s - 0.5, (self.cy + 0.5) * s - 0.5, self.distortion,
        )

    # -- geometry ------------------------------------------------------------------------------
    def project(self, points: torch.Tensor) -> torch.Tensor:
        """Camera-frame points to pixels. Shape: ``(..., 3) -> (..., 2)``, metres -> pixels."""
        z = points[..., 2]
        return torch.stack((self.fx * points[..., 0] / z + self.cx, self.fy * points[..., 1] / z + self.cy), dim=-1)

    def backproject(self, uv: torch.Tensor, depth: torch.Tensor) -> torch.Tensor:
        """Pixels with depth (metres, along z) to camera-frame points. Shape: ``(..., 2), (...) -> (..., 3)``."""
        x = (uv[..., 0] - self.cx) / self.fx * depth
        y = (uv[..., 1] - self.cy) / self.fy * depth
        return torch.stack((x, y, depth), dim=-1)

    def pixel_grid(self, dtype: torch.dtype = torch.float32) -> torch.Tensor:
        """Pixel centre coordinates ``(H, W, 2)`` as ``(u, v)``."""
        v, u = torch.meshgrid(
            torch.arange(self.height, dtype=dtype), torch.arange(self.width, dtype=dtype), indexing="ij"
        )
        return torch.stack((u, v), dim=-1)

    def in_bounds(self, u: torch.Tensor, v: torch.Tensor) -> torch.Tensor:
        """Mask of integer pixel coordinates inside the sensor."""
        return (u >= 0) & (u < self.width) & (v >= 0) & (v < self.height)

    def interaction_matrix(self, uv: torch.Tensor, depth: torch.Tensor) -> torch.Tensor:
        """Image-point Jacobian: pixel velocity = ``L @ [v, w]``; see :func:`interaction_matrix`."""
        return interaction_matrix(uv, depth, self.fx, self.fy, self.cx, self.cy)


def interaction_matrix(
    uv: torch.Tensor, depth: torch.Tensor, fx: float, fy: float, cx: float, cy: float
) -> torch.Tensor:
    """Interaction matrix mapping the object twist to the velocity of its image point.

    For an object point ``P`` moving as ``dP/dt = v + w x P`` (camera frame), the pixel at ``uv``
    with depth ``Z`` moves by ``d(uv)/dt = L @ [v, w]`` (pixels / s for m / s and rad / s).

    Shape: ``(..., 2), (...) -> (..., 2, 6)``.
    """
    uu = uv[..., 0] - cx
    vv = uv[..., 1] - cy
    iz = 1.0 / depth
    zero = torch.zeros_like(uu)
    row_u = torch.stack(
        (fx * iz, zero, -uu * iz, -uu * vv / fy, fx + uu * uu / fx, -vv * fx / fy), dim=-1
    )
    row_v = torch.stack(
        (zero, fy * iz, -vv * iz, -(fy + vv * vv / fy), uu * vv / fx, uu * fy / fx), dim=-1
    )
    return torch.stack((row_u, row_v), dim=-2)
