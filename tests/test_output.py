"""output against its oracle: the stage calls it composes, one after the other, bit for bit."""

import numpy as np
import pytest
import torch

from torchevtrack.geometry import quat_canonical, quat_exp
from torchevtrack.stages import periods
from torchevtrack.stages.propagate import propagate, twist_between
from torchevtrack.stages.ukf import PoseUKF
from torchevtrack.stages.velocity import CorrectionFeedback, shift_twist
from torchevtrack.update import OutputArgs, output

F64 = torch.float64
B, DT = 3, 0.002


def _inputs(seed=0):
    """Poses, a propagation twist, corrections of a few mm / mrad, a UKF and a feedback with some history."""
    gen = torch.Generator().manual_seed(seed)
    t = torch.tensor([[0.02, -0.01, 0.45], [-0.05, 0.03, 0.6], [0.0, 0.0, 0.5]], dtype=F64)
    pose = torch.cat((t, quat_exp(0.4 * torch.randn(B, 3, dtype=F64, generator=gen))), -1)
    twist = torch.randn(B, 6, dtype=F64, generator=gen) * 0.2
    predicted = propagate(pose, twist, DT)
    measured = propagate(predicted, torch.randn(B, 6, dtype=F64, generator=gen) * 0.5, DT)
    measured[:, 3:] = -measured[:, 3:]  # the same rotations, as quaternions with w < 0
    ukf = PoseUKF(B)
    ukf.reset(pose, twist)
    for _ in range(3):  # a covariance that is not the initial one
        ukf.predict(DT, twist)
        ukf.update(propagate(pose, twist, DT))
    feedback = CorrectionFeedback(batch_size=B)
    feedback.b.copy_(torch.randn(B, 6, dtype=F64, generator=gen) * 0.01)
    axis = torch.tensor([[0.0, 0.0, 1.0], [0.0, 0.0, 0.0], [0.6, 0.8, 0.0]], dtype=F64)
    return pose, predicted, measured, twist, ukf, feedback, axis


def _output(pose, predicted, measured, twist, min_depth, ukf=None, feedback=None, symmetry_axis=None):
    """The tracker's call: the arguments as numpy views, the results as tensors ``(pose, rejected, depth_lag)``."""
    lag = np.full(B, np.nan)
    a = OutputArgs(pose.numpy(), periods(B, DT), min_depth.numpy(), lag, None if ukf is None else ukf.arrays(),
                   None if feedback is None else feedback.arrays())
    out = output(a, predicted.numpy(), measured.numpy(), twist.numpy(),
                 None if symmetry_axis is None else symmetry_axis.numpy())
    return tuple(torch.from_numpy(v) for v in out + (lag,))


def _oracle(pose, predicted, measured, twist, ukf, feedback, axis, min_depth):
    """The tracker's output, stage call by stage call."""
    if feedback is not None:
        rate = twist_between(predicted, measured, DT)
        feedback(shift_twist(rate, predicted[:, :3]), axis)
    if ukf is not None:
        ukf.predict(DT, twist)
        ukf.update(measured)
        out = ukf.pose
    else:
        out = measured
    bad = ~torch.isfinite(out).all(-1) | (out[:, 2] <= min_depth)
    out = torch.where(bad[:, None], pose, out)
    if ukf is not None:
        ukf.x[bad, 6:13] = pose[bad]
    lag = torch.where(bad, 0.0, measured[:, 2] - out[:, 2])  # where the next correction's depth band is centred
    return torch.cat((out[:, :3], quat_canonical(out[:, 3:])), -1), bad, lag


@pytest.mark.parametrize("with_ukf, with_feedback, with_axis", [(True, True, True), (True, True, False),
                                                                (True, False, False), (False, True, True),
                                                                (False, False, False)])
def test_output_is_the_stage_calls_bit_for_bit(with_ukf, with_feedback, with_axis):
    pose, predicted, measured, twist, ukf, feedback, axis = _inputs()
    ref = _inputs()
    min_depth = torch.tensor([0.1, 0.1, 0.52], dtype=F64)  # element 2 (z about 0.5 m) comes out too near
    pick = lambda u, f, a: (u if with_ukf else None, f if with_feedback else None, a if with_axis else None)  # noqa: E731
    got_pose, got_bad, got_lag = _output(pose, predicted, measured, twist, min_depth, *pick(ukf, feedback, axis))
    want_pose, want_bad, want_lag = _oracle(*ref[:4], *pick(*ref[4:]), min_depth)
    assert torch.equal(got_pose, want_pose) and torch.equal(got_bad, want_bad) and torch.equal(got_lag, want_lag)
    assert bool((got_lag[:2] != 0).all()) == with_ukf and float(got_lag[2]) == 0.0  # none without the UKF
    assert got_bad.tolist() == [False, False, True]
    assert bool((got_pose[:, 3] >= 0).all()) and torch.equal(got_pose[2], quat_canonical_pose(pose[2]))
    assert torch.equal(ukf.x, ref[4].x) and torch.equal(ukf.P, ref[4].P)
    assert torch.equal(feedback.b, ref[5].b)
    assert torch.equal(ukf.x, _inputs()[4].x) != with_ukf  # updated in place only when given
    assert torch.equal(feedback.b, _inputs()[5].b) != with_feedback


def quat_canonical_pose(p):
    return torch.cat((p[:3], quat_canonical(p[3:])))


def test_a_filter_that_is_not_positive_definite_is_named():
    pose, predicted, measured, twist, ukf, feedback, axis = _inputs()
    ukf.P[1] = -torch.eye(12, dtype=F64)
    with pytest.raises(torch.linalg.LinAlgError, match="ukf_predict.*filter 1"):
        _output(pose, predicted, measured, twist, torch.full((B,), 0.1, dtype=F64), ukf)
