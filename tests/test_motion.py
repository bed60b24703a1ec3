"""motion against its oracle: the stage calls it composes, one after the other, bit for bit."""

import numpy as np
import pytest
import torch

from torchevtrack.camera import Camera
from torchevtrack.geometry import quat_exp, quat_mul
from torchevtrack.stages import periods
from torchevtrack.stages.flow import FlowField
from torchevtrack.stages.propagate import invalid_poses, propagate, twist_between
from torchevtrack.stages.velocity import VelocityKF, sample_depth, shift_twist
from torchevtrack.update import MotionArgs, motion

CAM = Camera.default()
F64 = torch.float64
B, G, DT, MAX_SPEED, RADIUS = 3, 60, 0.002, 4000.0, 2


def _poses(gen):
    t = torch.tensor([[0.02, -0.01, 0.45], [-0.05, 0.03, 0.6], [0.0, 0.0, 0.5]], dtype=F64)
    q = quat_exp(0.4 * torch.randn(B, 3, dtype=F64, generator=gen))
    return torch.cat((t, q), -1)


def _inputs(seed=0):
    """A velocity filter with a non-trivial state, a flow field with invalid and too fast vectors, a depth render."""
    gen = torch.Generator().manual_seed(seed)
    kf = VelocityKF(CAM, batch_size=B)
    kf.x.copy_(torch.randn(B, 6, dtype=F64, generator=gen) * 0.2)
    A = torch.randn(B, 6, 6, dtype=F64, generator=gen)
    kf.P.copy_(A @ A.transpose(1, 2) * 0.1 + torch.eye(6, dtype=F64))
    uv = (torch.rand(B, G, 2, generator=gen) * torch.tensor([200.0, 150.0]) + torch.tensor([220.0, 160.0]))
    flow = torch.randn(B, G, 2, generator=gen) * 1500.0  # some beyond MAX_SPEED
    valid = torch.rand(B, G, generator=gen) > 0.2
    fields = FlowField(uv, flow, valid, torch.ones(B, G, dtype=torch.long))
    depth = torch.zeros(B, 170, 220)
    depth[:, 20:150, 30:190] = 0.4 + 0.2 * torch.rand(B, 130, 160, generator=gen)  # an object, and background
    origin = torch.tensor([[200, 150], [210, 140], [205, 155]])
    pose = _poses(gen)
    prev = propagate(pose, torch.randn(B, 6, dtype=F64, generator=gen) * 0.1, -DT)
    feedback = torch.randn(B, 6, dtype=F64, generator=gen) * 0.05
    return kf, fields, depth, origin, pose, prev, feedback


def _motion(source, pose, prev, min_depth, kf=None, fields=None, depth=None, origin=None, feedback=None):
    """The tracker's call: the arguments as numpy views (the filter's and the flow's whatever the source), the
    results as tensors ``(predicted, twist, n_vectors, rejected)``."""
    a = MotionArgs(source, pose.numpy(), prev.numpy(), periods(B, DT), min_depth.numpy(),
                   None if kf is None else kf.arrays(), MAX_SPEED, RADIUS, None if feedback is None else feedback.numpy())
    flow = () if fields is None else (FlowField(*(f.numpy() for f in fields)), depth.numpy(), origin.numpy())
    return tuple(torch.from_numpy(v) for v in motion(a, *flow))


def _oracle(source, kf, fields, depth, origin, pose, prev, feedback, min_depth):
    """The tracker's steps 2-3 as separate stage calls."""
    n_vectors = torch.zeros(B, dtype=torch.long)
    if source == "flow":
        kf.predict()
        f = fields.flow.numpy()
        slow = torch.from_numpy(fields.valid.numpy() & (np.sqrt(f[..., 0] * f[..., 0] + f[..., 1] * f[..., 1])
                                                          < MAX_SPEED))
        z = sample_depth(depth, origin, fields.uv, slow, RADIUS)
        centre = pose[:, :3]
        upd = kf.update(fields.uv, fields.flow, z, slow, DT, centre=centre)
        twist_c = kf.x + feedback if feedback is not None else kf.x
        twist = shift_twist(twist_c, -centre)
        n_vectors = (upd.weights > 0).sum(-1)
    elif source == "poses":
        twist = twist_between(prev, pose, DT)
    else:
        twist = torch.zeros(B, 6, dtype=F64)
    predicted = propagate(pose, twist, DT)
    rejected = ~torch.isfinite(predicted).all(-1) | (predicted[:, 2] <= min_depth)
    predicted = torch.where(rejected[:, None], pose, predicted)
    twist = torch.where(rejected[:, None], 0.0, twist)
    return predicted, twist, n_vectors, rejected


@pytest.mark.parametrize("source, with_feedback", [("flow", True), ("flow", False), ("poses", False),
                                                   ("none", False)])
