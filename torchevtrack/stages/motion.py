"""Steps 2 and 3 of an update in one compiled call: the twist of each element and its propagated pose.

:func:`motion_step` runs, as one compiled call of the stages' own kernels, the small per-element operations between
the flow and the render: the velocity filter's prediction and update, the twist back about the camera, the
propagation and the validity check. Its results equal those of the stage-by-stage calls exactly
(``tests/test_motion.py``):

- ``source = "flow"`` (the paper): :meth:`VelocityKF.predict <torchevtrack.stages.velocity.VelocityKF.predict>`;
  the valid flow vectors slower than ``max_speed``; their depth from the last render
  (:func:`~torchevtrack.stages.velocity.sample_depth`); :meth:`VelocityKF.update
  <torchevtrack.stages.velocity.VelocityKF.update>` about the object centre; plus the correction feedback
  ``b`` if given; :func:`~torchevtrack.stages.velocity.shift_twist` back to ``[v, w]``.
- ``source = "poses"``: :func:`~torchevtrack.stages.propagate.twist_between` the last two poses.
- ``source = "none"``: zero twist.
- then :func:`~torchevtrack.stages.propagate.propagate` by ``dt``; a prediction that is not finite or puts the
  object centre at or nearer than ``min_depth`` is replaced by the pose itself, with zero twist.
"""

from __future__ import annotations

from typing import Callable, NamedTuple

import numba
import numpy as np
import torch

from torchevtrack.stages import periods
from torchevtrack.stages.flow import FlowField
from torchevtrack.stages.propagate import _propagate_kernel, _twist_between_kernel
from torchevtrack.stages.velocity import (
    VelocityKF,
    _kf_predict_kernel,
    _kf_update_kernel,
    _sample_depth_kernel,
    _shift_twist_kernel,
)

__all__ = ["Motion", "bind_motion", "invalid_poses", "motion_step", "SOURCES"]

SOURCES = ("flow", "poses", "none")


class Motion(NamedTuple):
    """Result of :func:`motion_step`.

    Attributes:
        predicted: ``(B, 7)`` float64 propagated poses ``[t (m), q (w, x, y, z)]``.
        twist: ``(B, 6)`` float64 camera-frame twist ``[v (m/s), w (rad/s)]`` they were propagated with.
        n_vectors: ``(B,)`` int64 flow vectors the velocity filter weighed (0 unless ``source = "flow"``).
        rejected: ``(B,)`` bool, the prediction was not valid and the pose was kept.
    """

    predicted: torch.Tensor
    twist: torch.Tensor
    n_vectors: torch.Tensor
    rejected: torch.Tensor


def motion_step(source: str, pose: torch.Tensor, prev_pose: torch.Tensor, dt: float, min_depth: torch.Tensor, *,
                kf: VelocityKF | None = None, flow: FlowField | None = None, max_speed: float = float("inf"),
                depth: torch.Tensor | None = None, origin: torch.Tensor | None = None, radius: int = 2,
                feedback: torch.Tensor | None = None) -> Motion:
    """The twist and propagated pose of every element (see the module docstring); with ``source = "flow"`` the
    filter ``kf`` is updated in place.

    Args:
        source: ``"flow"``, ``"poses"`` or ``"none"`` (:data:`SOURCES`).
        pose, prev_pose: ``(B, 7)`` float64 current and previous poses.
        dt: update period, seconds.
        min_depth: ``(B,)`` float64, the nearest valid object-centre depth (m).
        kf, flow, max_speed, depth, origin, radius, feedback: for ``source = "flow"``: the velocity filter; the
            flow field ``(B, G)``; the speed (px/s) from which a flow vector is dropped; the last render's
            depth ``(B, h, w)`` float32 with its top-left pixel ``origin`` ``(B, 2)`` int64 and the radius of
            :func:`~torchevtrack.stages.velocity.sample_depth`; the feedback twist ``(B, 6)`` about the centre
            added to the filter's (or ``None``).

    Raises:
        torch.linalg.LinAlgError: a velocity filter's covariance is not positive definite.

    Shape: ``(B, 7), (B, 7), (), (B,) -> Motion``.
    """
    if source not in SOURCES:
        raise ValueError(f"source must be one of {SOURCES}, got {source!r}")
    B = pose.shape[0]
    if pose.shape != (B, 7) or prev_pose.shape != (B, 7) or pose.dtype != torch.float64 \
            or prev_pose.dtype != torch.float64 or min_depth.shape != (B,):
        raise ValueError(f"expected float64 pose and prev_pose (B, 7) and min_depth (B,), got {tuple(pose.shape)}, "
                         f"{tuple(prev_pose.shape)}, {tuple(min_depth.shape)}")
    by_flow = source == "flow"
    if by_flow and (kf is None or flow is None or depth is None or origin is None):
        raise ValueError("source='flow' needs kf, flow, depth and origin")
    G = flow.valid.shape[1] if by_flow else 0
    if by_flow and (kf.batch_size != B or flow.valid.shape != (B, G) or flow.valid.dtype != torch.bool
                    or flow.uv.shape != (B, G, 2) or flow.flow.shape != (B, G, 2) or depth.ndim != 3
                    or depth.shape[0] != B or origin.shape != (B, 2) or origin.dtype != torch.int64
                    or (feedback is not None and feedback.shape != (B, 6))):
        raise ValueError(f"expected for B={B}: a filter of B, flow uv and flow (B, G, 2) with a bool valid (B, G), "
                         "depth (B, h, w), int64 origin (B, 2) and feedback (B, 6)")
    run = bind_motion(source, pose.numpy(), prev_pose.numpy(), float(dt), min_depth.numpy(), kf=kf, groups=G,
                      max_speed=max_speed, radius=radius, feedback=None if feedback is None else feedback.numpy())
    out = run(flow.uv.numpy(), flow.flow.numpy(), flow.valid.numpy(), depth.numpy(), origin.numpy()) if by_flow \
        else run()
    return Motion(*(torch.from_numpy(a) for a in out))


