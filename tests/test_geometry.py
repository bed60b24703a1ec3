import math

import numpy as np
import pytest
import torch
from scipy.spatial.transform import Rotation, Slerp

from torchevtrack import geometry as g

torch.manual_seed(0)


def _rand_quat(n):
    return g.quat_canonical(torch.randn(n, 4, dtype=torch.float64))


def _rand_pose(n):
    return torch.cat((torch.randn(n, 3, dtype=torch.float64), _rand_quat(n)), dim=-1)


def _scipy(q):
    return Rotation.from_quat(q[..., [1, 2, 3, 0]].numpy())


def test_quat_to_matrix_matches_scipy():
    q = _rand_quat(50)
    np.testing.assert_allclose(g.quat_to_matrix(q).numpy(), _scipy(q).as_matrix(), atol=1e-12)


def test_matrix_to_quat_roundtrip_and_sign():
    R = torch.from_numpy(Rotation.random(50, random_state=1).as_matrix())
    q = g.matrix_to_quat(R)
    assert (q[:, 0] >= 0).all()
    np.testing.assert_allclose(g.quat_to_matrix(q).numpy(), R.numpy(), atol=1e-10)


def test_quat_mul_is_rotation_composition():
    a, b = _rand_quat(20), _rand_quat(20)
    expected = (_scipy(a) * _scipy(b)).as_matrix()
    np.testing.assert_allclose(g.quat_to_matrix(g.quat_mul(a, b)).numpy(), expected, atol=1e-12)


def test_exp_log_match_scipy_rotvec():
    phi = torch.randn(30, 3, dtype=torch.float64)
    phi = phi / phi.norm(dim=-1, keepdim=True) * torch.rand(30, 1, dtype=torch.float64) * 3.0
    np.testing.assert_allclose(g.quat_to_matrix(g.quat_exp(phi)).numpy(), Rotation.from_rotvec(phi.numpy()).as_matrix(), atol=1e-12)
    np.testing.assert_allclose(g.quat_log(g.quat_exp(phi)).numpy(), phi.numpy(), atol=1e-9)


def test_exp_tiny_angle_is_stable():
    phi = torch.tensor([[1e-12, 0.0, 0.0]], dtype=torch.float64)
    q = g.quat_exp(phi)
    assert torch.isfinite(q).all() and abs(float(q[0, 0]) - 1.0) < 1e-12



@pytest.mark.parametrize("dtype", [torch.float64, torch.float32])
def test_exp_log_mul_equal_their_reference_formulas_bit_for_bit(dtype):
    """quat_exp / quat_log give kornia's axis-angle conversions' values and quat_mul the textbook
    expansion's, bit for bit (signed zeros and NaN included), for contiguous and strided inputs."""
    from kornia.geometry.conversions import axis_angle_to_quaternion, quaternion_to_axis_angle

    def same(a, b):
        return torch.equal(torch.nan_to_num(a, nan=7.0), torch.nan_to_num(b, nan=7.0)) and bool(
            (torch.signbit(a) == torch.signbit(b)).all())

    def mul(a, b):
        aw, ax, ay, az = a.unbind(-1)
        bw, bx, by, bz = b.unbind(-1)
        return torch.stack((aw * bw - ax * bx - ay * by - az * bz, aw * bx + ax * bw + ay * bz - az * by,
                            aw * by - ax * bz + ay * bw + az * bx, aw * bz + ax * by - ay * bx + az * bw), -1)

    gen = torch.Generator().manual_seed(1)
    big = torch.randn(6, 25, 13, generator=gen, dtype=dtype)
    big[0] = 0.0  # zero rotations, identity quaternions
    big[1, :, 9] = 0.0  # half turns
    big[2, :, 3] = float("nan")
    big[3] *= 1e-4  # tiny angles
    big[4, :, 10:] = -0.0
    for phi in (big[..., 3:6], big[..., 3:6].contiguous()):
        assert same(g.quat_exp(phi), axis_angle_to_quaternion(phi))
    for q in (big[..., 9:13], big[..., 9:13].contiguous(), g.quat_normalize(big[..., 9:13])):
        assert same(g.quat_log(q), quaternion_to_axis_angle(g.quat_canonical(q)))
        assert same(g.quat_mul(q, big[..., 5:9]), mul(q, big[..., 5:9]))
        assert same(g.quat_mul(q[:1], big[..., 5:9]), mul(q[:1], big[..., 5:9]))  # broadcasting

def test_quat_rotate_matches_matrix():
    q = _rand_quat(10)
    v = torch.randn(10, 3, dtype=torch.float64)
    np.testing.assert_allclose(g.quat_rotate(q, v).numpy(), _scipy(q).apply(v.numpy()), atol=1e-12)


def test_slerp_endpoints_midpoint_and_scipy():
    q0, q1 = _rand_quat(8), _rand_quat(8)
    np.testing.assert_allclose(g.quat_slerp(q0, q1, 0.0).numpy(), q0.numpy(), atol=1e-12)
    end = g.quat_slerp(q0, q1, 1.0)
    np.testing.assert_allclose(g.quat_to_matrix(end).numpy(), g.quat_to_matrix(q1).numpy(), atol=1e-12)
    for i in range(8):
        key = Rotation.from_quat(torch.stack((q0[i], q1[i]))[:, [1, 2, 3, 0]].numpy())
        mid = Slerp([0.0, 1.0], key)([0.3]).as_matrix()[0]
        np.testing.assert_allclose(g.quat_to_matrix(g.quat_slerp(q0[i], q1[i], 0.3)).numpy(), mid, atol=1e-10)


