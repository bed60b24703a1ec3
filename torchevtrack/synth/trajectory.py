"""Smooth, seeded 6D object trajectories in front of a static camera, and their speed statistics.

A trajectory is ``(t_us, poses)``: int64 microseconds ``(N,)`` sampled every ``dt_us`` and float64 poses
``(N, 7)`` ``[tx, ty, tz, qw, qx, qy, qz]`` (object in camera frame, see :mod:`torchevtrack.geometry`).

Construction (all draws from one ``numpy.random.Generator(PCG64(seed))``, so a seed fixes the result):

* **Image path.** The object origin (the mesh bounding-box centre) projects to ``(u, v)`` moving along a
  random smooth closed-form curve (a sum of sinusoids per axis, normalised into a box that keeps the
  whole object in view at the nearest depth). The curve is re-parametrised by arc length so that the
  centroid image speed follows a smooth random profile inside the group's range
  (``regular``: 100-300 px/s, ``fast``: 600-1500 px/s, ``turn``: 50-350 px/s, ``mixed``: 600-1500 px/s).
* **Depth.** ``z(t)`` is an independent smooth curve inside ``[0.3, 0.7]`` m (raised for objects too
  large to fit at 0.3 m).
* **Rotation.** A smooth random angular velocity (camera frame, sum of sinusoids per axis) scaled so its
  peak over a 20 s window is 80-100 % of the group's limit (``regular``: 60 deg/s, ``fast``:
  250 deg/s), or, for the hand-held groups, so that its median over the trajectory is a uniform draw in the
  group's range (``turn``: 240-440 deg/s, ``mixed``: 200-400 deg/s; the turning axis wanders through all
  directions, out-of-plane turns included), integrated exactly from a random initial orientation with
  ``q(t + dt) = exp(w dt) (x) q(t)`` (a parallel prefix product).

Random curves are normalised over a 20 s reference window, so a short trajectory is a piece of a long
one (with the same slow depth drift), not a stretched copy.

Every sample is then checked: the projected mesh bounding box must stay ``margin`` pixels inside the
image; if not, the lateral amplitude is shrunk and the trajectory rebuilt (deterministically).

Example:
    >>> import trimesh
    >>> from torchevtrack.camera import Camera
    >>> cam = Camera(64, 48, 50.0, 50.0, 31.5, 23.5)
    >>> t_us, poses = make_trajectory("regular", 0.05, 0, cam, trimesh.creation.box((0.05, 0.05, 0.08)))
    >>> t_us.shape, poses.shape
    (torch.Size([501]), torch.Size([501, 7]))
"""

from __future__ import annotations

import math
import warnings
from dataclasses import dataclass

import numpy as np
import torch

from torchevtrack.camera import Camera
from torchevtrack.geometry import interpolate_poses, quat_canonical, quat_exp, quat_mul, quat_to_matrix

__all__ = [
    "MOTION_GROUPS",
    "MotionGroup",
    "make_trajectory",
    "SLIDE_S",
    "back_on_path_s",
    "leave_and_return",
    "pose_at",
    "centroid_image_speed",
    "angular_speed",
    "motion_stats",
    "projected_bbox",
    "bbox_corners",
]


@dataclass(frozen=True)
class MotionGroup:
    """Speed ranges of a motion group.

    Attributes:
        speed_px_s: (min, max) centroid image speed, pixels / s.
        max_rot_deg_s: peak angular speed, degrees / s (``None`` when ``rot_median_deg_s`` sets the speed).
        rot_freq_hz: (min, max) frequencies of the angular-velocity sinusoids, Hz.
        speed_freq_hz: (min, max) frequencies of the image-speed profile, Hz.
        depth_freq_hz: (min, max) frequencies of the depth curve, Hz.
        rot_median_deg_s: (min, max) of the median angular speed, degrees / s, or ``None`` (then
            ``max_rot_deg_s`` sets the peak). Exactly one of the two is set.
    """

    speed_px_s: tuple[float, float]
    max_rot_deg_s: float | None
    rot_freq_hz: tuple[float, float]
    speed_freq_hz: tuple[float, float]
    depth_freq_hz: tuple[float, float]
    rot_median_deg_s: tuple[float, float] | None = None

    def __post_init__(self) -> None:
        if (self.max_rot_deg_s is None) == (self.rot_median_deg_s is None):
            raise ValueError("a motion group sets exactly one of max_rot_deg_s and rot_median_deg_s")


