"""Lens distortion: OpenCV's radial-tangential model and event undistortion.

Model (OpenCV ``k1, k2, p1, p2[, k3]``) on normalised image coordinates ``(x, y) = ((u - cx) / fx,
(v - cy) / fy)`` of the ideal pinhole image, with ``r2 = x^2 + y^2``::

    R  = 1 + k1 r2 + k2 r2^2 + k3 r2^3
    xd = x R + 2 p1 x y + p2 (r2 + 2 x^2)
    yd = y R + p1 (r2 + 2 y^2) + 2 p2 x y

and the sensor records ``(fx xd + cx, fy yd + cy)``. :func:`undistort_points` inverts the model by
Newton's method (analytic 2x2 Jacobian, float64, vectorised).

How templates and events meet: the tracker renders *pinhole* templates with the camera's ``K``. Real
events are therefore moved into that same pinhole image first: every sensor pixel is sent through the
inverse model once (an ``H x W`` lookup table, :func:`undistortion_map`), and each event then takes its
pixel's entry (:func:`undistort_events`, or :class:`Undistorter` chunk by chunk). Templates and events
then both live in the undistorted pinhole frame of the same ``K``, which is how "templates rendered
with the same camera model" holds. Events whose undistorted pixel falls outside the sensor (the
corners of a barrel-distorted image spread beyond it) are dropped; the dropped count is
``len(events) - len(result)`` (:attr:`Undistorter.dropped` keeps a running total).

Example:
    >>> import torch
    >>> from torchevtrack.camera import Camera
    >>> from torchevtrack.distortion import distort_points, undistort_points
    >>> cam = Camera(64, 48, 50.0, 50.0, 31.5, 23.5)
    >>> coeffs = (-0.3, 0.1, 1e-3, -5e-4, 0.0)
    >>> uv = torch.tensor([[2.0, 3.0]], dtype=torch.float64)
    >>> xy = (undistort_points(uv, cam, coeffs) - torch.tensor([31.5, 23.5])) / 50.0
    >>> back = distort_points(xy, coeffs) * 50.0 + torch.tensor([31.5, 23.5])
    >>> bool(torch.allclose(back, uv, atol=1e-9))
    True
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import torch
from torch import nn

from torchevtrack.camera import Camera
from torchevtrack.events import EventStream

__all__ = [
    "Undistorter",
    "as_coeffs",
    "distort_points",
    "nearest_table",
    "remap_pixels",
    "undistort_events",
    "undistort_pixels",
    "undistort_points",
    "undistortion_map",
]

ROUNDING = ("nearest", "random")
# A Newton solution whose re-distorted point misses the input by more than this (pixels) has no inverse
# (beyond the fold of a strongly non-monotonic model, or diverged): it becomes NaN.
_MISS_PX = 1e-3


def as_coeffs(coeffs: Sequence[float] | torch.Tensor | None, camera: Camera | None = None) -> torch.Tensor:
    """Distortion coefficients as a float64 ``(5,)`` tensor ``[k1, k2, p1, p2, k3]``.

    Accepts 4 (``k3 = 0``) or 5 numbers; ``None`` takes ``camera.distortion``.

    Raises:
        ValueError: wrong count, non-finite values, or no coefficients anywhere.
    """
    if coeffs is None:
        coeffs = None if camera is None else camera.distortion
        if coeffs is None:
            raise ValueError("coeffs: no distortion coefficients given and the camera has none")
    c = torch.as_tensor(coeffs, dtype=torch.float64).flatten()
    if c.numel() not in (4, 5):
        raise ValueError(f"coeffs must be [k1, k2, p1, p2] or [k1, k2, p1, p2, k3], got {c.numel()} values")
    if not bool(torch.isfinite(c).all()):
        raise ValueError(f"coeffs must be finite, got {c.tolist()}")
    return torch.cat((c, c.new_zeros(5 - c.numel())))


def _model(x: torch.Tensor, y: torch.Tensor, c: torch.Tensor, jacobian: bool = False):
    """Distorted ``(xd, yd)`` and optionally the Jacobian entries ``(a, b, d)`` of ``[[a, b], [b, d]]``."""
    k1, k2, p1, p2, k3 = c.tolist()
    xx, yy, xy = x * x, y * y, x * y
    r2 = xx + yy
    R = 1 + r2 * (k1 + r2 * (k2 + r2 * k3))
    xd = x * R + 2 * p1 * xy + p2 * (r2 + 2 * xx)
    yd = y * R + p1 * (r2 + 2 * yy) + 2 * p2 * xy
    if not jacobian:
        return xd, yd
    dR = 2 * (k1 + r2 * (2 * k2 + 3 * k3 * r2))  # dR/dx = dR * x, dR/dy = dR * y
    a = R + dR * xx + 2 * p1 * y + 6 * p2 * x
    b = dR * xy + 2 * p1 * x + 2 * p2 * y
    d = R + dR * yy + 6 * p1 * y + 2 * p2 * x
    return xd, yd, (a, b, d)


def distort_points(xy_normalised: torch.Tensor, coeffs: Sequence[float] | torch.Tensor) -> torch.Tensor:
    """Apply the radial-tangential model to normalised pinhole coordinates.

    Shape: ``(..., 2) -> (..., 2)`` float64 (unitless, ``x = (u - cx) / fx``).
    """
    xy = torch.as_tensor(xy_normalised, dtype=torch.float64)
    if xy.shape[-1:] != (2,):
        raise ValueError(f"xy_normalised must have shape (..., 2), got {tuple(xy.shape)}")
    return torch.stack(_model(xy[..., 0], xy[..., 1], as_coeffs(coeffs)), dim=-1)


def undistort_points(uv_pixels: torch.Tensor, camera: Camera, coeffs: Sequence[float] | torch.Tensor | None = None,
                     iterations: int = 20) -> torch.Tensor:
    """Sensor (distorted) pixels to pixels of the ideal pinhole image of the same ``K``.

    Newton's method on ``distort(x) = xd``, started at ``x = xd``; stops early once every point
    re-distorts to within 1e-12 of its input. Points with no inverse (re-distortion misses the input by
    more than 1e-3 px after ``iterations`` steps) are NaN.

    Args:
        uv_pixels: ``(..., 2)`` sensor pixel coordinates ``(u, v)``.
        camera: intrinsics (the distortion comes from ``coeffs`` or else ``camera.distortion``).
        coeffs: ``[k1, k2, p1, p2(, k3)]``.
        iterations: maximum Newton steps (>= 1).

    Shape: ``(..., 2) -> (..., 2)`` float64 pixels.
    """
    c = as_coeffs(coeffs, camera)
    if isinstance(iterations, bool) or not isinstance(iterations, int) or iterations < 1:
        raise ValueError(f"iterations must be an integer >= 1, got {iterations!r}")
    uv = torch.as_tensor(uv_pixels, dtype=torch.float64)
    if uv.shape[-1:] != (2,):
        raise ValueError(f"uv_pixels must have shape (..., 2), got {tuple(uv.shape)}")
    tx = (uv[..., 0] - camera.cx) / camera.fx
    ty = (uv[..., 1] - camera.cy) / camera.fy
    x, y = tx.clone(), ty.clone()
    for _ in range(iterations):
        xd, yd, (a, b, d) = _model(x, y, c, jacobian=True)
        rx, ry = xd - tx, yd - ty
        if not bool(((rx.abs() > 1e-12) | (ry.abs() > 1e-12)).any()):
            break
        det = a * d - b * b
        x = x - (d * rx - b * ry) / det
        y = y - (a * ry - b * rx) / det
    xd, yd = _model(x, y, c)
    ok = torch.maximum(((xd - tx) * camera.fx).abs(), ((yd - ty) * camera.fy).abs()) <= _MISS_PX  # NaN: False
    out = torch.stack((x * camera.fx + camera.cx, y * camera.fy + camera.cy), dim=-1)
    return torch.where(ok[..., None], out, torch.full_like(out, math.nan))


def undistortion_map(camera: Camera, coeffs: Sequence[float] | torch.Tensor | None = None,
                     iterations: int = 20) -> torch.Tensor:
    """Undistorted pinhole position of every sensor pixel (NaN where the model has no inverse).

    Shape: ``-> (H, W, 2)`` float64 pixels ``(u, v)``; entry ``[y, x]`` belongs to sensor pixel ``(x, y)``.
    """
    return undistort_points(camera.pixel_grid(torch.float64), camera, coeffs, iterations)


def _check_rounding(rounding: str) -> None:
    if rounding not in ROUNDING:
        raise ValueError(f"rounding must be one of {ROUNDING}, got {rounding!r}")


def undistort_pixels(x: torch.Tensor, y: torch.Tensor, lut: torch.Tensor, rounding: str = "nearest",
                     generator: torch.Generator | None = None) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Move integer event pixels through an undistortion lookup table.

    Args:
        x, y: ``(N,)`` integer sensor pixels (inside the table).
        lut: ``(H, W, 2)`` undistorted positions (:func:`undistortion_map`); the output image has the same size.
        rounding: ``"nearest"`` (round to the closest pixel, ties to even) or ``"random"`` (round up
            with probability equal to the fractional part: unbiased on average, needs ``generator`` for
            reproducibility).

    Returns:
        ``x, y`` ``(K,)`` new pixels (dtype of the input) and ``keep`` ``(N,)`` bool: the event's new
        pixel is inside the image (apply ``keep`` to ``t``, ``p`` and any batch index).
    """
    _check_rounding(rounding)
    if lut.ndim != 3 or lut.shape[-1] != 2:
        raise ValueError(f"lut must have shape (H, W, 2), got {tuple(lut.shape)}")
    H, W = lut.shape[:2]
    _check_pixels(x, y, H, W)
    uv = lut.reshape(-1, 2).index_select(0, y.long() * W + x.long())
    if rounding == "nearest":
        uv = uv.round()
    else:
        uv = (uv + torch.rand(uv.shape, generator=generator, dtype=uv.dtype)).floor()
    keep = (uv[:, 0] >= 0) & (uv[:, 0] <= W - 1) & (uv[:, 1] >= 0) & (uv[:, 1] <= H - 1)  # NaN -> False
    uv = uv[keep].to(x.dtype)
    return uv[:, 0], uv[:, 1], keep


