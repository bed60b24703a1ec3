"""Quaternions and rigid poses.

Conventions, used everywhere in torchevtrack:

* A **pose** is the object in the camera frame: a camera-frame point is
  ``X_cam = R @ X_obj + t``. Camera axes follow OpenCV (x right, y down, z forward), metres.
* A pose tensor has shape ``(..., 7)`` laid out as ``[tx, ty, tz, qw, qx, qy, qz]``.
* Quaternions are Hamilton, scalar first ``(w, x, y, z)``, unit norm, and are returned with
  ``w >= 0`` where a function picks a sign.
* A twist ``[v, w]`` (``(..., 6)``) is the object's velocity in the camera frame: every object
  point moves as ``dP/dt = v + w x P`` and ``dR/dt = [w]x R``, so rotations are applied on the
  **left**: ``q(t + dt) = exp(w dt) (x) q(t)``. Integration: ``torchevtrack.stages.propagate``.
* File formats that store ``qx qy qz qw`` (TUM, CSV) are converted at the I/O boundary only.

Example:
    >>> import torch
    >>> from torchevtrack.geometry import pose_from_rt, transform_points
    >>> pose = pose_from_rt(torch.eye(3), torch.tensor([0.0, 0.0, 0.5]))
    >>> transform_points(pose, torch.zeros(1, 3))
    tensor([[0.0000, 0.0000, 0.5000]])
"""

from __future__ import annotations

import math

import numpy as np
import torch
from kornia.geometry.conversions import quaternion_to_rotation_matrix, rotation_matrix_to_quaternion

from torchevtrack.kernels import kernel

__all__ = [
    "quat_normalize",
    "quat_canonical",
    "quat_mul",
    "quat_conj",
    "quat_to_matrix",
    "matrix_to_quat",
    "quat_exp",
    "quat_log",
    "quat_rotate",
    "quat_slerp",
    "pose_from_rt",
    "pose_to_matrix",
    "matrix_to_pose",
    "pose_compose",
    "pose_inverse",
    "transform_points",
    "interpolate_poses",
    "perturb_pose",
    "check_pose",
    "nb_cross",
    "nb_quat_mul",
    "nb_quat_canonical",
    "nb_normalise_quaternions",
    "nb_quat_exp",
    "nb_quat_log",
    "nb_quat_rotate",
    "nb_quat_to_matrix",
]


def quat_normalize(q: torch.Tensor) -> torch.Tensor:
    """Unit quaternion. Shape: ``(..., 4) -> (..., 4)``."""
    return q / torch.linalg.vector_norm(q, dim=-1, keepdim=True).clamp_min(1e-12)


def quat_canonical(q: torch.Tensor) -> torch.Tensor:
    """Normalised quaternion with non-negative scalar part. Shape: ``(..., 4)``."""
    q = quat_normalize(q)
    return torch.where(q[..., :1] < 0, -q, q)


