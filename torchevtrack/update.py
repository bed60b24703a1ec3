"""The tracker's fused steps: several stages' compiled pieces in one call that releases the GIL.

An update's small per-element operations cost less as one compiled call than as stage calls with tensor glue between
them, and on the tracker's threads a call that holds the GIL delays the other thread. Each fused step here is built
from the stages' public compiled pieces (their ``arrays()`` records, ``*_step`` and ``*_kernel`` functions), runs on
numpy views of their buffers, unchecked but for the events, and gives exactly the numbers of the stage calls one after
the other (``tests/test_intake.py``, ``tests/test_motion.py``, ``tests/test_output.py``):

- :func:`bind_intake`, step 1: a window's events into the :class:`~torchevtrack.stages.eros.EROS`, its
  :class:`~torchevtrack.stages.eros.TimeSurface` and the :class:`~torchevtrack.stages.flow.TripletFlow`. Each reads
  only its own state and the events, so their order does not matter: the flow (which checks every event before it
  writes), then the EROS and the time surface.
- :func:`motion`, steps 2-3: the twist and the propagated pose of every element. With ``source = "flow"`` (the
  paper) the velocity filter's step (:func:`~torchevtrack.stages.velocity.velocity_step`: predict, the slow valid
  flow vectors, their depth from the last render, update about the object centre, plus the correction feedback,
  back about the camera); ``"poses"``: :func:`~torchevtrack.stages.propagate.twist_between` the last two poses;
  ``"none"``: zero twist. Then :func:`~torchevtrack.stages.propagate.propagate_step` by ``dt``, which keeps the pose
  with zero twist where the prediction is not valid.
- :func:`output`, step 6: the correction's rate into the
  :class:`~torchevtrack.stages.velocity.CorrectionFeedback` (:func:`~torchevtrack.stages.propagate.twist_between`
  the predicted and measured poses about the predicted centre, :func:`~torchevtrack.stages.velocity.feedback_step`),
  the :class:`~torchevtrack.stages.ukf.PoseUKF` predict and update (:func:`~torchevtrack.stages.ukf.ukf_step`; its
  pose is the output, without it the measured pose), the current pose where the output is not valid, and canonical
  quaternions (``w >= 0``, :func:`~torchevtrack.geometry.quat_canonical`).
"""

from __future__ import annotations

from typing import Callable, NamedTuple

import numba
import numpy as np
import torch

from torchevtrack.stages.eros import EROS, TimeSurface, eros_kernel, prepare_events, time_kernel
from torchevtrack.stages.flow import (FlowField, TripletFlow, event_arrays, events_in_range, flow_packet, range_error,
                                      smooth_flow)
from torchevtrack.stages.propagate import propagate_kernel, propagate_step, twist_between_kernel, valid_pose
from torchevtrack.stages.ukf import UKFArrays, ukf_step
from torchevtrack.stages.velocity import FeedbackArrays, KFArrays, feedback_step, shift_twist_kernel, velocity_step

__all__ = ["MotionArgs", "OutputArgs", "bind_intake", "motion", "output", "render_ahead"]