def test_motion_is_the_stage_calls_bit_for_bit(source, with_feedback):
    kf, fields, depth, origin, pose, prev, feedback = _inputs()
    feedback = feedback if with_feedback else None
    min_depth = torch.full((B,), 0.1, dtype=F64)
    ref_kf, *_ = _inputs()
    want = _oracle(source, ref_kf, fields, depth, origin, pose, prev, feedback, min_depth)
    got = _motion(source, pose, prev, min_depth, kf, fields, depth, origin, feedback)
    for name, g, w in zip(("predicted", "twist", "n_vectors", "rejected"), got, want):
        assert g.dtype == w.dtype and torch.equal(g, w), name
    assert torch.equal(kf.x, ref_kf.x) and torch.equal(kf.P, ref_kf.P)
    if source == "flow":
        assert int(got[2].sum()) > 0 and not bool(got[3].any())
        assert not torch.equal(kf.x, _inputs()[0].x)  # the filter moved
    else:
        assert torch.equal(kf.x, _inputs()[0].x)  # untouched


def test_invalid_predictions_keep_the_pose_with_zero_twist():
    """Element 1 moves toward the camera past its minimum depth: rejected, the others are propagated."""
    kf, fields, depth, origin, pose, prev, _ = _inputs()
    prev = pose.clone()
    prev[1, 2] += 0.4  # it came from 0.4 m farther in one period: it will pass min_depth
    min_depth = torch.tensor([0.1, 0.5, 0.1], dtype=F64)
    predicted, twist, _, rejected = _motion("poses", pose, prev, min_depth)
    assert rejected.tolist() == [False, True, False]
    assert torch.equal(predicted[1], pose[1]) and not bool(twist[1].any())
    want = _oracle("poses", kf, fields, depth, origin, pose, prev, None, min_depth)
    assert torch.equal(predicted, want[0]) and torch.equal(twist, want[1])
    # a rotation-only twist keeps the position but turns the orientation
    prev = pose.clone()
    prev[:, 3:] = quat_mul(quat_exp(torch.tensor([[0.0, 0.0, 0.01]], dtype=F64)).expand(B, 4), pose[:, 3:])
    turned = _motion("poses", pose, prev, torch.full((B,), 0.1, dtype=F64))[0]
    assert torch.allclose(turned[:, :3], pose[:, :3], atol=1e-12) and not torch.allclose(turned[:, 3:], pose[:, 3:])


def test_a_filter_that_is_not_positive_definite_is_named():
    kf, fields, depth, origin, pose, prev, _ = _inputs()
    kf.P[1] = -100.0 * torch.eye(6, dtype=F64)
    with pytest.raises(torch.linalg.LinAlgError, match="kf_update: the covariance of filter 1"):
        _motion("flow", pose, prev, torch.full((B,), 0.1, dtype=F64), kf, fields, depth, origin)


def test_invalid_poses_is_the_rule():
    """Not finite anywhere, or the centre at or nearer than min_depth (numpy oracle)."""
    pose = _poses(torch.Generator().manual_seed(1)).repeat(2, 1)
    pose[1, 4] = float("nan")
    pose[2, 2] = 0.1  # exactly min_depth: rejected
    pose[3, 0] = float("inf")
    pose[4, 2] = -0.5
    min_depth = torch.full((6,), 0.1, dtype=F64)
    p = pose.numpy()
    want = ~np.isfinite(p).all(-1) | (p[:, 2] <= min_depth.numpy())
    assert invalid_poses(pose, min_depth).tolist() == want.tolist() == [False, True, True, True, True, False]


def test_render_ahead_kernel_swaps_in_the_last_prediction_and_propagates():
    """now = the poses predicted last time where they were valid, else this prediction; the buffers then hold this
    prediction moved on by its twist (propagate) and whether that is valid (invalid_poses)."""
    from torchevtrack.update import render_ahead

    g = torch.Generator().manual_seed(3)
    predicted = _poses(g)
    B = predicted.shape[0]
    twist = torch.randn(B, 6, generator=g, dtype=F64) * 0.5
    twist[1, 2] = -1e6  # moves the centre behind the camera: not valid next time
    ahead, ok = _poses(g), torch.tensor([True, False] * (B // 2) + [True] * (B % 2))
    min_depth = torch.full((B,), 0.05, dtype=F64)
    want_now = torch.where(ok[:, None], ahead, predicted)
    want_next = propagate(predicted, twist, 0.002)
    now, now32 = np.empty((B, 7)), np.empty((B, 7), dtype=np.float32)
    ahead_np, ok_np = ahead.numpy().copy(), ok.numpy().copy()
    render_ahead(predicted.numpy(), twist.numpy(), periods(B, 0.002), min_depth.numpy(), ahead_np, ok_np,
                         now, now32)
    assert np.array_equal(now, want_now.numpy()) and np.array_equal(now32, want_now.float().numpy())
    assert np.array_equal(ahead_np, want_next.numpy())
    assert ok_np.tolist() == (~invalid_poses(want_next, min_depth)).tolist() and not ok_np[1]
    dts = periods(B, 0.002)
    assert dts is periods(B, 0.002) and not dts.flags.writeable and dts.tolist() == [0.002] * B
