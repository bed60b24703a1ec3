"""Stage 4: pose propagation with the velocity-filter twist.

The twist ``[v, w]`` is the one the interaction matrix assumes (:func:`torchevtrack.camera.interaction_matrix`):
every object point ``P`` (camera frame) moves as ``dP/dt = v + w x P``. ``v`` is therefore the velocity of
the object point that momentarily sits at the camera origin (the paper's definition of ``v_ot``), not the
velocity of the object origin. For a twist held constant over ``dt`` the exact motion is the SE(3)
exponential applied on the left::

    T(t + dt) = exp([v, w]^ dt) @ T(t)
    q+ = exp(w dt) (x) q
    t+ = exp(w dt) t + V(w dt) v dt,   V(phi) = I + (1 - cos a) / a^2 [phi]x + (a - sin a) / a^3 [phi]x^2

so the object origin moves with ``dt/dt = v + w x t``. The paper's Eq. 6 (``t+ = t + v dt``) drops ``w x t``, which at a depth of 0.5 m and 1 rad/s is an
error of 0.5 m/s; it is only right when the object origin sits at the camera centre.

The stage holds no configuration or state, so it is a plain function (no Module).

Example:
    >>> import torch
    >>> from torchevtrack.stages.propagate import propagate
    >>> pose = torch.tensor([[0.0, 0.0, 0.5, 1.0, 0.0, 0.0, 0.0]], dtype=torch.float64)
    >>> twist = torch.tensor([[0.0, 0.0, 0.0, 0.0, 1.0, 0.0]], dtype=torch.float64)  # 1 rad/s about y
    >>> propagate(pose, twist, 1e-3)[0, :3]  # the origin moves along +x by w x t = 0.5 m/s
    tensor([0.0005, 0.0000, 0.5000], dtype=torch.float64)
"""

from __future__ import annotations

import math

import numpy as np
import torch

from torchevtrack.geometry import (
    nb_cross,
    nb_quat_canonical,
    nb_quat_exp,
    nb_quat_log,
    nb_quat_mul,
    nb_quat_rotate,
    quat_exp,
    quat_rotate,
)
from torchevtrack.kernels import kernel

__all__ = ["se3_exp_apply", "propagate", "propagate_kernel", "propagate_step", "twist_between", "twist_between_kernel",
           "invalid_poses", "valid_pose"]


def se3_exp_apply(xi: torch.Tensor, points: torch.Tensor) -> torch.Tensor:
    """Apply the rigid motion ``exp(xi^)`` (tangent ``xi = [rho, phi]``, ``phi`` a rotation vector) to points.

    Returns ``exp(phi) points + V(phi) rho``. Shape: ``(..., 6), (..., 3) -> (..., 3)``.
    """
    rho, phi = xi[..., :3], xi[..., 3:]
    a2 = (phi * phi).sum(-1, keepdim=True)
    small = a2 < 1e-8
    a2s = torch.where(small, torch.ones_like(a2), a2)
    a = a2s.sqrt()
    c1 = torch.where(small, 0.5 - a2 / 24.0, (1.0 - torch.cos(a)) / a2s)
    c2 = torch.where(small, 1.0 / 6.0 - a2 / 120.0, (a - torch.sin(a)) / (a2s * a))
    pr = torch.linalg.cross(phi, rho, dim=-1)
    trans = rho + c1 * pr + c2 * torch.linalg.cross(phi, pr, dim=-1)
    return quat_rotate(quat_exp(phi), points) + trans


@kernel
def propagate_kernel(pose, twist, dt, out):
    """:func:`propagate` row by row, unchecked, for compiled callers: float64 numpy ``pose (N, 7)``, ``twist (N, 6)``
    and ``dt (N,)`` seconds into ``out (N, 7)`` (canonical quaternions)."""
    for i in range(pose.shape[0]):
        T = dt[i]
        r0, r1, r2 = twist[i, 0] * T, twist[i, 1] * T, twist[i, 2] * T
        p0, p1, p2 = twist[i, 3] * T, twist[i, 4] * T, twist[i, 5] * T
        a2 = (p0 * p0 + p1 * p1) + p2 * p2
        if a2 < 1e-8:
            c1, c2 = 0.5 - a2 / 24.0, 1.0 / 6.0 - a2 / 120.0
        else:
            a = math.sqrt(a2)
            c1, c2 = (1.0 - math.cos(a)) / a2, (a - math.sin(a)) / (a2 * a)
        e0, e1, e2 = nb_cross(p0, p1, p2, r0, r1, r2)
        f0, f1, f2 = nb_cross(p0, p1, p2, e0, e1, e2)
        q0, q1, q2, q3 = nb_quat_exp(p0, p1, p2)
        t0, t1, t2 = nb_quat_rotate(q0, q1, q2, q3, pose[i, 0], pose[i, 1], pose[i, 2])
        out[i, 0] = t0 + (r0 + c1 * e0 + c2 * f0)
        out[i, 1] = t1 + (r1 + c1 * e1 + c2 * f1)
        out[i, 2] = t2 + (r2 + c1 * e2 + c2 * f2)
        q0, q1, q2, q3 = nb_quat_mul(q0, q1, q2, q3, pose[i, 3], pose[i, 4], pose[i, 5], pose[i, 6])
        out[i, 3], out[i, 4], out[i, 5], out[i, 6] = nb_quat_canonical(q0, q1, q2, q3)