def bind_intake(eros: EROS, time_surface: TimeSurface | None, flow: TripletFlow,
                rows: slice | None = None) -> Callable[..., FlowField]:
    """Step 1 bound to the stages' buffers (numpy views of their ``rows``, default all ``B``, written in place at each
    call); ``time_surface`` ``None``: none is kept.

    Returns ``run(x, y, t, p, b, surfaces=True, checked=None)``: ``eros(x, y, b, rows)``, ``time_surface(x, y, t, b,
    rows)`` and ``flow(x, y, t, p, b, rows)`` in one compiled call, with the arguments and errors of the stages'
    ``forward`` (packed events: ``(N,)`` integer pixels ``x, y``, int64 microseconds ``t``, polarity ``p``, batch
    index ``b`` counted from the first of ``rows``); on an error nothing is written. It gives the flow's
    :class:`~torchevtrack.stages.flow.FlowField` as numpy arrays. With ``surfaces=False`` it runs the flow alone,
    leaving the EROS and the time surface to the caller. ``checked``, if given, is called with the events as numpy
    arrays ``(x, y, t, b)`` (``b`` ``None`` for one element) once every event is known to be in range, before
    anything is written (from there on the call cannot fail): the caller may start taking them into the EROS and the
    time surface elsewhere then (:func:`~torchevtrack.stages.eros.bind_observe`).
    """
    surface = eros.surface if rows is None else eros.surface[rows]
    sae = flow.sae_padded if rows is None else flow.sae_padded[rows]
    B, C = sae.shape[:2]
    times = time_surface is not None
    last = (time_surface.last_us if rows is None else time_surface.last_us[rows]) if times else \
        torch.empty(B, 0, 0, dtype=torch.int64)
    if surface.shape[0] != B or last.shape[0] != B:
        raise ValueError(f"the EROS, the time surface and the flow must hold the same elements, got "
                         f"{surface.shape[0]}, {last.shape[0]} and {B}")
    G = flow.n_blocks
    s, last_np, sae_np = surface.numpy(), last.numpy(), sae.numpy()
    lam, r = s.dtype.type(eros.lam), eros.kernel_size // 2
    matching = flow.params

    def _range_errors(x, y, t, p, b):
        prepare_events(x, y, b, *surface.shape[1:], B)  # the EROS stage's range error
        range_error(tuple(sae.shape[:2]) + (flow.height, flow.width), x, y, t, p, b)  # the flow's (polarity)

    def run(x: torch.Tensor, y: torch.Tensor, t: torch.Tensor, p: torch.Tensor | None = None,
            b: torch.Tensor | None = None, surfaces: bool = True,
            checked: Callable[..., object] | None = None) -> FlowField:
        xn, yn, tn, pn, bn, batched = event_arrays(C, x, y, t, p, b)  # checks the fields as the EROS stage does
        if checked is not None:
            if not events_in_range(xn, yn, pn, bn, C, batched, B, flow.height, flow.width):
                _range_errors(x, y, t, p, b)
            checked(xn, yn, tn, bn if batched else None)
        out, uv = np.zeros((B, G, 2), dtype=np.float32), np.empty((B, G, 2), dtype=np.float32)
        valid, count = np.empty((B, G), dtype=np.bool_), np.empty((B, G), dtype=np.int64)
        if not _intake_kernel(s, lam, r, last_np, surfaces, surfaces and times, sae_np, xn, yn, tn, pn, bn, C, batched,
                              *matching, out, uv, valid, count):
            _range_errors(x, y, t, p, b)
        if flow.smooth:
            out, uv = (a.numpy() for a in smooth_flow(torch.from_numpy(out), torch.from_numpy(uv),
                                                      torch.from_numpy(valid), flow.gy, flow.gx))
        return FlowField(uv, out, valid, count)
    return run


@numba.njit(cache=True, nogil=True)
def _intake_kernel(surface, lam, r, last, surfaces, times, sae, x, y, t, p, b, C, batched, dirs, pad, dt_max_us,
                   tol, chunk, block_x, block_y, G, min_samples, max_candidates, tie_tol, normal, inlier, fill, out, uv,
                   valid, count):
    """:func:`~torchevtrack.stages.flow.flow_packet`, then (``surfaces``) :func:`~torchevtrack.stages.eros.eros_kernel`
    and (``times``) :func:`~torchevtrack.stages.eros.time_kernel` if every event was in range (False: nothing
    written)."""
    ok = flow_packet(sae, x, y, t, p, b, C, batched, dirs, pad, dt_max_us, tol, chunk, block_x, block_y, G,
                     min_samples, max_candidates, tie_tol, normal, inlier, fill, out, uv, valid, count)
    if ok and surfaces and x.shape[0]:
        ok = eros_kernel(surface, x, y, b, batched, r, lam) and (not times or time_kernel(last, x, y, t, b, batched))
    return ok