MOTION_GROUPS: dict[str, MotionGroup] = {
    "regular": MotionGroup((100.0, 300.0), 60.0, (0.2, 0.8), (0.2, 0.8), (0.1, 0.4)),
    "fast": MotionGroup((600.0, 1500.0), 250.0, (0.5, 2.0), (0.5, 2.0), (0.3, 1.0)),
    # hand-held: turned fast about wandering axes while the centre moves slowly (turn) or fast (mixed)
    "turn": MotionGroup((50.0, 350.0), None, (0.3, 1.2), (0.2, 0.8), (0.1, 0.4), rot_median_deg_s=(240.0, 440.0)),
    "mixed": MotionGroup((600.0, 1500.0), None, (0.5, 2.0), (0.5, 2.0), (0.3, 1.0), rot_median_deg_s=(200.0, 400.0)),
}

_N_SINES = 3


_REFERENCE_SPAN_S = 20.0


def _smooth_unit(rng: np.random.Generator, x: np.ndarray, f_lo: float, f_hi: float,
                 dims: int) -> tuple[np.ndarray, np.ndarray]:
    """Random sum of sinusoids per column, in ``[-1, 1]``, at ``x`` (seconds) and on the reference grid.

    Each column is centred and scaled so that it spans exactly ``[-1, 1]`` over the reference window
    ``[0, max(x[-1], 20 s)]``: a short trajectory is a piece of a long one, not a stretched copy.
    Returns ``(values at x (N, dims), values on the reference grid (20001, dims))``.
    """
    ref = np.linspace(0.0, max(float(x[-1]), _REFERENCE_SPAN_S), 20_001)
    out = np.empty((x.shape[0], dims))
    out_ref = np.empty((ref.shape[0], dims))
    for d in range(dims):
        f = rng.uniform(f_lo, f_hi, _N_SINES)
        phase = rng.uniform(0.0, 2.0 * math.pi, _N_SINES)
        amp = rng.uniform(0.5, 1.0, _N_SINES)

        def sines(s: np.ndarray) -> np.ndarray:
            return (amp * np.sin(2.0 * math.pi * f * s[:, None] + phase)).sum(1)

        r = sines(ref)
        mid, half = 0.5 * (r.max() + r.min()), max(0.5 * (r.max() - r.min()), 1e-12)
        out[:, d] = np.clip((sines(x) - mid) / half, -1.0, 1.0)
        out_ref[:, d] = (r - mid) / half
    return out, out_ref


def _prefix_quat_product(dq: torch.Tensor) -> torch.Tensor:
    """Left-cumulative products ``P_i = dq_i (x) dq_{i-1} (x) ... (x) dq_0`` (Hillis-Steele scan).

    Shape: ``(N, 4) -> (N, 4)``.
    """
    p = dq.clone()
    d = 1
    while d < p.shape[0]:
        p = torch.cat((p[:d], quat_mul(p[d:], p[:-d])), dim=0)
        d *= 2
    return quat_canonical(p)


def bbox_corners(mesh) -> torch.Tensor:
    """The 8 corners of a mesh's axis-aligned bounding box, object frame, metres. Shape: ``(8, 3)`` float64."""
    lo, hi = np.asarray(mesh.bounds, dtype=np.float64)
    corners = np.array([[x, y, z] for x in (lo[0], hi[0]) for y in (lo[1], hi[1]) for z in (lo[2], hi[2])])
    return torch.from_numpy(corners)


def projected_bbox(poses: torch.Tensor, camera: Camera, corners: torch.Tensor) -> torch.Tensor:
    """Image bounding box ``[u_min, v_min, u_max, v_max]`` (pixels) of object-frame points.

    ``corners`` are the 8 corners of the mesh bounding box (their projected hull contains the mesh).
    Shape: ``(N, 7), camera, (M, 3) -> (N, 4)``.
    """
    R = quat_to_matrix(poses[:, 3:])
    pc = corners.to(poses.dtype) @ R.transpose(-1, -2) + poses[:, None, :3]
    uv = camera.project(pc)
    return torch.cat((uv.amin(1), uv.amax(1)), dim=-1)