def bind_motion(source: str, pose: np.ndarray, prev_pose: np.ndarray, dt: float, min_depth: np.ndarray, *,
                kf: VelocityKF | None = None, groups: int = 0, max_speed: float = float("inf"), radius: int = 2,
                feedback: np.ndarray | None = None) -> Callable[..., tuple[np.ndarray, ...]]:
    """:func:`motion_step` bound to its state, unchecked, for a caller that runs it every update on the same
    buffers (the tracker): the arrays are numpy views of the tensors :func:`motion_step` takes, read at each call
    (``kf``'s state is updated in place); ``groups`` is the flow's number of blocks ``G``.

    Returns ``run(uv, flow, valid, depth, origin)`` (the flow field's arrays and the render's, for ``source =
    "flow"``; ``run()`` otherwise) giving new arrays ``(predicted, twist, n_vectors, rejected)`` as :class:`Motion`.
    """
    B = pose.shape[0]
    dts = periods(B, float(dt))
    if source != "flow":
        code = SOURCES.index(source)

        def run() -> tuple[np.ndarray, ...]:
            out = np.empty((B, 7)), np.empty((B, 6)), np.zeros(B, dtype=np.int64), np.empty(B, dtype=np.bool_)
            _motion_kernel(code, pose, prev_pose, dts, min_depth, *_NO_FLOW, *out)
            return out
        return run
    c = kf.camera
    x, P, Q = kf.x.numpy(), kf.P.numpy(), kf.Q.numpy()
    fb = _NO_FEEDBACK if feedback is None else feedback
    scratch = (np.empty((B, groups), dtype=np.bool_), np.empty((B, groups)), np.empty((B, groups)),
               np.empty((B, groups)), np.empty(B, dtype=np.bool_))
    speed, r, iters, k, min_vectors = float(max_speed), int(radius), kf.iters, kf.k, kf.min_vectors

    def run(uv, flow, valid, depth, origin) -> tuple[np.ndarray, ...]:
        out = np.empty((B, 7)), np.empty((B, 6)), np.zeros(B, dtype=np.int64), np.empty(B, dtype=np.bool_)
        bad = _motion_kernel(0, pose, prev_pose, dts, min_depth, x, P, kf.rho, Q, uv, flow, valid, speed, depth,
                             origin, r, c.fx, c.fy, c.cx, c.cy, kf.r_px, iters, k, min_vectors, kf.normal, fb,
                             feedback is not None, *scratch, *out)
        if bad >= 0:
            raise torch.linalg.LinAlgError(f"kf_update: the covariance of filter {bad} is not positive-definite")
        return out
    return run


def invalid_poses(pose: torch.Tensor, min_depth: torch.Tensor) -> torch.Tensor:
    """The poses :func:`motion_step` (and :func:`~torchevtrack.stages.output.output_step`) reject: not finite, or
    the object centre at or nearer than ``min_depth`` (m).

    Shape: ``(B, 7), (B,) -> (B,)`` bool.
    """
    out = np.empty(pose.shape[0], dtype=np.bool_)
    _invalid_kernel(pose.detach().double().numpy(), min_depth.detach().double().numpy(), out)
    return torch.from_numpy(out)