@kernel
def twist_between_kernel(start, end, dt, out):
    """:func:`twist_between` row by row, unchecked, for compiled callers: float64 numpy ``start, end (N, 7)`` and
    ``dt (N,)`` seconds into ``out (N, 6)`` ``[v (m/s), w (rad/s)]``."""
    for i in range(start.shape[0]):
        q0, q1, q2, q3 = nb_quat_mul(end[i, 3], end[i, 4], end[i, 5], end[i, 6],
                                     start[i, 3], -start[i, 4], -start[i, 5], -start[i, 6])
        p0, p1, p2 = nb_quat_log(q0, q1, q2, q3)
        s0, s1, s2 = nb_quat_rotate(q0, q1, q2, q3, start[i, 0], start[i, 1], start[i, 2])
        d0, d1, d2 = end[i, 0] - s0, end[i, 1] - s1, end[i, 2] - s2
        a2 = (p0 * p0 + p1 * p1) + p2 * p2
        if a2 < 1e-8:
            c = 1.0 / 12.0 + a2 / 720.0
        else:
            a = math.sqrt(a2)
            c = (1.0 - a * math.sin(a) / (2.0 * (1.0 - math.cos(a)))) / a2
        e0, e1, e2 = nb_cross(p0, p1, p2, d0, d1, d2)
        f0, f1, f2 = nb_cross(p0, p1, p2, e0, e1, e2)
        T = dt[i]
        out[i, 0] = (d0 - 0.5 * e0 + c * f0) / T
        out[i, 1] = (d1 - 0.5 * e1 + c * f1) / T
        out[i, 2] = (d2 - 0.5 * e2 + c * f2) / T
        out[i, 3], out[i, 4], out[i, 5] = p0 / T, p1 / T, p2 / T


def _rows(a: torch.Tensor, b: torch.Tensor, dt, na: int, nb: int):
    """``a (..., na)``, ``b (..., nb)`` and ``dt`` (float, ``()`` or ``(...)``) broadcast over their leading dims,
    as contiguous float64 numpy rows ``(N, na)``, ``(N, nb)``, ``(N,)``; and the leading shape and the dtype.

    ``dt`` comes read-only, as the tracker's compiled steps pass their periods (:func:`~torchevtrack.stages.periods`):
    the kernels then compile one signature for both kinds of caller, not two."""
    dtype = a.dtype
    if not isinstance(dt, torch.Tensor) and a.ndim == 2 and b.shape[:-1] == a.shape[:-1]:
        lead = a.shape[:-1]
        dt = np.full(lead[0], float(dt), dtype=np.float64)
    else:
        dt = torch.as_tensor(dt, dtype=torch.float64).detach()
        # numpy's: torch.broadcast_shapes' first call in a process imports for ~0.5 s (a stall inside a run)
        lead = np.broadcast_shapes(a.shape[:-1], b.shape[:-1], dt.shape)
        a, b = a.expand(*lead, na), b.expand(*lead, nb)
        dt = dt.expand(lead).reshape(-1).contiguous().numpy()
    dt = dt.view()
    dt.flags.writeable = False
    return _f64_rows(a, na), _f64_rows(b, nb), dt, lead, dtype


def _f64_rows(a: torch.Tensor, n: int) -> np.ndarray:
    """Contiguous float64 numpy rows ``(N, n)`` of ``a`` (a view when it already is one)."""
    if a.dtype != torch.float64 or a.ndim != 2 or not a.is_contiguous() or a.requires_grad:
        a = a.detach().to(torch.float64).reshape(-1, n).contiguous()
    return a.numpy()