def test_slerp_identical_quaternions():
    q = _rand_quat(1)
    np.testing.assert_allclose(g.quat_slerp(q, q, 0.5).numpy(), q.numpy(), atol=1e-12)


def test_pose_matrix_compose_inverse():
    a, b = _rand_pose(10), _rand_pose(10)
    Ta, Tb = g.pose_to_matrix(a), g.pose_to_matrix(b)
    np.testing.assert_allclose(g.pose_to_matrix(g.pose_compose(a, b)).numpy(), (Ta @ Tb).numpy(), atol=1e-12)
    np.testing.assert_allclose(g.pose_to_matrix(g.pose_inverse(a)).numpy(), np.linalg.inv(Ta.numpy()), atol=1e-10)
    np.testing.assert_allclose(g.matrix_to_pose(Ta).numpy(), a.numpy(), atol=1e-10)


def test_transform_points_matches_scipy():
    pose = _rand_pose(1)[0]
    pts = torch.randn(7, 3, dtype=torch.float64)
    expected = _scipy(pose[3:]).apply(pts.numpy()) + pose[:3].numpy()
    np.testing.assert_allclose(g.transform_points(pose, pts).numpy(), expected, atol=1e-12)


def test_interpolate_poses_slerp_and_no_extrapolation():
    t = torch.tensor([0, 1000, 3000], dtype=torch.int64)
    poses = _rand_pose(3)
    q = torch.tensor([0, 500, 1000, 2000, 3000], dtype=torch.int64)
    out = g.interpolate_poses(t, poses, q)
    np.testing.assert_allclose(out[[0, 2, 4]].numpy(), poses.numpy(), atol=1e-12)  # knots come back unchanged
    key = Rotation.from_quat(poses[:, [4, 5, 6, 3]].numpy())
    expected = Slerp([0.0, 1000.0, 3000.0], key)([500.0, 2000.0]).as_matrix()
    np.testing.assert_allclose(g.quat_to_matrix(out[[1, 3], 3:]).numpy(), expected, atol=1e-10)
    np.testing.assert_allclose(out[1, :3].numpy(), ((poses[0, :3] + poses[1, :3]) / 2).numpy(), atol=1e-12)
    with pytest.raises(ValueError, match="extrapolation"):
        g.interpolate_poses(t, poses, torch.tensor([3001]))


def test_check_pose_rejects_bad_poses():
    good = torch.tensor([0.0, 0.0, 0.5, 1.0, 0.0, 0.0, 0.0])
    assert torch.equal(g.check_pose(good), good)
    with pytest.raises(ValueError, match="NaN"):
        g.check_pose(torch.tensor([math.nan, 0, 0.5, 1, 0, 0, 0]))
    with pytest.raises(ValueError, match="unit"):
        g.check_pose(torch.tensor([0, 0, 0.5, 2.0, 0, 0, 0]))
    with pytest.raises(ValueError, match="behind"):
        g.check_pose(torch.tensor([0, 0, -0.5, 1.0, 0, 0, 0]))
    with pytest.raises(ValueError, match="shape"):
        g.check_pose(torch.zeros(6))


def test_perturb_pose_moves_and_turns_by_exactly_the_given_amounts():
    rot = Rotation.random(64, random_state=3)
    q = torch.from_numpy(rot.as_quat()[:, [3, 0, 1, 2]])
    pose = torch.cat((torch.rand(64, 3, dtype=torch.float64), q), -1)
    out = g.perturb_pose(pose, 0.002, math.radians(1.5), torch.Generator().manual_seed(7))
    shift = (out[:, :3] - pose[:, :3]).norm(dim=-1)
    torch.testing.assert_close(shift, torch.full((64,), 0.002, dtype=torch.float64))
    turned = Rotation.from_quat(out[:, [4, 5, 6, 3]].numpy()) * rot.inv()  # the left factor exp(angle * axis)
    np.testing.assert_allclose(turned.magnitude(), math.radians(1.5), rtol=0, atol=1e-9)
    assert (out[:, 3] >= 0).all()
    # the draws are random directions: one generator state gives one draw, another a different one
    again = g.perturb_pose(pose, 0.002, math.radians(1.5), torch.Generator().manual_seed(7))
    other = g.perturb_pose(pose, 0.002, math.radians(1.5), torch.Generator().manual_seed(8))
    assert torch.equal(out, again) and not torch.allclose(out, other)
    directions = (out[:, :3] - pose[:, :3]) / 0.002
    assert directions.mean(0).norm() < 0.35  # not all one way (|mean| of 64 uniform unit vectors: ~0.07)
    assert g.perturb_pose(pose[0].float(), 0.0, 0.0).dtype == torch.float32
    with pytest.raises(ValueError, match="finite and >= 0"):
        g.perturb_pose(pose, -0.001, 0.0)