class MotionArgs(NamedTuple):
    """What :func:`motion` reads besides the flow and the render (numpy views, read at each call): ``source``
    (``"flow"``, ``"poses"`` or ``"none"``, as ``velocity.source`` of the config), the current and previous poses
    ``(B, 7)`` float64, the period ``dt`` ``(B,)`` s (:func:`~torchevtrack.stages.periods`) and ``min_depth`` ``(B,)``
    float64, the nearest valid object-centre depth (m); for ``source = "flow"`` the velocity filter's
    :class:`~torchevtrack.stages.velocity.KFArrays` (:meth:`~torchevtrack.stages.velocity.VelocityKF.arrays`; else
    ``None``), the speed ``max_speed`` (px/s) from which a flow vector is dropped, the radius (px) of
    :func:`~torchevtrack.stages.velocity.sample_depth` and the feedback twist ``(B, 6)`` about the centre added to the
    filter's (or ``None``)."""

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
    """Steps 2-3 (see the module docstring) in one compiled call, unchecked: the twist and the propagated pose of
    every element; with ``source = "flow"`` the filter of ``a.kf`` is updated in place.

    Args:
        a: the bound arguments (:class:`MotionArgs`).
        field, depth, origin: for ``source = "flow"``: the flow field ``(B, G)`` as numpy arrays
            (:func:`bind_intake`), the last render's depth ``(B, h, w)`` float32 and its top-left pixel ``(B, 2)``
            int64.

    Returns:
        New arrays ``(predicted, twist, n_vectors, rejected)``: the propagated poses ``(B, 7)`` float64
        ``[t (m), q (w, x, y, z)]``, the camera-frame twist ``(B, 6)`` float64 ``[v (m/s), w (rad/s)]`` they were
        propagated with, the flow vectors the filter weighed ``(B,)`` int64 (0 unless ``source = "flow"``) and
        ``(B,)`` bool where the prediction was not valid and the pose was kept with zero twist.

    Raises:
        torch.linalg.LinAlgError: a velocity filter's covariance is not positive definite.
    """
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
        twist_between_kernel(prev_pose, pose, dt, twist)
    else:
        twist[:] = 0.0
    propagate_step(pose, twist, dt, min_depth, predicted, rejected)
    return -1


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
    propagate_kernel(predicted, twist, dt, ahead)
    for b in range(predicted.shape[0]):
        ahead_ok[b] = valid_pose(ahead[b], min_depth[b])


class OutputArgs(NamedTuple):
    """What :func:`output` reads besides the update's poses (numpy views, read at each call): the current (last output)
    pose ``(B, 7)`` float64, the period ``dt`` ``(B,)`` s, ``min_depth`` ``(B,)`` float64 m, the UKF's
    :class:`~torchevtrack.stages.ukf.UKFArrays` (``None``: the measured poses are the output) and the feedback's
    :class:`~torchevtrack.stages.velocity.FeedbackArrays` (``None``: none)."""

    pose: np.ndarray
    dt: np.ndarray
    min_depth: np.ndarray
    ukf: UKFArrays | None = None
    feedback: FeedbackArrays | None = None


def output(a: OutputArgs, predicted: np.ndarray, measured: np.ndarray, twist: np.ndarray,
           symmetry_axis: np.ndarray | None) -> tuple[np.ndarray, np.ndarray]:
    """Step 6 (see the module docstring) in one compiled call, unchecked: the output poses of an update; the UKF and
    the feedback of ``a`` are updated in place.

    Args:
        a: the bound arguments (:class:`OutputArgs`).
        predicted, measured: ``(B, 7)`` float64 propagated and corrected poses; twist: ``(B, 6)`` float64 ``[v, w]``
            of the propagation.
        symmetry_axis: ``(B, 3)`` float64 camera-frame unit axes the feedback ignores turns about (zero rows: none),
            or ``None``.

    Returns:
        New arrays ``(pose, rejected)``: the output poses ``(B, 7)`` float64 with canonical quaternions and ``(B,)``
        bool where the output was not valid and the current pose was kept.

    Raises:
        torch.linalg.LinAlgError: a UKF covariance is not positive definite.
    """
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
        twist_between_kernel(predicted, measured, dt, rate)
        shift_twist_kernel(rate, predicted[:, :3].copy(), rate_c)  # about the predicted centre
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
