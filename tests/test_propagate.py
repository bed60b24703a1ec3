import doctest

import numpy as np
import pytest
import torch
from scipy.integrate import solve_ivp
from scipy.linalg import expm

from torchevtrack import geometry as g
from torchevtrack.camera import Camera
from torchevtrack.stages import propagate as prop_mod
from torchevtrack.stages.propagate import propagate, twist_between

torch.manual_seed(3)


def _rand_pose(n):
    t = torch.randn(n, 3, dtype=torch.float64) * 0.1 + torch.tensor([0.0, 0.0, 0.6], dtype=torch.float64)
    return torch.cat((t, g.quat_canonical(torch.randn(n, 4, dtype=torch.float64))), dim=-1)


def _hat(twist):
    v, w = twist[:3], twist[3:]
    M = np.zeros((4, 4))
    M[:3, :3] = [[0, -w[2], w[1]], [w[2], 0, -w[0]], [-w[1], w[0], 0]]
    M[:3, 3] = v
    return M


def test_matches_ode_of_object_points():
    """Each object point obeys dP/dt = v + w x P (the interaction-matrix model); integrate it with scipy."""
    pose = _rand_pose(4)
    twist = torch.randn(4, 6, dtype=torch.float64) * torch.tensor([0.3, 0.3, 0.3, 2.0, 2.0, 2.0], dtype=torch.float64)
    dt = 0.35
    obj = torch.randn(5, 3, dtype=torch.float64) * 0.05
    obj = torch.cat((torch.zeros(1, 3, dtype=torch.float64), obj))  # include the object origin
    out = propagate(pose, twist, dt)
    for b in range(4):
        v, w = twist[b, :3].numpy(), twist[b, 3:].numpy()
        P0 = g.transform_points(pose[b], obj).numpy()

        def rhs(_, y):
            P = y.reshape(-1, 3)
            return (v + np.cross(w, P)).ravel()

        sol = solve_ivp(rhs, (0.0, dt), P0.ravel(), rtol=1e-11, atol=1e-13, method="DOP853")
        expected = sol.y[:, -1].reshape(-1, 3)
        np.testing.assert_allclose(g.transform_points(out[b], obj).numpy(), expected, atol=1e-9)
        # origin velocity v + w x t, and rotation dR/dt = [w]x R
        R_expected = expm(_hat(twist[b].numpy()) * dt)[:3, :3] @ g.quat_to_matrix(pose[b, 3:]).numpy()
        np.testing.assert_allclose(g.quat_to_matrix(out[b, 3:]).numpy(), R_expected, atol=1e-10)


def test_matches_matrix_exponential_and_per_element_dt():
    pose = _rand_pose(6)
    twist = torch.randn(6, 6, dtype=torch.float64)
    dt = torch.tensor([0.0, 1e-6, 1e-3, 0.1, 0.7, 2.0], dtype=torch.float64)
    out = propagate(pose, twist, dt)
    for b in range(6):
        T = expm(_hat(twist[b].numpy()) * float(dt[b])) @ g.pose_to_matrix(pose[b]).numpy()
        np.testing.assert_allclose(g.pose_to_matrix(out[b]).numpy(), T, atol=1e-10)
    np.testing.assert_allclose(out[0, :3].numpy(), pose[0, :3].numpy(), atol=1e-15)  # dt = 0: unchanged


def test_pure_translation_and_small_rotation_limit():
    pose = _rand_pose(3)
    twist = torch.zeros(3, 6, dtype=torch.float64)
    twist[:, :3] = torch.randn(3, 3, dtype=torch.float64)
    out = propagate(pose, twist, 0.2)
    np.testing.assert_allclose(out[:, :3].numpy(), (pose[:, :3] + 0.2 * twist[:, :3]).numpy(), atol=1e-14)
    # tiny angles take the series branch; compare with expm
    twist[:, 3:] = 1e-6
    out = propagate(pose, twist, 0.5)
    for b in range(3):
        T = expm(_hat(twist[b].numpy()) * 0.5) @ g.pose_to_matrix(pose[b]).numpy()
        np.testing.assert_allclose(g.pose_to_matrix(out[b]).numpy(), T, atol=1e-13)


def test_consistent_with_interaction_matrix():
    """The pixel of a propagated object point moves at L(uv, Z) @ twist for small dt."""
    cam = Camera.default()
    pose = _rand_pose(1)
    obj = torch.randn(20, 3, dtype=torch.float64) * 0.05
    twist = torch.tensor([[0.2, -0.1, 0.3, 1.0, -2.0, 0.5]], dtype=torch.float64)
    h = 1e-6
    P0 = g.transform_points(pose[0], obj)
    uv0 = cam.project(P0)
    uv_p = cam.project(g.transform_points(propagate(pose, twist, h)[0], obj))
    uv_m = cam.project(g.transform_points(propagate(pose, twist, -h)[0], obj))
    flow = (uv_p - uv_m) / (2 * h)
    L = cam.interaction_matrix(uv0, P0[:, 2])
    np.testing.assert_allclose(flow.numpy(), (L @ twist[0]).numpy(), rtol=1e-6, atol=1e-5)


def test_paper_euler_step_misses_w_cross_t():
    """The paper's Eq. 6 (t + v dt) differs from the exact motion by about (w x t) dt."""
    pose = torch.tensor([[0.0, 0.0, 0.5, 1.0, 0.0, 0.0, 0.0]], dtype=torch.float64)
    twist = torch.tensor([[0.0, 0.0, 0.0, 0.0, 1.0, 0.0]], dtype=torch.float64)
    dt = 1e-3
    exact = propagate(pose, twist, dt)
    paper_t = pose[0, :3] + twist[0, :3] * dt
    np.testing.assert_allclose((exact[0, :3] - paper_t).numpy(), [0.5 * dt, 0.0, 0.0], atol=1e-6)  # up to O(dt^2)


def test_bad_shapes():
    with pytest.raises(ValueError, match="pose"):
        propagate(torch.zeros(2, 6), torch.zeros(2, 6), 0.1)
    with pytest.raises(ValueError, match="twist"):
        propagate(torch.zeros(2, 7), torch.zeros(2, 3), 0.1)


def test_docstring_example():
    assert doctest.testmod(prop_mod, raise_on_error=False).failed == 0


def test_twist_between_inverts_propagate_exactly():
    gen = torch.Generator().manual_seed(4)
    pose = torch.cat((torch.randn(5, 3, dtype=torch.float64, generator=gen) * 0.1 + torch.tensor([0, 0, 0.5]),
                      g.quat_canonical(torch.randn(5, 4, dtype=torch.float64, generator=gen))), -1)
    twist = torch.randn(5, 6, dtype=torch.float64, generator=gen) * torch.tensor([0.5] * 3 + [3.0] * 3, dtype=torch.float64)
    twist[0] = 0.0  # no motion
    twist[1, 3:] = 1e-9  # tiny rotation branch
    for dt in (1e-3, 0.2):
        est = twist_between(pose, propagate(pose, twist, dt), dt)
        np.testing.assert_allclose(est.numpy(), twist.numpy(), atol=1e-7)