@numba.njit(cache=True, nogil=True)
def _render_ahead_kernel(predicted, twist, dt, min_depth, ahead, ahead_ok, now, now32):
    """The tracker's ``render.ahead`` poses, row by row: ``now`` (float64 and ``now32`` float32) is ``ahead`` where
    ``ahead_ok`` (the last update's poses for this one), else ``predicted``; then ``ahead`` becomes ``predicted``
    moved on by ``twist`` for ``dt`` (:func:`~torchevtrack.stages.propagate.propagate`) and ``ahead_ok`` whether
    that is a valid pose (the next update's).

    Shape: ``predicted (B, 7)``, ``twist (B, 6)``, ``dt, min_depth (B,)``; ``ahead (B, 7)``, ``ahead_ok (B,)`` in and
    out; ``now, now32 (B, 7)`` out.
    """
    for b in range(predicted.shape[0]):
        src = ahead[b] if ahead_ok[b] else predicted[b]
        for j in range(7):
            now[b, j] = src[j]
            now32[b, j] = np.float32(src[j])
    _propagate_kernel(predicted, twist, dt, ahead)
    for b in range(predicted.shape[0]):
        ahead_ok[b] = _valid_pose(ahead[b], min_depth[b])


@numba.njit(cache=True, nogil=True)
def _invalid_kernel(pose, min_depth, out):
    for b in range(pose.shape[0]):
        out[b] = not _valid_pose(pose[b], min_depth[b])


_NO_FEEDBACK = np.zeros((1, 6))
# The flow arguments of _motion_kernel when the source is not the flow (not read).
_NO_FLOW = (np.zeros((1, 6)), np.zeros((1, 6, 6)), 0.0, np.zeros((6, 6)), np.zeros((1, 0, 2), np.float32),
            np.zeros((1, 0, 2), np.float32), np.zeros((1, 0), np.bool_), 0.0, np.zeros((1, 1, 1), np.float32),
            np.zeros((1, 2), np.int64), 0, 1.0, 1.0, 0.0, 0.0, 1.0, 0, 1.0, 0, False, _NO_FEEDBACK, False,
            np.zeros((1, 0), np.bool_), np.zeros((1, 0)), np.zeros((1, 0)), np.zeros((1, 0)), np.zeros(1, np.bool_))


@numba.njit(cache=True, nogil=True)
def _motion_kernel(source, pose, prev_pose, dt, min_depth, x, P, rho, Q, uv, flow, valid, max_speed, depth, origin,
                   radius, fx, fy, cx, cy, r_px, iters, k, min_vectors, normal, feedback, has_feedback, slow, z, w, res,
                   used, predicted, twist, n_vectors, rejected):
    """:func:`motion_step` (``source`` the index in :data:`SOURCES`); ``slow, z, w, res, used`` are scratch of the
    flow shape. Returns -1, or the index of a velocity filter whose covariance is not positive definite."""
    B = pose.shape[0]
    if source == 0:
        _kf_predict_kernel(x, P, rho, Q)
        limit = np.float32(max_speed)
        for b in range(B):
            for g in range(valid.shape[1]):
                f0, f1 = flow[b, g, 0], flow[b, g, 1]
                slow[b, g] = valid[b, g] and np.sqrt(f0 * f0 + f1 * f1) < limit
        _sample_depth_kernel(depth, origin, uv, slow, radius, z)
        centre = pose[:, :3].copy()
        bad = _kf_update_kernel(x, P, uv, flow, z, slow, dt, centre, True, fx, fy, cx, cy, r_px, iters, k,
                                min_vectors, normal, x, P, w, res, used)  # in place: each filter is read first
        if bad >= 0:
            return bad
        twist_c = x.copy()
        if has_feedback:
            twist_c += feedback
        _shift_twist_kernel(twist_c, -centre, twist)  # [c_dot, w] about the centre -> [v, w]
        for b in range(B):
            n_vectors[b] = np.count_nonzero(w[b] > 0)
    elif source == 1:
        _twist_between_kernel(prev_pose, pose, dt, twist)
    else:
        twist[:] = 0.0
    _propagate_kernel(pose, twist, dt, predicted)
    for b in range(B):
        rejected[b] = not _valid_pose(predicted[b], min_depth[b])
        if rejected[b]:
            predicted[b] = pose[b]
            twist[b] = 0.0
    return -1


@numba.njit(cache=True, nogil=True)
def _valid_pose(pose, min_depth):
    """A pose ``(7,)`` is valid: finite, with the object centre farther than ``min_depth`` (metres)."""
    ok = pose[2] > min_depth
    for j in range(7):
        ok = ok and np.isfinite(pose[j])
    return ok