def make_trajectory(
    motion: str,
    duration_s: float,
    seed: int,
    camera: Camera,
    mesh,
    *,
    dt_us: int = 100,
    depth_range: tuple[float, float] = (0.3, 0.7),
    margin_px: float | None = None,
) -> tuple[torch.Tensor, torch.Tensor]:
    """Seeded smooth random 6D trajectory of ``mesh`` fully in view of ``camera``.

    Args:
        motion: ``"regular"``, ``"fast"``, ``"turn"`` or ``"mixed"`` (see :data:`MOTION_GROUPS`).
        duration_s: length in seconds (> 0).
        seed: integer seed; the same arguments give bit-identical output.
        camera: the pinhole camera.
        mesh: ``trimesh.Trimesh`` in metres, object origin at its bounding-box centre.
        dt_us: sampling period, microseconds.
        depth_range: ``(z_min, z_max)`` metres; ``z_min`` is raised when the object would not fit (with a warning
            when that lifts the whole range: ``z_max`` then becomes ``z_min + 0.1``).
        margin_px: the projected bounding box keeps this distance to the image border
            (default ``max(2, 2 % of the smaller image side)``).

    Returns:
        ``t_us (N,) int64`` with ``t_us[0] = 0`` and ``poses (N, 7) float64``.
    """
    if motion not in MOTION_GROUPS:
        raise ValueError(f"motion must be one of {sorted(MOTION_GROUPS)}, got {motion!r}")
    if not duration_s > 0:
        raise ValueError(f"duration_s must be positive, got {duration_s}")
    if int(dt_us) <= 0:
        raise ValueError(f"dt_us must be a positive integer, got {dt_us}")
    if not isinstance(seed, (int, np.integer)) or isinstance(seed, bool):
        raise TypeError(f"seed must be an integer, got {type(seed).__name__}")
    group = MOTION_GROUPS[motion]
    margin = max(2.0, 0.02 * min(camera.width, camera.height)) if margin_px is None else float(margin_px)
    corners = bbox_corners(mesh)
    radius = float(corners.norm(dim=-1).max())
    f = max(camera.fx, camera.fy)

    # Nearest depth at which the object's bounding sphere spans at most 75 % of the smaller half-side.
    half_min = 0.5 * min(camera.width, camera.height) - margin
    z_fit = radius + f * radius / (0.75 * half_min)
    z_lo = max(depth_range[0], z_fit)
    z_hi = max(depth_range[1], z_lo + 0.1)
    if z_fit > depth_range[1]:
        warnings.warn(f"the object (bounding radius {radius:.3f} m) fits a {camera.width}x{camera.height} image with "
                      f"f = {f:g} px only from {z_fit:.2f} m: depth range {depth_range[0]:g}-{depth_range[1]:g} m "
                      f"raised to {z_lo:.2f}-{z_hi:.2f} m", stacklevel=2)
    r_px = f * radius / (z_lo - radius)

    n = int(round(duration_s * 1e6 / dt_us)) + 1
    t_us = torch.arange(n, dtype=torch.int64) * int(dt_us)
    t_s = t_us.numpy().astype(np.float64) / 1e6

    rng = np.random.default_rng(int(seed))
    # Image-speed profile and the arc length it must cover.
    prof = _smooth_unit(rng, t_s, *group.speed_freq_hz, 1)[0][:, 0]
    speed = group.speed_px_s[0] + 0.5 * (prof + 1.0) * (group.speed_px_s[1] - group.speed_px_s[0])
    arc = np.concatenate(([0.0], np.cumsum(0.5 * (speed[1:] + speed[:-1]) * np.diff(t_s))))
    # Random path shape (unit box), depth curve, angular velocity, initial orientation.
    path_f = rng.uniform(0.5, 1.5, (2, _N_SINES))
    path_phase = rng.uniform(0.0, 2.0 * math.pi, (2, _N_SINES))
    path_amp = rng.uniform(0.5, 1.0, (2, _N_SINES))
    depth = _smooth_unit(rng, t_s, *group.depth_freq_hz, 1)[0][:, 0]
    t_mid = t_s[:-1] + 0.5 * np.diff(t_s)
    omega, omega_ref = _smooth_unit(rng, t_mid, *group.rot_freq_hz, 3)
    if group.rot_median_deg_s is None:
        omega *= rng.uniform(0.8, 1.0) * math.radians(group.max_rot_deg_s) / np.linalg.norm(omega_ref, axis=1).max()
    else:
        omega *= math.radians(rng.uniform(*group.rot_median_deg_s)) / np.median(np.linalg.norm(omega, axis=1))
    q0 = quat_canonical(torch.from_numpy(rng.normal(size=4)))

    z = z_lo + 0.5 * (depth + 1.0) * (z_hi - z_lo)
    dq = quat_exp(torch.from_numpy(omega * np.diff(t_s)[:, None]))
    q = torch.cat((q0[None], quat_mul(_prefix_quat_product(dq), q0)), dim=0)

    centre = np.array([(camera.width - 1) / 2.0, (camera.height - 1) / 2.0])
    half = np.array([camera.width, camera.height]) / 2.0 - margin - r_px
    if (half <= 0).any():
        raise ValueError(f"object of radius {radius:.3f} m does not fit in a {camera.width}x{camera.height} camera")
    for shrink in 0.85 ** np.arange(30):
        uv = _arc_length_path(arc, path_f, path_phase, path_amp, centre, half * shrink)
        xyz = np.stack(((uv[:, 0] - camera.cx) * z / camera.fx, (uv[:, 1] - camera.cy) * z / camera.fy, z), 1)
        poses = torch.cat((torch.from_numpy(xyz), q), dim=1)
        box = projected_bbox(poses, camera, corners)
        inside = (box[:, :2] >= margin).all() and (box[:, 2] <= camera.width - 1 - margin).all() and (
            box[:, 3] <= camera.height - 1 - margin
        ).all()
        if inside:
            return t_us, poses
    raise ValueError("could not keep the object in view; use a larger depth_range or a smaller margin")