def propagate(pose: torch.Tensor, twist: torch.Tensor, dt: torch.Tensor | float) -> torch.Tensor:
    """Move poses by a camera-frame twist held constant for ``dt`` seconds (exact SE(3) exponential).

    Args:
        pose: ``(B, 7)`` object-in-camera poses ``[t (m), q (w, x, y, z)]``.
        twist: ``(B, 6)`` ``[v (m/s), w (rad/s)]`` with ``dP/dt = v + w x P`` for object points ``P``.
        dt: seconds, a float or a ``(B,)`` tensor (relative time, float64 recommended).

    Returns:
        ``(B, 7)`` propagated poses (canonical quaternions, ``qw >= 0``).

    Computed in float64 (a compiled kernel, row by row: :func:`se3_exp_apply` on the position, ``exp(w dt) (x) q``
    on the orientation) and returned in the dtype of ``pose``.

    Shape: ``(B, 7), (B, 6), () or (B,) -> (B, 7)``; any leading dims broadcast like ``B``.
    """
    if not isinstance(pose, torch.Tensor) or pose.shape[-1:] != (7,):
        raise ValueError(f"pose must be a tensor of shape (B, 7), got {getattr(pose, 'shape', type(pose))}")
    if not isinstance(twist, torch.Tensor) or twist.shape[-1:] != (6,):
        raise ValueError(f"twist must be a tensor of shape (B, 6), got {getattr(twist, 'shape', type(twist))}")
    p, tw, dt, lead, dtype = _rows(pose, twist, dt, 7, 6)
    out = torch.empty(*lead, 7, dtype=torch.float64)
    propagate_kernel(p, tw, dt, out.view(-1, 7).numpy())
    return out if dtype == torch.float64 else out.to(dtype)


def twist_between(start: torch.Tensor, end: torch.Tensor, dt: torch.Tensor | float) -> torch.Tensor:
    """The constant twist that :func:`propagate` needs to move ``start`` to ``end`` in ``dt`` seconds.

    The exact SE(3) logarithm of ``T_end T_start^-1``, divided by ``dt``: ``w = log(q_end q_start^-1) / dt``
    and ``v = V(phi)^-1 (t_end - exp(phi) t_start) / dt`` with ``phi = w dt``. Computed in float64 (a compiled
    kernel) and returned in the dtype of ``start``.

    Shape: ``(..., 7), (..., 7), () or (...) -> (..., 6)`` ``[v (m/s), w (rad/s)]``.
    """
    s, e, dt, lead, dtype = _rows(start, end, dt, 7, 7)
    out = torch.empty(*lead, 6, dtype=torch.float64)
    twist_between_kernel(s, e, dt, out.view(-1, 6).numpy())
    return out if dtype == torch.float64 else out.to(dtype)


@kernel
def valid_pose(pose, min_depth):
    """A pose ``(7,)`` is valid: finite, with the object centre farther than ``min_depth`` (metres)."""
    ok = pose[2] > min_depth
    for j in range(7):
        ok = ok and np.isfinite(pose[j])
    return ok


@kernel
def _invalid_kernel(pose, min_depth, out):
    for b in range(pose.shape[0]):
        out[b] = not valid_pose(pose[b], min_depth[b])


def invalid_poses(pose: torch.Tensor, min_depth: torch.Tensor) -> torch.Tensor:
    """The poses the tracker rejects (as a prediction, an output or a start): not finite, or the object centre at or
    nearer than ``min_depth`` (m).

    Shape: ``(B, 7), (B,) -> (B,)`` bool.
    """
    out = np.empty(pose.shape[0], dtype=np.bool_)
    _invalid_kernel(pose.detach().double().numpy(), min_depth.detach().double().numpy(), out)
    return torch.from_numpy(out)


@kernel
def propagate_step(pose, twist, dt, min_depth, predicted, rejected):
    """:func:`propagate` of ``pose`` ``(B, 7)`` by ``twist`` ``(B, 6)`` over ``dt`` ``(B,)`` seconds into ``predicted``,
    unchecked; where that is not a valid pose (:func:`valid_pose` with ``min_depth`` ``(B,)``) the pose itself
    with zero twist (``twist`` is written), and ``rejected`` ``(B,)`` says so."""
    propagate_kernel(pose, twist, dt, predicted)
    for b in range(pose.shape[0]):
        rejected[b] = not valid_pose(predicted[b], min_depth[b])
        if rejected[b]:
            predicted[b] = pose[b]
            twist[b] = 0.0
