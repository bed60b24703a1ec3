import math

import numpy as np
import pytest
import torch
from scipy.spatial.transform import Rotation

from torchevtrack.camera import Camera
from torchevtrack.mesh import load_mesh
from torchevtrack.synth.trajectory import (MOTION_GROUPS, SLIDE_S, leave_and_return, make_trajectory, motion_stats,
                                          pose_at)

CAM = Camera.default()


@pytest.fixture(scope="module")
def can():
    return load_mesh("can")


def rotations(poses):
    q = poses[:, 3:].numpy()
    return Rotation.from_quat(q[:, [1, 2, 3, 0]])  # scipy: (x, y, z, w)


@pytest.mark.parametrize("motion", ["regular", "fast"])
def test_speed_ranges_view_and_depth(motion, can):
    t_us, poses = make_trajectory(motion, 1.0, 11, CAM, can)
    g = MOTION_GROUPS[motion]
    assert t_us.dtype == torch.int64 and poses.dtype == torch.float64 and poses.shape == (10_001, 7)
    assert t_us[0] == 0 and t_us[-1] == 1_000_000 and (torch.diff(t_us) == 100).all()
    p = poses.numpy()
    # centroid image speed, measured independently with numpy
    u = CAM.fx * p[:, 0] / p[:, 2] + CAM.cx
    v = CAM.fy * p[:, 1] / p[:, 2] + CAM.cy
    speed = np.hypot(np.diff(u), np.diff(v)) / 1e-4
    in_range = (speed > 0.97 * g.speed_px_s[0]) & (speed < 1.03 * g.speed_px_s[1])
    assert in_range.mean() > 0.9 and speed.max() < 1.03 * g.speed_px_s[1]
    # angular speed from scipy: |log(R_{k+1} R_k^T)| / dt
    R = rotations(poses)
    w = (R[1:] * R[:-1].inv()).magnitude() / 1e-4
    assert np.degrees(w).max() <= 1.01 * g.max_rot_deg_s
    assert np.degrees(w).max() >= 0.3 * g.max_rot_deg_s
    # every mesh vertex stays inside the image (every 10th pose)
    V = np.asarray(can.vertices)
    for k in range(0, len(p), 10):
        X = R[k].apply(V) + p[k, :3]
        uu = CAM.fx * X[:, 0] / X[:, 2] + CAM.cx
        vv = CAM.fy * X[:, 1] / X[:, 2] + CAM.cy
        assert uu.min() >= 0 and vv.min() >= 0 and uu.max() <= CAM.width - 1 and vv.max() <= CAM.height - 1
    assert p[:, 2].min() >= 0.3 - 1e-9 and p[:, 2].max() <= 0.7 + 1e-9
    assert np.allclose(np.linalg.norm(p[:, 3:], axis=1), 1.0) and (p[:, 3] >= 0).all()


@pytest.mark.parametrize("motion", ["regular", "fast"])
def test_peak_rotation_speed_over_20s(motion, can):
    # the angular velocity is scaled so that its peak over 20 s is 80-100 % of the group's limit
    t_us, poses = make_trajectory(motion, 20.0, 2, CAM, can, dt_us=1000)
    R = rotations(poses)
    w = np.degrees((R[1:] * R[:-1].inv()).magnitude() / 1e-3)
    assert 0.79 * MOTION_GROUPS[motion].max_rot_deg_s <= w.max() <= 1.01 * MOTION_GROUPS[motion].max_rot_deg_s


def test_short_trajectory_is_not_stretched(can):
    # 50 ms must not sweep the whole depth range (normalisation over a long reference window)
    _, poses = make_trajectory("fast", 0.05, 3, CAM, can)
    assert float(poses[:, 2].max() - poses[:, 2].min()) < 0.05


def test_smooth_motion(can):
    # seed 5 over 2 s crosses a cusp of the random image curve: the object must slow down there, not
    # reverse at full speed (which showed as a 14000 m/s^2 spike)
    t_us, poses = make_trajectory("fast", 2.0, 5, CAM, can)
    p = poses.numpy()
    acc = np.linalg.norm(np.diff(p[:, :3], 2, axis=0), axis=1) / 1e-8  # m/s^2
    assert acc.max() < 1000.0
    R = rotations(poses)
    w = (R[1:] * R[:-1].inv()).as_rotvec() / 1e-4  # camera-frame angular velocity, rad/s
    assert np.abs(np.diff(w, axis=0)).max() / 1e-4 < 2000.0  # rad/s^2: no jumps


