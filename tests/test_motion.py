"""motion_step against its oracle: the stage calls it composes, one after the other, bit for bit."""

import numpy as np
import pytest
import torch

from torchevtrack.camera import Camera
from torchevtrack.geometry import quat_exp, quat_mul
from torchevtrack.stages.flow import FlowField
from torchevtrack.stages.propagate import invalid_poses, propagate, twist_between
from torchevtrack.stages.velocity import VelocityKF, sample_depth, shift_twist
from torchevtrack.update import motion_step

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
def test_motion_step_is_the_stage_calls_bit_for_bit(source, with_feedback):
    kf, fields, depth, origin, pose, prev, feedback = _inputs()
    feedback = feedback if with_feedback else None
    min_depth = torch.full((B,), 0.1, dtype=F64)
    ref_kf, *_ = _inputs()
    want = _oracle(source, ref_kf, fields, depth, origin, pose, prev, feedback, min_depth)
    got = motion_step(source, pose, prev, DT, min_depth, kf=kf, flow=fields, max_speed=MAX_SPEED, depth=depth,
                      origin=origin, radius=RADIUS, feedback=feedback)
    for name, g, w in zip(got._fields, got, want):
        assert torch.equal(g, w), name
    assert torch.equal(kf.x, ref_kf.x) and torch.equal(kf.P, ref_kf.P)
    if source == "flow":
        assert int(got.n_vectors.sum()) > 0 and not bool(got.rejected.any())
        assert not torch.equal(kf.x, _inputs()[0].x)  # the filter moved
    else:
        assert torch.equal(kf.x, _inputs()[0].x)  # untouched


def test_invalid_predictions_keep_the_pose_with_zero_twist():
    """Element 1 moves toward the camera past its minimum depth: rejected, the others are propagated."""
    kf, fields, depth, origin, pose, prev, _ = _inputs()
    prev = pose.clone()
    prev[1, 2] += 0.4  # it came from 0.4 m farther in one period: it will pass min_depth
    min_depth = torch.tensor([0.1, 0.5, 0.1], dtype=F64)
    got = motion_step("poses", pose, prev, DT, min_depth)
    assert got.rejected.tolist() == [False, True, False]
    assert torch.equal(got.predicted[1], pose[1]) and not bool(got.twist[1].any())
    want = _oracle("poses", kf, fields, depth, origin, pose, prev, None, min_depth)
    assert torch.equal(got.predicted, want[0]) and torch.equal(got.twist, want[1])
    # a rotation-only twist keeps the position but turns the orientation
    prev = pose.clone()
    prev[:, 3:] = quat_mul(quat_exp(torch.tensor([[0.0, 0.0, 0.01]], dtype=F64)).expand(B, 4), pose[:, 3:])
    turned = motion_step("poses", pose, prev, DT, torch.full((B,), 0.1, dtype=F64)).predicted
    assert torch.allclose(turned[:, :3], pose[:, :3], atol=1e-12) and not torch.allclose(turned[:, 3:], pose[:, 3:])


def test_bad_arguments_are_clear_errors():
    kf, fields, depth, origin, pose, prev, _ = _inputs()
    min_depth = torch.full((B,), 0.1, dtype=F64)
    with pytest.raises(ValueError, match="source"):
        motion_step("imu", pose, prev, DT, min_depth)
    with pytest.raises(ValueError, match="needs kf"):
        motion_step("flow", pose, prev, DT, min_depth, flow=fields)
    with pytest.raises(ValueError, match="float64"):
        motion_step("none", pose.float(), prev, DT, min_depth)
    with pytest.raises(ValueError, match="B=3"):  # a filter of another batch size: refused, not read out of bounds
        motion_step("flow", pose, prev, DT, min_depth, kf=VelocityKF(CAM, batch_size=2), flow=fields, depth=depth,
                    origin=origin)
    with pytest.raises(ValueError, match="B=3"):
        motion_step("flow", pose, prev, DT, min_depth, kf=kf, flow=fields, depth=depth, origin=origin[:2])


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
    from torchevtrack.stages import periods
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