def _arc_length_path(arc, freq, phase, amp, centre, half) -> np.ndarray:
    """Pixel positions ``(N, 2)`` that walk the random curve with cumulative arc length ``arc`` (px),
    slowing down where the curve turns back on itself."""

    def curve(s):
        c = (amp[None] * np.sin(2.0 * math.pi * freq[None] * s[:, None, None] + phase[None])).sum(-1)
        return centre + half * c / amp.sum(-1)

    # Tabulate the curve's arc length finely (steps of at most ~0.1 px), extending until long enough.
    bound = 2.0 * math.pi * float((amp * freq).sum(-1).max() / amp.sum(-1).min()) * float(half.max())
    s_max = 4.0 * arc[-1] / max(bound, 1e-9) + 1.0
    while True:
        m = int(min(max(s_max * bound / 0.1, 1000), 4e6))
        s = np.linspace(0.0, s_max, m)
        p = curve(s)
        seg = np.linalg.norm(np.diff(p, axis=0), axis=1)
        # Floored arc length: where the curve nearly stops (a cusp, |c'| < floor) the object slows
        # down smoothly instead of flipping direction at full speed.
        length = np.concatenate(([0.0], np.cumsum(np.maximum(seg, 0.5 * np.median(seg)))))
        if length[-1] >= arc[-1] or s_max > 1e6:
            break
        s_max *= 2.0
    return curve(np.interp(arc, length, s))


SLIDE_S = 0.35  # leave_and_return: seconds the object takes to slide out of the view, and back


def back_on_path_s(start_s: float, away_s: float) -> float:
    """When :func:`leave_and_return`'s object, leaving at ``start_s`` for ``away_s`` seconds, is back on its path (s):
    ``start_s + away_s + 2 SLIDE_S``."""
    return start_s + away_s + 2 * SLIDE_S


