"""The tracker's fused steps: several stages' compiled pieces in one call that releases the GIL.

An update's small per-element operations cost less as one compiled call than as stage calls with tensor glue between
them, and on the tracker's threads a call that holds the GIL delays the other thread. Each fused step here is built
from the stages' public fast pieces (their ``arrays()`` records and compiled ``*_step`` functions), and its checked
form (``*_step`` here) gives exactly the numbers of the stage calls (``tests/test_motion.py``,
``tests/test_output.py``):

- :func:`motion_step`, steps 2-3: the twist and the propagated pose of every element. With ``source = "flow"`` (the
  paper) the velocity filter's step (:func:`~torchevtrack.stages.velocity.velocity_step`: predict, the slow valid
  flow vectors, their depth from the last render, update about the object centre, plus the correction feedback,
  back about the camera); ``"poses"``: :func:`~torchevtrack.stages.propagate.twist_between` the last two poses;
  ``"none"``: zero twist. Then :func:`~torchevtrack.stages.propagate.propagate_step` by ``dt``, which keeps the pose
  with zero twist where the prediction is not valid.
- :func:`output_step`, step 6: the correction's rate into the
  :class:`~torchevtrack.stages.velocity.CorrectionFeedback` (:func:`~torchevtrack.stages.propagate.twist_between`
  the predicted and measured poses about the predicted centre, :func:`~torchevtrack.stages.velocity.feedback_step`),
  the :class:`~torchevtrack.stages.ukf.PoseUKF` predict and update (:func:`~torchevtrack.stages.ukf.ukf_step`; its
  pose is the output, without it the measured pose), the current pose where the output is not valid, and canonical
  quaternions (``w >= 0``, :func:`~torchevtrack.geometry.quat_canonical`).
"""

from __future__ import annotations

from typing import NamedTuple

import numba
import numpy as np
import torch

from torchevtrack.stages import periods
from torchevtrack.stages.flow import FlowField
from torchevtrack.stages.propagate import _propagate_kernel, _twist_between_kernel, propagate_step, valid_pose
from torchevtrack.stages.ukf import PoseUKF, UKFArrays, ukf_step
from torchevtrack.stages.velocity import (CorrectionFeedback, FeedbackArrays, KFArrays, VelocityKF, _shift_twist_kernel,
                                          feedback_step, velocity_step)

__all__ = ["Motion", "MotionArgs", "Output", "OutputArgs", "SOURCES", "motion", "motion_step", "output",
           "output_step"]

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


class MotionArgs(NamedTuple):
    """What :func:`motion` reads besides the flow and the render: ``source`` (:data:`SOURCES`), the current and
    previous poses ``(B, 7)`` float64, the period ``dt`` ``(B,)`` s, ``min_depth`` ``(B,)`` m (numpy views, read at each
    call); for ``source = "flow"`` the velocity filter's :class:`~torchevtrack.stages.velocity.KFArrays` (else
    ``None``), the speed ``max_speed`` (px/s) from which a flow vector is dropped, the depth sampling ``radius`` (px)
    and the feedback twist ``(B, 6)`` about the centre (or ``None``)."""

    source: str
    pose: np.ndarray
    prev_pose: np.ndarray
    dt: np.ndarray
    min_depth: np.ndarray
    kf: KFArrays | None = None
    max_speed: float = float("inf")
    radius: int = 2
    feedback: np.ndarray | None = None


def motion(a: MotionArgs, field: FlowField | None = None, depth: np.ndarray | None = None,
           origin: np.ndarray | None = None) -> tuple[np.ndarray, ...]:
    """:func:`motion_step` unchecked, on numpy arrays: the flow ``field`` and the last render's ``depth`` and
    ``origin`` for ``source = "flow"``. Returns new arrays ``(predicted, twist, n_vectors, rejected)`` as
    :class:`Motion`; the filter of ``a.kf`` is updated in place."""
    B = a.pose.shape[0]
    out = np.empty((B, 7)), np.empty((B, 6)), np.zeros(B, dtype=np.int64), np.empty(B, dtype=np.bool_)
    kf = a.kf if a.source == "flow" else None
    bad = _motion_kernel(a.source == "poses", a.pose, a.prev_pose, a.dt, a.min_depth, kf, field, depth, origin,
                         float(a.max_speed), int(a.radius), a.feedback, *out)
    if bad >= 0:
        raise torch.linalg.LinAlgError(f"kf_update: the covariance of filter {bad} is not positive-definite")
    return out


