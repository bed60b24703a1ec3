"""The end of an update in one compiled call: correction feedback, UKF, validity check, canonical output pose.

:func:`output_step` turns the measured poses of an update into its output poses by running the stages' own kernels,
in this order, inside one compiled call; its results equal those of the stage calls exactly
(``tests/test_output.py``):

1. with a :class:`~torchevtrack.stages.velocity.CorrectionFeedback`: the correction's rate,
   :func:`~torchevtrack.stages.propagate.twist_between` the predicted and measured poses, taken about the
   predicted centre (:func:`~torchevtrack.stages.velocity.shift_twist`) into the feedback, in place (without
   its component along the objects' symmetry axes, if given);
2. with a :class:`~torchevtrack.stages.ukf.PoseUKF`: :meth:`~torchevtrack.stages.ukf.PoseUKF.predict` with the
   twist, then :meth:`~torchevtrack.stages.ukf.PoseUKF.update` with the measured poses, in place; its pose is the
   output (without: the measured poses);
3. an output that is not finite or puts the object centre at or nearer than ``min_depth`` is replaced by the
   current pose (the UKF's pose too);
4. the output quaternions are normalised with ``w >= 0``
   (:func:`~torchevtrack.geometry.quat_canonical`).
"""

from __future__ import annotations

from typing import Callable, NamedTuple

import numba
import numpy as np
import torch

from torchevtrack.stages import periods
from torchevtrack.stages.motion import _valid_pose
from torchevtrack.stages.propagate import _twist_between_kernel
from torchevtrack.stages.ukf import PoseUKF, _cov_arg, _ukf_predict_kernel, _ukf_update_kernel, _weights_np
from torchevtrack.stages.velocity import CorrectionFeedback, _feedback_kernel, _shift_twist_kernel

__all__ = ["Output", "bind_output", "output_step"]


class Output(NamedTuple):
    """Result of :func:`output_step`.

    Attributes:
        pose: ``(B, 7)`` float64 output poses ``[t (m), q (w, x, y, z)]``, canonical quaternions.
        rejected: ``(B,)`` bool, the output was not valid and the current pose was kept.
    """

    pose: torch.Tensor
    rejected: torch.Tensor


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
    run = bind_output(pose.numpy(), float(dt), min_depth.numpy(), ukf=ukf, feedback=feedback)
    out = run(predicted.numpy(), measured.numpy(), twist.numpy(),
              None if symmetry_axis is None else symmetry_axis.double().numpy())
    return Output(*(torch.from_numpy(a) for a in out))


def bind_output(pose: np.ndarray, dt: float, min_depth: np.ndarray, *, ukf: PoseUKF | None = None,
                feedback: CorrectionFeedback | None = None) -> Callable[..., tuple[np.ndarray, np.ndarray]]:
    """:func:`output_step` bound to its state, unchecked, for a caller that runs it every update on the same
    buffers (the tracker): ``pose`` and ``min_depth`` are numpy views of the tensors :func:`output_step` takes,
    read at each call (``ukf`` and ``feedback`` are updated in place).

    Returns ``run(predicted, measured, twist, symmetry_axis)`` (float64 numpy arrays; the axis ``(B, 3)`` or
    ``None``) giving new arrays ``(pose, rejected)`` as :class:`Output`.
    """
    B = pose.shape[0]
    dts = periods(B, float(dt))
    fb = feedback is not None
    if ukf is not None:
        Wm, Wc, spread = _weights_np(ukf.alpha, ukf.beta, ukf.kappa)
        (q, q_diag), (r, r_diag) = _cov_arg(ukf.q_density), _cov_arg(ukf.R)
        filt = (True, ukf.x.numpy(), ukf.P.numpy(), q, q_diag, r, r_diag, Wm, Wc, spread)
    else:
        filt = (False, *_NO_UKF)
    gains = (feedback.gain, feedback.leak, feedback.mask.numpy(), feedback.limit.numpy()) if fb \
        else (0.0, 0.0, _NO_MASK, _NO_LIMIT)
    b = feedback.b.numpy() if fb else _NO_B

    def run(predicted, measured, twist, symmetry_axis) -> tuple[np.ndarray, np.ndarray]:
        out, rejected = np.empty((B, 7)), np.empty(B, dtype=np.bool_)
        has_axis = symmetry_axis is not None
        bad = _output_kernel(pose, predicted, measured, twist, dts, min_depth, fb, b,
                             symmetry_axis if has_axis else _NO_AXIS, has_axis, *gains, *filt, out, rejected)
        if bad >= 0:
            raise torch.linalg.LinAlgError(f"{'ukf_predict' if bad < B else 'ukf_update'}: the covariance of "
                                           f"filter {bad % B} is not positive-definite")
        return out, rejected
    return run


_NO_B, _NO_AXIS, _NO_MASK, _NO_LIMIT = np.zeros((1, 6)), np.zeros((1, 3)), np.zeros(6, np.bool_), np.zeros(6)
# The UKF arguments of _output_kernel without a UKF (not read), in its order: x, P, q, q_diag, r, r_diag, Wm, Wc, spread.
_NO_UKF = (np.zeros((1, 13)), np.zeros((1, 12, 12)), np.zeros((1, 12)), True, np.zeros((1, 6)), True, np.zeros(25),
           np.zeros(25), 1.0)


@numba.njit(cache=True, nogil=True)
def _output_kernel(pose, predicted, measured, twist, dt, min_depth, has_feedback, b, axis, has_axis, gain, leak, mask,
                   limit, has_ukf, x, P, q, q_diag, r, r_diag, Wm, Wc, spread, out, rejected):
    """:func:`output_step` into ``out``, ``rejected``. Returns -1, or the failing UKF filter: its index in the
    prediction, ``B`` + its index in the update."""
    B = pose.shape[0]
    if has_feedback:
        rate, rate_c = np.empty((B, 6)), np.empty((B, 6))
        _twist_between_kernel(predicted, measured, dt, rate)
        _shift_twist_kernel(rate, predicted[:, :3].copy(), rate_c)  # about the predicted centre
        _feedback_kernel(b, rate_c, axis, has_axis, gain, leak, mask, limit, True, b)
    if has_ukf:
        bad = _ukf_predict_kernel(x, P, dt, q, q_diag, twist, True, Wm, Wc, spread, x, P)
        if bad >= 0:
            return bad
        bad = _ukf_update_kernel(x, P, measured, r, r_diag, Wm, Wc, spread, x, P)
        if bad >= 0:
            return B + bad
        out[:] = x[:, 6:13]
    else:
        out[:] = measured
    for i in range(B):
        rejected[i] = not _valid_pose(out[i], min_depth[i])
        if rejected[i]:
            out[i] = pose[i]
            if has_ukf:
                x[i, 6:13] = pose[i]
        q0, q1, q2, q3 = out[i, 3], out[i, 4], out[i, 5], out[i, 6]  # quat_canonical: the same sum of squares
        norm = max(np.sqrt(((q0 * q0 + q1 * q1) + q2 * q2) + q3 * q3), 1e-12)
        sign = -1.0 if q0 / norm < 0 else 1.0
        for j in range(3, 7):
            out[i, j] = sign * (out[i, j] / norm)
    return -1