def leave_and_return(t_us: torch.Tensor, poses: torch.Tensor, camera: Camera, mesh, start_s: float,
                     away_s: float) -> torch.Tensor:
    """The trajectory with an excursion out of the view and back: from ``start_s`` the object slides sideways (its
    image position eased over :data:`SLIDE_S` seconds, depth and rotation as they were) to beyond the nearer side
    border (its bounding sphere's image radius past it), stays out of view for ``away_s`` seconds, and slides back
    over :data:`SLIDE_S` seconds onto its own path: an object that leaves the view and returns, for a tracker's
    recovery.

    Shape: ``(N,), (N, 7) -> (N, 7)`` float64 (``t_us`` int64 microseconds; ``mesh`` in metres, as
    :func:`make_trajectory`'s).

    Example:
        >>> import torch, trimesh
        >>> cam = Camera.default()
        >>> t, poses = make_trajectory("regular", 1.0, 0, cam, trimesh.creation.box((0.1, 0.1, 0.1)))
        >>> away = leave_and_return(t, poses, cam, trimesh.creation.box((0.1, 0.1, 0.1)), 0.2, 0.2)
        >>> u = cam.project(away[:, :3])[:, 0]
        >>> bool(torch.equal(away[:2000], poses[:2000])), bool((u[5500:7500] > 640).all() or (u[5500:7500] < 0).all())
        (True, True)
    """
    if not (start_s >= 0 and away_s >= 0):
        raise ValueError(f"need start_s >= 0 and away_s >= 0 seconds, got {start_s}, {away_s}")
    t = t_us.to(torch.float64) / 1e6
    radius = float(bbox_corners(mesh).norm(dim=-1).max())

    def ease(a: float) -> torch.Tensor:
        x = ((t - a) / SLIDE_S).clamp(0.0, 1.0)
        return x * x * (3.0 - 2.0 * x)

    share = ease(start_s) - ease(start_s + SLIDE_S + away_s)  # 0 on the path, 1 out of view
    out = poses.to(torch.float64).clone()
    z = out[:, 2]
    u = camera.fx * out[:, 0] / z + camera.cx
    beyond = camera.fx * radius / (z - radius).clamp(min=1e-3) + 2.0  # the bounding sphere's image radius, and 2 px
    leaving = float(u[(share > 0).nonzero()[0, 0]]) if bool((share > 0).any()) else float(u[0])  # where it starts
    goal = camera.width - 1 + beyond if leaving >= (camera.width - 1) / 2 else -beyond
    out[:, 0] = torch.where(share > 0, ((u + share * (goal - u)) - camera.cx) * z / camera.fx, out[:, 0])
    return out


def pose_at(t_us: torch.Tensor, poses: torch.Tensor, query_us) -> torch.Tensor:
    """Poses of a trajectory at ``query_us`` (int64 microseconds; linear + slerp). Shape: ``(M,) -> (M, 7)``."""
    return interpolate_poses(t_us, poses, torch.as_tensor(query_us, dtype=torch.int64).reshape(-1))


def centroid_image_speed(t_us: torch.Tensor, poses: torch.Tensor, camera: Camera) -> torch.Tensor:
    """Image speed of the projected object origin between consecutive samples, pixels / s.

    Shape: ``(N,), (N, 7) -> (N - 1,)`` float64.
    """
    uv = camera.project(poses[:, :3].to(torch.float64))
    dt = torch.diff(t_us).to(torch.float64) / 1e6
    return torch.linalg.norm(torch.diff(uv, dim=0), dim=-1) / dt


def angular_speed(t_us: torch.Tensor, poses: torch.Tensor) -> torch.Tensor:
    """Angular speed between consecutive samples, degrees / s. Shape: ``(N,), (N, 7) -> (N - 1,)`` float64."""
    q = poses[:, 3:].to(torch.float64)
    dot = (q[1:] * q[:-1]).sum(-1).abs().clamp(max=1.0)
    angle = 2.0 * torch.acos(dot)
    dt = torch.diff(t_us).to(torch.float64) / 1e6
    return torch.rad2deg(angle) / dt


def motion_stats(t_us: torch.Tensor, poses: torch.Tensor, camera: Camera) -> dict:
    """Summary of centroid image speed (px/s) and angular speed (deg/s): mean, p10, median, p90, max.

    Returns ``{"image_speed_px_s": {...}, "angular_speed_deg_s": {...}}`` of plain floats.
    """
    if t_us.numel() < 2:
        raise ValueError("need at least two poses to measure speeds")

    def summary(x: torch.Tensor) -> dict:
        qs = torch.quantile(x, torch.tensor([0.1, 0.5, 0.9], dtype=x.dtype)).tolist()
        return {"mean": float(x.mean()), "p10": qs[0], "median": qs[1], "p90": qs[2], "max": float(x.max())}

    return {
        "image_speed_px_s": summary(centroid_image_speed(t_us, poses, camera)),
        "angular_speed_deg_s": summary(angular_speed(t_us, poses)),
    }