def nearest_table(lut: torch.Tensor) -> torch.Tensor:
    """Per-pixel table of :func:`undistort_pixels` with ``rounding="nearest"``, for :func:`remap_pixels`.

    Shape: ``(H, W, 2) -> (H * W,)`` int32: linear index ``v * W + u`` of the nearest undistorted pixel,
    ``-1`` where it falls outside the image (or has no inverse).
    """
    if lut.ndim != 3 or lut.shape[-1] != 2:
        raise ValueError(f"lut must have shape (H, W, 2), got {tuple(lut.shape)}")
    H, W = lut.shape[:2]
    uv = lut.reshape(-1, 2).round()
    inside = (uv[:, 0] >= 0) & (uv[:, 0] <= W - 1) & (uv[:, 1] >= 0) & (uv[:, 1] <= H - 1)
    index = (uv[:, 1] * W + uv[:, 0]).nan_to_num(0.0).to(torch.int32)
    return torch.where(inside, index, torch.full_like(index, -1))


def remap_pixels(x: torch.Tensor, y: torch.Tensor, table: torch.Tensor, width: int
                 ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Fast path of :func:`undistort_pixels` (nearest rounding): one integer gather per event.

    Args:
        x, y: ``(N,)`` integer sensor pixels (inside the sensor).
        table: ``(H * W,)`` from :func:`nearest_table`; width: ``W``.

    Returns:
        ``x, y`` ``(K,)`` new pixels (dtype of the input) and ``keep`` ``(N,)`` bool.
    """
    _check_pixels(x, y, table.numel() // width, width)
    idx = table.index_select(0, y.long() * width + x.long())
    keep = idx >= 0
    idx = idx[keep]
    return (idx % width).to(x.dtype), torch.div(idx, width, rounding_mode="floor").to(y.dtype), keep


def _check_pixels(x: torch.Tensor, y: torch.Tensor, H: int, W: int) -> None:
    for name, f in (("x", x), ("y", y)):
        if not isinstance(f, torch.Tensor) or f.is_floating_point() or f.dtype == torch.bool or f.ndim != 1:
            raise TypeError(f"{name} must be a 1-D integer tensor")
    if x.shape != y.shape:
        raise ValueError(f"x and y must have the same shape, got {tuple(x.shape)} and {tuple(y.shape)}")
    if x.numel() and bool((x.min() < 0) | (x.max() >= W) | (y.min() < 0) | (y.max() >= H)):
        raise ValueError(f"event pixels must be inside the {W}x{H} sensor of the lookup table")


class Undistorter(nn.Module):
    """Undistort event chunks on the fly with a lookup table built once.

    Args:
        camera: the sensor (size and ``K``); the undistorted events are in the pinhole image of the same camera.
        coeffs: ``[k1, k2, p1, p2(, k3)]`` (default ``camera.distortion``).
        rounding: ``"nearest"`` or ``"random"`` (see :func:`undistort_pixels`).
        iterations: Newton steps used to build the table.
        seed: seeds the random rounding.

    Buffers:
        lut: ``(H, W, 2)`` float32 undistorted pixel of every sensor pixel (NaN: no inverse).
        table: ``(H * W,)`` int32 :func:`nearest_table` of ``lut`` (the fast path of nearest rounding).
        dropped: ``()`` int64 events dropped so far (new pixel outside the sensor).

    Example:
        >>> from torchevtrack.camera import Camera
        >>> from torchevtrack.events import EventStream
        >>> und = Undistorter(Camera(64, 48, 40.0, 40.0, 31.5, 23.5), (-0.3, 0.1, 0.0, 0.0))
        >>> out = und(EventStream.from_arrays(x=[0, 31], y=[0, 23], t=[0, 1], p=[1, 1]))
        >>> out.x.tolist(), int(und.dropped)  # the corner pixel lands outside the sensor
        ([31], 1)
    """

    lut: torch.Tensor
    dropped: torch.Tensor

    def __init__(self, camera: Camera, coeffs: Sequence[float] | torch.Tensor | None = None, *,
                 rounding: str = "nearest", iterations: int = 20, seed: int = 0) -> None:
        super().__init__()
        _check_rounding(rounding)
        self.camera, self.rounding = camera, rounding
        self.coeffs = as_coeffs(coeffs, camera)
        # float32: 1e-4 px resolution at 2k px, half the memory of float64.
        self.register_buffer("lut", undistortion_map(camera, self.coeffs, iterations).float())
        self.register_buffer("table", nearest_table(self.lut))
        self.register_buffer("dropped", torch.zeros((), dtype=torch.int64))
        self.generator = torch.Generator().manual_seed(seed)

    def remap(self, x: torch.Tensor, y: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """Packed event pixels ``(N,)`` -> new ``x, y`` ``(K,)`` and ``keep`` ``(N,)``; counts the drops."""
        if self.rounding == "nearest":
            nx, ny, keep = remap_pixels(x, y, self.table, self.camera.width)
        else:
            nx, ny, keep = undistort_pixels(x, y, self.lut, self.rounding, self.generator)
        self.dropped += int(keep.numel() - nx.numel())
        return nx, ny, keep

    def forward(self, events: EventStream) -> EventStream:
        """Undistorted copy of ``events`` (time order kept, dropped events removed)."""
        x, y, keep = self.remap(events.x, events.y)
        return EventStream(x, y, events.t[keep], events.p[keep])

    def extra_repr(self) -> str:
        return f"camera={self.camera}, coeffs={self.coeffs.tolist()}, rounding={self.rounding!r}"


def undistort_events(events: EventStream, camera: Camera, coeffs: Sequence[float] | torch.Tensor | None = None, *,
                     rounding: str = "nearest", iterations: int = 20, seed: int = 0) -> EventStream:
    """Move a whole stream into the undistorted pinhole image of ``camera`` (see the module docstring).

    Builds the ``H x W`` lookup table once (:class:`Undistorter`), then one gather per event. Events
    landing outside the sensor are dropped: ``len(events) - len(result)`` of them.
    """
    return Undistorter(camera, coeffs, rounding=rounding, iterations=iterations, seed=seed)(events)