@numba.njit(cache=True, nogil=True)
def _motion_kernel(from_poses, pose, prev_pose, dt, min_depth, kf, field, depth, origin, max_speed, radius, feedback,
                   predicted, twist, n_vectors, rejected):
    """:func:`motion` (``kf`` ``None``: the twist of the last two poses, ``from_poses``, or zero). Returns -1, or the
    index of a velocity filter whose covariance is not positive definite."""
    if kf is not None:
        bad = velocity_step(kf, field, depth, origin, max_speed, radius, dt, pose[:, :3].copy(), feedback, twist,
                            n_vectors)
        if bad >= 0:
            return bad
    elif from_poses:
        _twist_between_kernel(prev_pose, pose, dt, twist)
    else:
        twist[:] = 0.0
    propagate_step(pose, twist, dt, min_depth, predicted, rejected)
    return -1


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
    a = MotionArgs(source, pose.numpy(), prev_pose.numpy(), periods(B, float(dt)), min_depth.numpy(),
                   kf.arrays() if by_flow else None, max_speed, radius, None if feedback is None else feedback.numpy())
    out = motion(a, FlowField(*(f.numpy() for f in flow)), depth.numpy(), origin.numpy()) if by_flow else motion(a)
    return Motion(*(torch.from_numpy(v) for v in out))


@numba.njit(cache=True, nogil=True)
def render_ahead(predicted, twist, dt, min_depth, ahead, ahead_ok, now, now32):
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
        ahead_ok[b] = valid_pose(ahead[b], min_depth[b])


class Output(NamedTuple):
    """Result of :func:`output_step`.

    Attributes:
        pose: ``(B, 7)`` float64 output poses ``[t (m), q (w, x, y, z)]``, canonical quaternions.
        rejected: ``(B,)`` bool, the output was not valid and the current pose was kept.
    """

    pose: torch.Tensor
    rejected: torch.Tensor


class OutputArgs(NamedTuple):
    """What :func:`output` reads besides the update's poses: the current pose ``(B, 7)``, the period ``dt`` ``(B,)`` s,
    ``min_depth`` ``(B,)`` m (numpy views, read at each call), the UKF's
    :class:`~torchevtrack.stages.ukf.UKFArrays` and the feedback's
    :class:`~torchevtrack.stages.velocity.FeedbackArrays` (``None``: not used)."""

    pose: np.ndarray
    dt: np.ndarray
    min_depth: np.ndarray
    ukf: UKFArrays | None = None
    feedback: FeedbackArrays | None = None


def output(a: OutputArgs, predicted: np.ndarray, measured: np.ndarray, twist: np.ndarray,
           symmetry_axis: np.ndarray | None) -> tuple[np.ndarray, np.ndarray]:
    """:func:`output_step` unchecked, on float64 numpy arrays (the axis ``(B, 3)`` or ``None``). Returns new arrays
    ``(pose, rejected)`` as :class:`Output`; the UKF and the feedback of ``a`` are updated in place."""
    B = a.pose.shape[0]
    out, rejected = np.empty((B, 7)), np.empty(B, dtype=np.bool_)
    bad = _output_kernel(a.pose, predicted, measured, twist, a.dt, a.min_depth, a.feedback, symmetry_axis, a.ukf, out,
                         rejected)
    if bad >= 0:
        raise torch.linalg.LinAlgError(f"{'ukf_predict' if bad < B else 'ukf_update'}: the covariance of "
                                       f"filter {bad % B} is not positive-definite")
    return out, rejected