def test_seeded_determinism(can):
    a = make_trajectory("regular", 0.2, 3, CAM, can)
    b = make_trajectory("regular", 0.2, 3, CAM, can)
    c = make_trajectory("regular", 0.2, 4, CAM, can)
    assert torch.equal(a[1], b[1]) and torch.equal(a[0], b[0])
    assert not torch.allclose(a[1], c[1])


def test_large_object_pushed_back_and_in_view():
    big = load_mesh("box")  # 0.16 x 0.06 x 0.21 m: does not fit at 0.3 m in 480 rows
    small = Camera(64, 48, 50.0, 50.0, 31.5, 23.5)
    for cam in (CAM, small):
        _, poses = make_trajectory("fast", 0.3, 2, cam, big)
        assert poses[:, 2].min() > 0.3
        R = rotations(poses)
        for k in range(0, len(poses), 50):
            X = R[k].apply(np.asarray(big.vertices)) + poses[k, :3].numpy()
            uu = cam.fx * X[:, 0] / X[:, 2] + cam.cx
            vv = cam.fy * X[:, 1] / X[:, 2] + cam.cy
            assert uu.min() >= 0 and vv.min() >= 0 and uu.max() <= cam.width - 1 and vv.max() <= cam.height - 1


def test_motion_stats_and_pose_at(can):
    t_us, poses = make_trajectory("regular", 0.3, 1, CAM, can)
    s = motion_stats(t_us, poses, CAM)
    uv = poses[:, :2].numpy() / poses[:, 2:3].numpy() * CAM.fx + np.array([CAM.cx, CAM.cy])
    sp = np.linalg.norm(np.diff(uv, axis=0), axis=1) / 1e-4
    assert math.isclose(s["image_speed_px_s"]["median"], float(np.median(sp)), rel_tol=1e-6)
    assert math.isclose(s["image_speed_px_s"]["max"], float(sp.max()), rel_tol=1e-9)
    ang = np.degrees((rotations(poses)[1:] * rotations(poses)[:-1].inv()).magnitude()) / 1e-4
    assert math.isclose(s["angular_speed_deg_s"]["mean"], float(ang.mean()), rel_tol=1e-4)
    assert torch.allclose(pose_at(t_us, poses, [0, 1000]), poses[[0, 10]])
    mid = pose_at(t_us, poses, [150])[0]
    assert torch.allclose(mid[:3], 0.5 * (poses[1, :3] + poses[2, :3]))


def test_bad_arguments(can):
    with pytest.raises(ValueError, match="motion"):
        make_trajectory("slow", 1.0, 0, CAM, can)
    with pytest.raises(ValueError, match="duration"):
        make_trajectory("fast", 0.0, 0, CAM, can)
    with pytest.raises(TypeError, match="seed"):
        make_trajectory("fast", 1.0, 0.5, CAM, can)


def test_leave_and_return_goes_out_of_view_and_back_onto_the_path(can):
    """Before the excursion and after it the poses are the path's; while away every pixel of the object's bounding
    sphere is outside the image; depth and rotation never change; the object slides steadily out and back."""
    t, path = make_trajectory("regular", 2.0, 5, CAM, can)
    start, away = 0.4, 0.3
    poses = leave_and_return(t, path, CAM, can, start, away)
    s = t.double() / 1e6
    before, after = s < start, s > start + 2 * SLIDE_S + away
    gone = (s >= start + SLIDE_S) & (s <= start + SLIDE_S + away)
    assert torch.equal(poses[before], path[before]) and torch.equal(poses[after], path[after])
    assert torch.equal(poses[:, 2:], path[:, 2:].double())
    radius = float(can.bounding_sphere.primitive.radius + np.linalg.norm(can.bounding_sphere.primitive.center))
    z = poses[gone, 2]
    u = CAM.fx * poses[gone, 0] / z + CAM.cx
    r_px = CAM.fx * radius / (z - radius)
    assert bool(((u - r_px > CAM.width - 1) | (u + r_px < 0)).all())
    sliding = (s > start) & (s < start + SLIDE_S)
    du = torch.diff(CAM.fx * poses[sliding, 0] / poses[sliding, 2] - CAM.fx * path[sliding, 0] / path[sliding, 2])
    assert bool((du > 0).all() or (du < 0).all())  # one way out, relative to the path
    with pytest.raises(ValueError, match="start_s >= 0"):
        leave_and_return(t, path, CAM, can, -0.1, 0.2)