def quat_mul(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    """Hamilton product ``a (x) b`` of ``(w, x, y, z)`` quaternions (rotation ``b`` first).

    Component ``i`` is ``sum_k a_k (s_ik b_{j(i, k)})``, summed in the order ``k = 0..3`` (the textbook
    expansion ``aw bw - ax bx - ay by - az bz``, ...; all products formed in one broadcast multiply).

    Shape: ``(..., 4), (..., 4) -> (..., 4)`` with broadcasting.
    """
    sb = b.index_select(-1, _MUL_INDEX.to(b.device)) * _MUL_SIGN.to(b)
    p = a[..., None, :] * sb.unflatten(-1, (4, 4))
    return p[..., 0] + p[..., 1] + p[..., 2] + p[..., 3]


# quat_mul: row i lists the b component (and its sign) multiplying a_0 .. a_3 in component i of a (x) b.
_MUL_INDEX = torch.tensor([0, 1, 2, 3, 1, 0, 3, 2, 2, 3, 0, 1, 3, 2, 1, 0])
_MUL_SIGN = torch.tensor([1.0, -1.0, -1.0, -1.0, 1.0, 1.0, 1.0, -1.0, 1.0, -1.0, 1.0, 1.0, 1.0, 1.0, -1.0, 1.0])


def quat_conj(q: torch.Tensor) -> torch.Tensor:
    """Conjugate (the inverse of a unit quaternion). Shape: ``(..., 4)``."""
    return q * q.new_tensor([1.0, -1.0, -1.0, -1.0])


def quat_to_matrix(q: torch.Tensor) -> torch.Tensor:
    """Rotation matrix of a ``(w, x, y, z)`` quaternion. Shape: ``(..., 4) -> (..., 3, 3)``."""
    return quaternion_to_rotation_matrix(quat_normalize(q))


def matrix_to_quat(R: torch.Tensor) -> torch.Tensor:
    """Canonical ``(w, x, y, z)`` quaternion of a rotation matrix. Shape: ``(..., 3, 3) -> (..., 4)``."""
    return quat_canonical(rotation_matrix_to_quaternion(R.contiguous()))


def quat_exp(phi: torch.Tensor) -> torch.Tensor:
    """Quaternion of the rotation vector ``phi`` (axis * angle, radians).

    This is ``exp(phi / 2)`` of the pure quaternion ``(0, phi)``: ``(cos(a / 2), sin(a / 2) phi / a)``,
    ``a = |phi|``, and ``(1, phi / 2)`` where ``|phi|^2`` is 0 (the values of
    ``kornia.geometry.conversions.axis_angle_to_quaternion``, exactly, in fewer operations).
    Shape: ``(..., 3) -> (..., 4)``.
    """
    a0, a1, a2 = phi[..., 0:1], phi[..., 1:2], phi[..., 2:3]
    sq = a0 * a0 + a1 * a1 + a2 * a2
    pos = sq > 0.0
    angle = torch.where(pos, sq, 1.0).sqrt_()
    half = angle * 0.5
    k = torch.where(pos, half.sin() / angle, 0.5)
    return torch.cat((torch.where(pos, half.cos(), 1.0), phi * k), dim=-1)


def quat_log(q: torch.Tensor) -> torch.Tensor:
    """Rotation vector (radians) of a unit quaternion, angle in ``[0, pi]``. Shape: ``(..., 4) -> (..., 3)``.

    The values of ``kornia.geometry.conversions.quaternion_to_axis_angle`` of the canonical quaternion, bit for
    bit, in fewer operations.
    """
    q = quat_canonical(q)
    c = q[..., 0]
    s2 = q[..., 1] * q[..., 1] + q[..., 2] * q[..., 2] + q[..., 3] * q[..., 3]
    pos = s2 > 0.0
    s = torch.where(pos, s2, 0.0).sqrt_()
    two = 2.0 * torch.where(c < 0.0, torch.atan2(-s, -c), torch.atan2(s, c))
    k = torch.where(pos, two / s, torch.where(c != 0.0, 2.0 / c, 0.0))
    return q[..., 1:] * k[..., None] + 0.0


def quat_rotate(q: torch.Tensor, v: torch.Tensor) -> torch.Tensor:
    """Rotate vectors ``v`` by unit quaternions ``q``. Shape: ``(..., 4), (..., 3) -> (..., 3)``."""
    w, u = q[..., :1], q[..., 1:]
    uv = torch.linalg.cross(u.expand_as(v), v, dim=-1)
    return v + 2.0 * (w * uv + torch.linalg.cross(u.expand_as(v), uv, dim=-1))


def quat_slerp(q0: torch.Tensor, q1: torch.Tensor, tau: torch.Tensor | float) -> torch.Tensor:
    """Spherical linear interpolation along the shorter arc.

    Shape: ``(..., 4), (..., 4), (...) -> (..., 4)``; ``tau`` in ``[0, 1]``.
    """
    tau = torch.as_tensor(tau, dtype=q0.dtype, device=q0.device)[..., None]
    q0, q1 = quat_normalize(q0), quat_normalize(q1)
    dot = (q0 * q1).sum(-1, keepdim=True)
    q1 = torch.where(dot < 0, -q1, q1)
    dot = dot.abs().clamp(max=1.0)
    theta = torch.acos(dot)
    sin_theta = torch.sin(theta)
    small = sin_theta < 1e-6
    safe = torch.where(small, torch.ones_like(sin_theta), sin_theta)
    w0 = torch.where(small, 1.0 - tau, torch.sin((1.0 - tau) * theta) / safe)
    w1 = torch.where(small, tau, torch.sin(tau * theta) / safe)
    return quat_normalize(w0 * q0 + w1 * q1)


def pose_from_rt(R: torch.Tensor, t: torch.Tensor) -> torch.Tensor:
    """Pose ``[t, q]`` from a rotation matrix and translation. Shape: ``(..., 3, 3), (..., 3) -> (..., 7)``."""
    return torch.cat((t, matrix_to_quat(R).to(t.dtype)), dim=-1)


def pose_to_matrix(pose: torch.Tensor) -> torch.Tensor:
    """Homogeneous 4x4 transform of a pose. Shape: ``(..., 7) -> (..., 4, 4)``."""
    T = torch.zeros(*pose.shape[:-1], 4, 4, dtype=pose.dtype, device=pose.device)
    T[..., :3, :3] = quat_to_matrix(pose[..., 3:])
    T[..., :3, 3] = pose[..., :3]
    T[..., 3, 3] = 1.0
    return T


def matrix_to_pose(T: torch.Tensor) -> torch.Tensor:
    """Pose of a homogeneous transform. Shape: ``(..., 4, 4) -> (..., 7)``."""
    return pose_from_rt(T[..., :3, :3], T[..., :3, 3])


def pose_compose(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    """Composition ``a * b`` (apply ``b`` first). Shape: ``(..., 7), (..., 7) -> (..., 7)``."""
    t = quat_rotate(a[..., 3:], b[..., :3]) + a[..., :3]
    return torch.cat((t, quat_canonical(quat_mul(a[..., 3:], b[..., 3:]))), dim=-1)


def pose_inverse(pose: torch.Tensor) -> torch.Tensor:
    """Inverse pose. Shape: ``(..., 7) -> (..., 7)``."""
    qi = quat_conj(pose[..., 3:])
    return torch.cat((-quat_rotate(qi, pose[..., :3]), quat_canonical(qi)), dim=-1)


def transform_points(pose: torch.Tensor, points: torch.Tensor) -> torch.Tensor:
    """Map object points into the camera frame.

    Shape: ``(..., 7), (..., N, 3) -> (..., N, 3)``.
    """
    R = quat_to_matrix(pose[..., 3:])
    return points @ R.transpose(-1, -2) + pose[..., None, :3]


def interpolate_poses(times: torch.Tensor, poses: torch.Tensor, query: torch.Tensor) -> torch.Tensor:
    """Poses at ``query`` times: linear in translation, slerp in rotation.

    Times are int64 microseconds (or any monotonic integer / float64 unit, the same for both).
    Queries outside ``[times[0], times[-1]]`` raise: nothing is extrapolated.

    Shape: ``(N,), (N, 7), (M,) -> (M, 7)``.
    """
    if times.ndim != 1 or poses.shape != (times.shape[0], 7):
        raise ValueError(f"expected times (N,) and poses (N, 7), got {tuple(times.shape)} and {tuple(poses.shape)}")
    if times.numel() == 0:
        raise ValueError("cannot interpolate an empty trajectory")
    if bool((query < times[0]).any() or (query > times[-1]).any()):
        raise ValueError(
            f"query times [{int(query.min())}, {int(query.max())}] leave the trajectory range "
            f"[{int(times[0])}, {int(times[-1])}]: no extrapolation"
        )
    i1 = torch.searchsorted(times, query, right=False).clamp(1, max(times.numel() - 1, 1))
    i0 = i1 - 1
    if times.numel() == 1:
        return poses.expand(query.shape[0], 7).clone()
    span = (times[i1] - times[i0]).to(torch.float64)
    tau = ((query - times[i0]).to(torch.float64) / span.clamp_min(1e-12)).clamp(0, 1).to(poses.dtype)
    t = poses[i0, :3] + (poses[i1, :3] - poses[i0, :3]) * tau[:, None]
    q = quat_slerp(poses[i0, 3:], poses[i1, 3:], tau)
    return torch.cat((t, quat_canonical(q)), dim=-1)


def perturb_pose(pose: torch.Tensor, translation_m: float, rotation_rad: float,
                 generator: torch.Generator | None = None) -> torch.Tensor:
    """``pose`` shifted by exactly ``translation_m`` along a uniformly random direction and turned by exactly
    ``rotation_rad`` about a uniformly random axis through the object origin (``q' = exp(angle * axis) (x) q``,
    the axis in camera coordinates): the start-pose error of a robustness test.

    One independent draw per pose, from ``generator`` (float64 normals: direction first, then axis).
    Shape: ``(..., 7) -> (..., 7)`` in the dtype of ``pose``.

    Example:
        >>> import torch
        >>> pose = torch.tensor([0.0, 0.0, 0.5, 1.0, 0.0, 0.0, 0.0])
        >>> moved = perturb_pose(pose, 0.002, 0.01, torch.Generator().manual_seed(0))
        >>> round(float((moved[:3] - pose[:3]).norm()), 6)
        0.002
    """
    if not (math.isfinite(translation_m) and translation_m >= 0 and math.isfinite(rotation_rad)
            and rotation_rad >= 0):
        raise ValueError(f"translation_m and rotation_rad must be finite and >= 0, got {translation_m!r}, "
                         f"{rotation_rad!r}")
    shape = (*pose.shape[:-1], 3)
    direction = torch.randn(shape, generator=generator, dtype=torch.float64)
    axis = torch.randn(shape, generator=generator, dtype=torch.float64)
    direction /= torch.linalg.vector_norm(direction, dim=-1, keepdim=True)
    axis /= torch.linalg.vector_norm(axis, dim=-1, keepdim=True)
    p = pose.double()
    t = p[..., :3] + translation_m * direction
    q = quat_canonical(quat_mul(quat_exp(rotation_rad * axis), p[..., 3:]))
    return torch.cat((t, q), -1).to(pose.dtype)


def check_pose(pose: torch.Tensor, name: str = "pose", atol: float = 1e-3) -> torch.Tensor:
    """Validate poses ``(..., 7)``: finite, unit quaternion (to ``atol``), object in front of the camera.

    Returns the pose with its quaternion renormalised; raises ``ValueError`` with the reason.
    """
    pose = torch.as_tensor(pose)
    if pose.shape[-1:] != (7,):
        raise ValueError(f"{name} must have shape (..., 7) [tx, ty, tz, qw, qx, qy, qz], got {tuple(pose.shape)}")
    if not torch.isfinite(pose).all():
        raise ValueError(f"{name} contains NaN or infinite values")
    norm = pose[..., 3:].norm(dim=-1)
    if ((norm - 1).abs() > atol).any():
        raise ValueError(f"{name} quaternion is not unit norm (|q| = {norm.flatten().tolist()})")
    if (pose[..., 2] <= 0).any():
        raise ValueError(f"{name} places the object behind the camera (tz <= 0)")
    return torch.cat((pose[..., :3], quat_canonical(pose[..., 3:])), dim=-1)


# -- scalar kernels --------------------------------------------------------------------------------
# The same operations for the compiled (numba) kernels of the filters, the pose propagation, the template search
# and the renderers: on one quaternion / vector at a time (float scalars in, a tuple of floats out, inlined into
# their callers), and nb_normalise_quaternions on an array of poses in place. Each follows its tensor function
# above operation by operation, so the two agree to float64 rounding.


@kernel(inline="always")
def nb_cross(a0, a1, a2, b0, b1, b2):
    """``a x b`` (as :func:`torch.linalg.cross`)."""
    return a1 * b2 - a2 * b1, a2 * b0 - a0 * b2, a0 * b1 - a1 * b0


@kernel(inline="always")
def nb_quat_mul(a0, a1, a2, a3, b0, b1, b2, b3):
    """:func:`quat_mul` (the same sums in the same order)."""
    return (a0 * b0 - a1 * b1 - a2 * b2 - a3 * b3,
            a0 * b1 + a1 * b0 + a2 * b3 - a3 * b2,
            a0 * b2 - a1 * b3 + a2 * b0 + a3 * b1,
            a0 * b3 + a1 * b2 - a2 * b1 + a3 * b0)


@kernel(inline="always")
def nb_quat_canonical(q0, q1, q2, q3):
    """:func:`quat_canonical`."""
    n = max(math.sqrt(q0 * q0 + q1 * q1 + q2 * q2 + q3 * q3), 1e-12)
    q0, q1, q2, q3 = q0 / n, q1 / n, q2 / n, q3 / n
    if q0 < 0.0:
        return -q0, -q1, -q2, -q3
    return q0, q1, q2, q3


@kernel
def nb_normalise_quaternions(p, norm):
    """Divide the quaternions of poses ``p`` ``(B, 7)`` by their norms (squares summed in order) in place, the norms
    into ``norm`` ``(B,)``."""
    for b in range(p.shape[0]):
        n = math.sqrt(p[b, 3] * p[b, 3] + p[b, 4] * p[b, 4] + p[b, 5] * p[b, 5] + p[b, 6] * p[b, 6])
        norm[b] = n
        for k in range(3, 7):
            p[b, k] /= n


@kernel(inline="always")
def nb_quat_exp(a0, a1, a2):
    """:func:`quat_exp`."""
    sq = a0 * a0 + a1 * a1 + a2 * a2
    if sq > 0.0:
        angle = math.sqrt(sq)
        half = angle * 0.5
        k = math.sin(half) / angle
        return math.cos(half), a0 * k, a1 * k, a2 * k
    return 1.0, a0 * 0.5, a1 * 0.5, a2 * 0.5


@kernel(inline="always")
def nb_quat_log(q0, q1, q2, q3):
    """:func:`quat_log` (of the canonical quaternion)."""
    c, x, y, z = nb_quat_canonical(q0, q1, q2, q3)
    s2 = x * x + y * y + z * z
    if s2 > 0.0:
        s = math.sqrt(s2)
        two = 2.0 * (math.atan2(-s, -c) if c < 0.0 else math.atan2(s, c))
        k = two / s
    else:
        k = 2.0 / c if c != 0.0 else 0.0
    return x * k + 0.0, y * k + 0.0, z * k + 0.0


@kernel(inline="always")
def nb_quat_rotate(q0, q1, q2, q3, v0, v1, v2):
    """:func:`quat_rotate`."""
    c0, c1, c2 = nb_cross(q1, q2, q3, v0, v1, v2)
    d0, d1, d2 = nb_cross(q1, q2, q3, c0, c1, c2)
    return v0 + 2.0 * (q0 * c0 + d0), v1 + 2.0 * (q0 * c1 + d1), v2 + 2.0 * (q0 * c2 + d2)


@kernel
def nb_quat_to_matrix(w, x, y, z):
    """Rotation matrix ``(3, 3)`` of the unit quaternion ``(w, x, y, z)`` (:func:`quat_to_matrix` without the
    normalisation)."""
    return np.array([[1.0 - 2.0 * (y * y + z * z), 2.0 * (x * y - w * z), 2.0 * (x * z + w * y)],
                     [2.0 * (x * y + w * z), 1.0 - 2.0 * (x * x + z * z), 2.0 * (y * z - w * x)],
                     [2.0 * (x * z - w * y), 2.0 * (y * z + w * x), 1.0 - 2.0 * (x * x + y * y)]])