@numba.njit(cache=True, nogil=True)
def _output_kernel(pose, predicted, measured, twist, dt, min_depth, feedback, axis, ukf, out, rejected):
    """:func:`output` into ``out``, ``rejected``. Returns -1, or the failing UKF filter (see
    :func:`~torchevtrack.stages.ukf.ukf_step`)."""
    if feedback is not None:
        B = pose.shape[0]
        rate, rate_c = np.empty((B, 6)), np.empty((B, 6))
        _twist_between_kernel(predicted, measured, dt, rate)
        _shift_twist_kernel(rate, predicted[:, :3].copy(), rate_c)  # about the predicted centre
        feedback_step(feedback, rate_c, axis)
    if ukf is not None:
        bad = ukf_step(ukf, dt, twist, measured)
        if bad >= 0:
            return bad
        out[:] = ukf.x[:, 6:13]
    else:
        out[:] = measured
    for i in range(pose.shape[0]):
        rejected[i] = not valid_pose(out[i], min_depth[i])
        if rejected[i]:
            out[i] = pose[i]
            if ukf is not None:
                ukf.x[i, 6:13] = pose[i]
        q0, q1, q2, q3 = out[i, 3], out[i, 4], out[i, 5], out[i, 6]  # quat_canonical: the same sum of squares
        norm = max(np.sqrt(((q0 * q0 + q1 * q1) + q2 * q2) + q3 * q3), 1e-12)
        sign = -1.0 if q0 / norm < 0 else 1.0
        for j in range(3, 7):
            out[i, j] = sign * (out[i, j] / norm)
    return -1


def output_step(pose: torch.Tensor, predicted: torch.Tensor, measured: torch.Tensor, twist: torch.Tensor, dt: float,
                min_depth: torch.Tensor, *, ukf: PoseUKF | None = None, feedback: CorrectionFeedback | None = None,
                symmetry_axis: torch.Tensor | None = None) -> Output:
    """The output poses of an update (see the module docstring); ``ukf`` and ``feedback`` are updated in place.

    Args:
        pose: ``(B, 7)`` current (last output) poses; predicted: ``(B, 7)`` propagated poses; measured:
            ``(B, 7)`` corrected poses; twist: ``(B, 6)`` ``[v, w]`` of the propagation; all float64.
        dt: update period, seconds.
        min_depth: ``(B,)`` float64, the nearest valid object-centre depth (m).
        ukf: the pose smoother (``None``: the measured poses are the output).
        feedback: the correction feedback (``None``: none).
        symmetry_axis: ``(B, 3)`` camera-frame unit axes the feedback ignores turns about (zero rows: none).

    Raises:
        torch.linalg.LinAlgError: a UKF covariance is not positive definite.

    Shape: ``(B, 7), (B, 7), (B, 7), (B, 6), (), (B,) -> Output``.
    """
    B = pose.shape[0]
    for name, v, n in (("pose", pose, 7), ("predicted", predicted, 7), ("measured", measured, 7), ("twist", twist, 6)):
        if v.shape != (B, n) or v.dtype != torch.float64:
            raise ValueError(f"{name} must be a float64 ({B}, {n}) tensor, got {v.dtype} {tuple(v.shape)}")
    if min_depth.shape != (B,):
        raise ValueError(f"min_depth must have shape ({B},), got {tuple(min_depth.shape)}")
    if (ukf is not None and ukf.batch_size != B) or (feedback is not None and feedback.b.shape != (B, 6)):
        raise ValueError(f"the UKF and the feedback must have B={B} elements")
    if symmetry_axis is not None and symmetry_axis.shape != (B, 3):
        raise ValueError(f"symmetry_axis must have shape ({B}, 3), got {tuple(symmetry_axis.shape)}")
    a = OutputArgs(pose.numpy(), periods(B, float(dt)), min_depth.numpy(), None if ukf is None else ukf.arrays(),
                   None if feedback is None else feedback.arrays())
    out = output(a, predicted.numpy(), measured.numpy(), twist.numpy(),
                 None if symmetry_axis is None else symmetry_axis.double().numpy())
    return Output(*(torch.from_numpy(v) for v in out))
