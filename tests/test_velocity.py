import doctest
import math

import numpy as np
import pytest
import torch
from filterpy.kalman import KalmanFilter

from torchevtrack import geometry as g
from torchevtrack.camera import Camera
from torchevtrack.config import VelocityConfig
from torchevtrack.stages import velocity as vel_mod
from torchevtrack.stages.velocity import (CorrectionFeedback, VelocityKF, kf_predict, kf_update, turn_decay,
                                         turn_persistence, turn_update)

CAM = Camera.default()
F64 = torch.float64
SCALE = torch.tensor([0.3, 0.3, 0.3, 2.0, 2.0, 2.0], dtype=F64)


def _scene(gen, G, B=None):
    """Random pixels over the sensor with depths 0.3..0.8 m."""
    shape = (G,) if B is None else (B, G)
    uv = torch.rand(*shape, 2, dtype=F64, generator=gen) * torch.tensor([600.0, 440.0], dtype=F64) + 20.0
    depth = 0.3 + 0.5 * torch.rand(*shape, dtype=F64, generator=gen)
    return uv, depth


def _flow(uv, depth, twist):
    return (CAM.interaction_matrix(uv, depth) @ twist[..., None, :, None])[..., 0]


def _rel(a, b):
    return float((a - b).norm() / b.norm())


def test_interaction_matrix_matches_finite_differences():
    """dP/dt = v + w x P for object points; the projected velocity is L(uv, Z) @ [v, w]."""
    gen = torch.Generator().manual_seed(0)
    P = torch.randn(40, 3, dtype=F64, generator=gen) * torch.tensor([0.2, 0.15, 0.1], dtype=F64)
    P[:, 2] += 0.6
    twist = torch.randn(6, dtype=F64, generator=gen) * SCALE
    v, w = twist[:3], twist[3:]
    h = 1e-6
    vel = v + torch.linalg.cross(w.expand_as(P), P, dim=-1)
    # central differences of the exact rigid motion (rotation about the camera origin + translation)
    def moved(s):
        return g.quat_rotate(g.quat_exp(w * s), P) + v * s + 0.5 * s * s * torch.linalg.cross(w.expand_as(P), v.expand_as(P), dim=-1)

    fd = (CAM.project(moved(h)) - CAM.project(moved(-h))) / (2 * h)
    uv = CAM.project(P)
    L = CAM.interaction_matrix(uv, P[:, 2])
    np.testing.assert_allclose((L @ twist).numpy(), fd.numpy(), rtol=1e-6, atol=1e-4)
    # and the analytic derivative of the projection along dP/dt
    X, Y, Z = P.unbind(-1)
    du = CAM.fx * (vel[:, 0] / Z - X * vel[:, 2] / Z**2)
    dv = CAM.fy * (vel[:, 1] / Z - Y * vel[:, 2] / Z**2)
    np.testing.assert_allclose((L @ twist).numpy(), torch.stack((du, dv), -1).numpy(), rtol=1e-10, atol=1e-8)


def test_single_update_is_least_squares():
    """Huge P0 and no re-weighting: the update is the least-squares twist (numpy lstsq oracle)."""
    gen = torch.Generator().manual_seed(1)
    uv, depth = _scene(gen, 80)
    twist = torch.randn(6, dtype=F64, generator=gen) * SCALE
    flow = _flow(uv, depth, twist) + 30.0 * torch.randn(80, 2, dtype=F64, generator=gen)
    dt = 0.004
    A = (CAM.interaction_matrix(uv, depth) * dt).reshape(-1, 6).numpy()
    expected = np.linalg.lstsq(A, (flow * dt).reshape(-1).numpy(), rcond=None)[0]
    x0 = torch.zeros(1, 6, dtype=F64)
    P0 = torch.eye(6, dtype=F64)[None] * 1e10
    out = kf_update(x0, P0, uv[None], flow[None], depth[None], torch.ones(1, 80, dtype=torch.bool), CAM, dt, iters=0)
    np.testing.assert_allclose(out.x[0].numpy(), expected, rtol=1e-7, atol=1e-9)
    np.testing.assert_allclose(out.P[0].numpy(), np.linalg.inv(A.T @ A), rtol=1e-6)
    assert bool(out.used[0]) and torch.all(out.weights == 1)


def test_filter_converges_to_constant_twist():
    gen = torch.Generator().manual_seed(2)
    twist = torch.tensor([0.2, -0.1, 0.15, 1.0, -1.5, 2.0], dtype=F64)
    kf = VelocityKF(CAM)
    for _ in range(8):
        uv, depth = _scene(gen, 100)
        flow = _flow(uv, depth, twist) + 20.0 * torch.randn(100, 2, dtype=F64, generator=gen)
        kf.predict()
        kf.update(uv[None], flow[None], depth[None], torch.ones(1, 100, dtype=torch.bool), dt=0.002)
    assert _rel(kf.x[0], twist) < 0.03


def test_robust_reweighting_rejects_gross_outliers():
    gen = torch.Generator().manual_seed(3)
    G, dt = 120, 0.002
    twist = torch.tensor([0.25, 0.1, -0.2, -1.0, 2.0, 1.5], dtype=F64)
    uv, depth = _scene(gen, G)
    flow = _flow(uv, depth, twist) + 20.0 * torch.randn(G, 2, dtype=F64, generator=gen)
    out_idx = torch.randperm(G, generator=gen)[: int(0.3 * G)]
    flow[out_idx] = (torch.rand(len(out_idx), 2, dtype=F64, generator=gen) - 0.5) * 4000.0
    x0, P0 = torch.zeros(1, 6, dtype=F64), torch.diag(torch.tensor([1.0] * 3 + [25.0] * 3, dtype=F64))[None]
    args = (uv[None], flow[None], depth[None], torch.ones(1, G, dtype=torch.bool), CAM, dt)
    r_px = 20.0 * dt  # the inlier noise in px of displacement per update
    robust = kf_update(x0, P0, *args, r_px=r_px, iters=3)
    plain = kf_update(x0, P0, *args, r_px=r_px, iters=0)
    assert _rel(robust.x[0], twist) < 0.05
    assert _rel(plain.x[0], twist) > 0.3
    inlier = torch.ones(G, dtype=torch.bool)
    inlier[out_idx] = False
    assert float(robust.weights[0, ~inlier].max()) < 0.05 < float(robust.weights[0, inlier].median())


def test_batch_equals_separate_runs_with_padding_and_too_few_vectors():
    gen = torch.Generator().manual_seed(4)
    B, G = 3, 50
    uv, depth = _scene(gen, G, B)
    twists = torch.randn(B, 6, dtype=F64, generator=gen) * SCALE
    flow = _flow(uv, depth, twists) + 10.0 * torch.randn(B, G, 2, dtype=F64, generator=gen)
    valid = torch.ones(B, G, dtype=torch.bool)
    valid[1, 30:] = False  # padding
    valid[2, 2:] = False  # only 2 vectors: predict only
    depth[0, :5] = 0.0  # background depth: ignored
    dt = torch.tensor([0.002, 0.004, 0.003], dtype=F64)
    batch = VelocityKF(CAM, batch_size=B)
    singles = [VelocityKF(CAM) for _ in range(B)]
    for _ in range(3):
        batch.predict()
        out = batch.update(uv, flow, depth, valid, dt)
        for b, kf in enumerate(singles):
            keep = valid[b] & (depth[b] > 0)
            kf.predict()
            kf.update(uv[b, keep][None], flow[b, keep][None], depth[b, keep][None], torch.ones(1, int(keep.sum()), dtype=torch.bool), float(dt[b]))
    for b, kf in enumerate(singles):
        np.testing.assert_allclose(batch.x[b].numpy(), kf.x[0].numpy(), rtol=1e-9, atol=1e-12)
        np.testing.assert_allclose(batch.P[b].numpy(), kf.P[0].numpy(), rtol=1e-9, atol=1e-15)
    assert out.used.tolist() == [True, True, False]
    assert torch.all(out.weights[0, :5] == 0) and torch.all(out.weights[1, 30:] == 0)
    # filter 2 never updated: it only followed the motion model
    x, P = torch.zeros(1, 6, dtype=F64), batch.P0[None]
    for _ in range(3):
        x, P = kf_predict(x, P, batch.rho, batch.Q)
    np.testing.assert_allclose(batch.P[2].numpy(), P[0].numpy(), rtol=1e-12)


def test_linear_step_matches_filterpy():
    gen = torch.Generator().manual_seed(5)
    G, dt, r_px, rho = 25, 0.003, 0.7, 0.5
    uv, depth = _scene(gen, G)
    flow = _flow(uv, depth, torch.randn(6, dtype=F64, generator=gen) * SCALE) + 40.0 * torch.randn(G, 2, dtype=F64, generator=gen)
    x0 = torch.randn(6, dtype=F64, generator=gen) * SCALE
    M = torch.randn(6, 6, dtype=F64, generator=gen)
    P0 = M @ M.T * 0.1 + torch.eye(6, dtype=F64) * 0.05
    Q = torch.diag(torch.tensor([0.1, 0.2, 0.3, 1.0, 2.0, 3.0], dtype=F64))

    ref = KalmanFilter(dim_x=6, dim_z=2 * G)
    ref.x, ref.P = x0.numpy().copy(), P0.numpy().copy()
    ref.F, ref.Q = np.eye(6) * rho, Q.numpy()
    ref.H = (CAM.interaction_matrix(uv, depth) * dt).reshape(-1, 6).numpy()
    ref.R = np.eye(2 * G) * r_px**2
    ref.predict()
    ref.update((flow * dt).reshape(-1).numpy())

    x, P = kf_predict(x0[None], P0[None], rho, Q)
    out = kf_update(x, P, uv[None], flow[None], depth[None], torch.ones(1, G, dtype=torch.bool), CAM, dt, r_px=r_px, iters=0)
    np.testing.assert_allclose(out.x[0].numpy(), ref.x, rtol=1e-8, atol=1e-10)
    np.testing.assert_allclose(out.P[0].numpy(), ref.P, rtol=1e-7, atol=1e-12)


def test_speed_proportional_noise_matches_filterpy():
    """With ``r_rel > 0`` each vector's noise is ``sqrt(r_px^2 + (r_rel |F| dt)^2)`` px: filterpy's KF with that
    diagonal R is the oracle (plain update, no re-weighting); a fast vector then counts less than a slow one."""
    gen = torch.Generator().manual_seed(7)
    G, dt, r_px, r_rel, rho = 25, 0.002, 0.2, 0.4, 0.75
    uv, depth = _scene(gen, G)
    flow = _flow(uv, depth, torch.randn(6, dtype=F64, generator=gen) * SCALE) + 40.0 * torch.randn(G, 2, dtype=F64, generator=gen)
    x0 = torch.randn(6, dtype=F64, generator=gen) * SCALE
    P0 = torch.eye(6, dtype=F64) * 0.5
    Q = torch.diag(torch.tensor([0.1, 0.2, 0.3, 1.0, 2.0, 3.0], dtype=F64))
    sigma2 = r_px**2 + (r_rel * flow.norm(dim=-1) * dt) ** 2  # (G,) px^2

    ref = KalmanFilter(dim_x=6, dim_z=2 * G)
    ref.x, ref.P = x0.numpy().copy(), P0.numpy().copy()
    ref.F, ref.Q = np.eye(6) * rho, Q.numpy()
    ref.H = (CAM.interaction_matrix(uv, depth) * dt).reshape(-1, 6).numpy()
    ref.R = np.diag(sigma2.repeat_interleave(2).numpy())
    ref.predict()
    ref.update((flow * dt).reshape(-1).numpy())

    x, P = kf_predict(x0[None], P0[None], rho, Q)
    args = (uv[None], flow[None], depth[None], torch.ones(1, G, dtype=torch.bool), CAM, dt)
    out = kf_update(x, P, *args, r_px=r_px, r_rel=r_rel, iters=0)
    np.testing.assert_allclose(out.x[0].numpy(), ref.x, rtol=1e-8, atol=1e-10)
    np.testing.assert_allclose(out.P[0].numpy(), ref.P, rtol=1e-7, atol=1e-12)
    flat = kf_update(x, P, *args, r_px=r_px, iters=0)  # r_rel = 0: every vector at r_px, more information
    assert float(torch.linalg.det(flat.P[0])) < float(torch.linalg.det(out.P[0]))
    with pytest.raises(ValueError, match="r_rel"):
        kf_update(x, P, *args, r_px=r_px, r_rel=-0.1)


def _turn_twists(steps: int, gen: torch.Generator) -> torch.Tensor:
    """Flow twists of a steady turn (element 0: 4 rad/s about a fixed tilted axis) and of a rotation that reverses
    every update (element 1), both with a drifting translation."""
    axis = torch.tensor([0.6, -0.7, 0.4], dtype=F64)
    axis /= axis.norm()
    tw = torch.zeros(steps, 2, 6, dtype=F64)
    tw[:, :, :3] = 0.05 * torch.randn(steps, 2, 3, dtype=F64, generator=gen)
    tw[:, 0, 3:] = 4.0 * axis
    tw[:, 1, 3:] = 4.0 * axis * torch.tensor([(-1.0) ** k for k in range(steps)], dtype=F64)[:, None]
    return tw


def test_turn_decay_matches_filterpy_with_its_own_running_means():
    """Oracle: filterpy's KF per element, its transition ``F = diag(d)`` rebuilt every step from running means of
    its own posterior rotation rate (numpy, the definition of turn_update / turn_persistence / turn_decay)."""
    gen = torch.Generator().manual_seed(11)
    G, dt, steps, rho, rho_turn, ema = 30, 0.002, 12, 0.75, 0.9, 0.2
    kf = VelocityKF(CAM, rho=rho, rho_turn=rho_turn, turn_ema=ema, r_px=0.3, r_rel=0.0, iters=0, batch_size=2)
    twists = _turn_twists(steps, gen)
    refs, means = [], np.zeros((2, 4))
    for b in range(2):
        ref = KalmanFilter(dim_x=6, dim_z=2 * G)
        ref.x, ref.P, ref.Q = np.zeros(6), kf.P0.numpy().copy(), kf.Q.numpy().copy()
        ref.R = np.eye(2 * G) * 0.3**2
        refs.append(ref)
    for k in range(steps):
        uv, depth = _scene(gen, G, B=2)
        flow = _flow(uv, depth, twists[k]) + 20.0 * torch.randn(2, G, 2, dtype=F64, generator=gen)
        kf.predict()
        kf.update(uv, flow, depth, torch.ones(2, G, dtype=torch.bool), dt)
        for b, ref in enumerate(refs):
            m, s = means[b, :3], means[b, 3]
            p = min(np.linalg.norm(m) / s, 1.0) if s > 0 else 0.0
            d = np.full(6, rho)
            d[3:5] = rho + (rho_turn - rho) * p
            ref.F = np.diag(d)
            ref.H = (CAM.interaction_matrix(uv[b], depth[b]) * dt).reshape(-1, 6).numpy()
            ref.predict()
            ref.update((flow[b] * dt).reshape(-1).numpy())
            w = ref.x[3:]
            means[b, :3] += ema * (w - means[b, :3])
            means[b, 3] += ema * (np.linalg.norm(w) - means[b, 3])
    for b, ref in enumerate(refs):
        np.testing.assert_allclose(kf.x[b].numpy(), ref.x, rtol=1e-8, atol=1e-9)
        np.testing.assert_allclose(kf.P[b].numpy(), ref.P, rtol=1e-7, atol=1e-12)
    np.testing.assert_allclose(kf.turn.numpy(), means, rtol=1e-9, atol=1e-12)
    p = turn_persistence(kf.turn)
    assert p[0] > 0.9 and p[1] < 0.5  # the steady turn, the reversing rotation
    d = turn_decay(kf.turn, rho, rho_turn)
    assert d[0, 3] > 0.87 and d[1, 3] < 0.8
    assert torch.all(d[:, [0, 1, 2, 5]] == rho) and torch.all(d[:, 3] == d[:, 4])


def test_turn_running_means_and_reset():
    """A rate about a fixed axis gives persistence 1 and the pitch and yaw decay rho_turn; a rate that flips
    every update gives nearly 0; no rotation at all gives 0; reset clears the selected elements only."""
    turn = torch.zeros(3, 4, dtype=F64)
    x = torch.zeros(3, 6, dtype=F64)
    for k in range(200):
        x[0, 3:] = torch.tensor([1.0, 2.0, -0.5], dtype=F64) * (1 + 0.2 * math.sin(k))  # steady axis, varying rate
        x[1, 3:] = torch.tensor([0.0, 3.0, 0.0], dtype=F64) * (-1) ** k
        x[2, :3] = 0.3  # translation only
        turn = turn_update(turn, x, 0.05)
    p = turn_persistence(turn)
    assert abs(float(p[0]) - 1.0) < 1e-9 and float(p[1]) < 0.06 and float(p[2]) == 0.0
    d = turn_decay(turn, 0.75, 0.9)
    torch.testing.assert_close(d[0], torch.tensor([0.75, 0.75, 0.75, 0.9, 0.9, 0.75], dtype=F64))
    torch.testing.assert_close(d[2], torch.full((6,), 0.75, dtype=F64))
    one = turn_decay(turn, 0.75, 0.75)  # rho_turn = rho: the single decay of the paper's model
    assert torch.all(one == 0.75)

    kf = VelocityKF(CAM, batch_size=3)
    kf.turn.copy_(turn)
    kf.reset(mask=torch.tensor([True, False, False]))
    assert torch.all(kf.turn[0] == 0) and torch.equal(kf.turn[1:], turn[1:])
    assert "turn" in kf.state_dict()
    with pytest.raises(ValueError, match="rho_turn"):
        VelocityKF(CAM, rho_turn=1.5)
    with pytest.raises(ValueError, match="turn_ema"):
        VelocityKF(CAM, turn_ema=0.0)
    with pytest.raises(ValueError, match="decay"):
        kf_predict(torch.zeros(2, 6, dtype=F64), torch.eye(6, dtype=F64).expand(2, 6, 6), torch.ones(3, 6), kf.Q)


@pytest.mark.parametrize("k", [0.5, 2.0])
def test_one_reweighting_round_is_weighted_least_squares_with_laplacian_weights(k):
    """Huge P0, one round: weights ``exp(-max(r - m, 0) / (k max(1.4826 m, 1)))`` from the plain fit's
    residuals ``r`` (units of ``r_px``; ``m`` their lower median), then the weighted least-squares twist."""
    gen = torch.Generator().manual_seed(11)
    G, dt, r_px = 60, 0.002, 0.05
    uv, depth = _scene(gen, G)
    twist = torch.randn(6, dtype=F64, generator=gen) * SCALE
    flow = _flow(uv, depth, twist) + 40.0 * torch.randn(G, 2, dtype=F64, generator=gen)
    flow[:10] += 800.0 * torch.randn(10, 2, dtype=F64, generator=gen)
    A = (CAM.interaction_matrix(uv, depth) * dt).numpy()  # (G, 2, 6)
    z = (flow * dt).numpy()
    plain = np.linalg.lstsq(A.reshape(-1, 6), z.reshape(-1), rcond=None)[0]
    r = np.linalg.norm(z - A @ plain, axis=-1) / r_px
    m = np.sort(r)[(G - 1) // 2]
    w = np.exp(-np.maximum(r - m, 0.0) / (k * max(1.4826 * m, 1.0)))
    sw = np.repeat(np.sqrt(w), 2)
    expected = np.linalg.lstsq(A.reshape(-1, 6) * sw[:, None], z.reshape(-1) * sw, rcond=None)[0]
    out = kf_update(torch.zeros(1, 6, dtype=F64), torch.eye(6, dtype=F64)[None] * 1e10, uv[None], flow[None],
                    depth[None], torch.ones(1, G, dtype=torch.bool), CAM, dt, r_px=r_px, iters=1, k=k)
    np.testing.assert_allclose(out.weights[0].numpy(), w, rtol=1e-6, atol=1e-9)
    np.testing.assert_allclose(out.x[0].numpy(), expected, rtol=1e-6, atol=1e-9)
    assert np.median(w[:10]) < 0.1 < np.median(w[10:])


def test_the_first_reweighting_round_starts_from_the_prior_when_it_fits_the_median_vector_better():
    """Vectors of a wrong flow that drag the plain update (here 45 %, all the same way) leave the median vector
    unfitted; the prior (the true twist) fits it. Then the first round's weights are those of the residuals at the
    prior, and the posterior is the information-form update with them: one round, against numpy."""
    gen = torch.Generator().manual_seed(5)
    G, dt, r_px, k = 60, 0.002, 0.05, 0.5
    uv, depth = _scene(gen, G)
    twist = torch.randn(6, dtype=F64, generator=gen) * SCALE
    flow = _flow(uv, depth, twist) + 20.0 * torch.randn(G, 2, dtype=F64, generator=gen)
    flow[:27, 0] += 900.0
    H = (CAM.interaction_matrix(uv, depth) * dt).numpy().reshape(-1, 6)
    z = (flow * dt).numpy().reshape(-1)
    x0 = twist.numpy()
    Y0 = np.eye(6) / 1e4
    info = lambda w: Y0 + H.T @ (H * np.repeat(w, 2)[:, None]) / r_px ** 2
    solve = lambda w: x0 + np.linalg.solve(info(w), H.T @ (np.repeat(w, 2) * (z - H @ x0)) / r_px ** 2)
    resid = lambda x: np.linalg.norm((z - H @ x).reshape(G, 2), axis=1) / r_px
    lower_median = lambda r: np.sort(r)[(G - 1) // 2]
    r_plain, r_prior = resid(solve(np.ones(G))), resid(x0)
    assert lower_median(r_prior) < lower_median(r_plain)  # the case under test
    m = lower_median(r_prior)
    w = np.exp(-np.maximum(r_prior - m, 0.0) / (k * max(1.4826 * m, 1.0)))
    out = kf_update(twist[None], torch.eye(6, dtype=F64)[None] * 1e4, uv[None], flow[None], depth[None],
                    torch.ones(1, G, dtype=torch.bool), CAM, dt, r_px=r_px, iters=1, k=k)
    np.testing.assert_allclose(out.weights[0].numpy(), w, rtol=1e-6, atol=1e-9)
    np.testing.assert_allclose(out.x[0].numpy(), solve(w), rtol=1e-6, atol=1e-9)
    assert float(w[:27].max()) < 0.01 < float(np.median(w[27:]))
    plain = kf_update(twist[None], torch.eye(6, dtype=F64)[None] * 1e4, uv[None], flow[None], depth[None],
                      torch.ones(1, G, dtype=torch.bool), CAM, dt, r_px=r_px, iters=0)
    assert _rel(out.x[0], twist) < 0.1 < _rel(plain.x[0], twist)


def test_velocity_config_sets_the_robust_width():
    cfg = VelocityConfig(robust_k=0.5)
    assert VelocityKF.from_config(CAM, cfg).k == 0.5
    with pytest.raises(ValueError, match="k must be positive"):
        VelocityKF.from_config(CAM, VelocityConfig(robust_k=0.0))


def test_bad_inputs():
    x, P = torch.zeros(1, 6, dtype=F64), torch.eye(6, dtype=F64)[None]
    uv, flow = torch.zeros(1, 4, 2), torch.zeros(1, 4, 2)
    depth, valid = torch.ones(1, 4), torch.ones(1, 4, dtype=torch.bool)
    with pytest.raises(ValueError, match="uv"):
        kf_update(x, P, torch.zeros(1, 4, 3), flow, depth, valid, CAM, 0.01)
    with pytest.raises(ValueError, match="flow"):
        kf_update(x, P, uv, torch.zeros(1, 5, 2), depth, valid, CAM, 0.01)
    with pytest.raises(TypeError, match="valid"):
        kf_update(x, P, uv, flow, depth, valid.float(), CAM, 0.01)
    with pytest.raises(ValueError, match="dt"):
        kf_update(x, P, uv, flow, depth, valid, CAM, 0.0)
    with pytest.raises(TypeError, match="camera"):
        VelocityKF("cam")
    with pytest.raises(ValueError, match="twist"):
        VelocityKF(CAM, batch_size=2).reset(torch.zeros(1, 6))


def test_docstring_example():
    assert doctest.testmod(vel_mod, raise_on_error=False).failed == 0


def test_reweighting_leaves_clean_data_alone():
    """Residuals within the nominal noise r_px are not re-weighted (no collapse onto a subset)."""
    gen = torch.Generator().manual_seed(6)
    uv, depth = _scene(gen, 60)
    twist = torch.randn(6, dtype=F64, generator=gen) * SCALE
    flow = _flow(uv, depth, twist) + 5.0 * torch.randn(60, 2, dtype=F64, generator=gen)
    x0, P0 = torch.zeros(1, 6, dtype=F64), torch.eye(6, dtype=F64)[None]
    args = (uv[None], flow[None], depth[None], torch.ones(1, 60, dtype=torch.bool), CAM, 0.002)
    robust, plain = kf_update(x0, P0, *args, iters=3), kf_update(x0, P0, *args, iters=0)
    assert float(robust.weights.min()) > 0.85
    assert _rel(robust.x[0], plain.x[0]) < 1e-2


def test_normal_flow_update_is_projected_least_squares():
    """Normal flows (the true flow projected on random edge normals) recover the twist; the oracle is
    numpy lstsq on the projected rows n^T L, while reading them as full flows is biased."""
    gen = torch.Generator().manual_seed(7)
    G = 120
    uv, depth = _scene(gen, G)
    twist = torch.randn(6, dtype=F64, generator=gen) * SCALE
    full = _flow(uv, depth, twist)
    angle = torch.rand(G, dtype=F64, generator=gen) * 2 * np.pi
    n = torch.stack((angle.cos(), angle.sin()), -1)
    proj = (full * n).sum(-1, keepdim=True)
    n = torch.where(proj < 0, -n, n)  # the normal flow points along +n
    normal_flow = n * proj.abs()
    dt = 0.002
    L = CAM.interaction_matrix(uv, depth)
    A = ((n[:, None, :] @ L)[:, 0, :] * dt).numpy()
    expected = np.linalg.lstsq(A, (proj.abs()[:, 0] * dt).numpy(), rcond=None)[0]
    x0 = torch.zeros(1, 6, dtype=F64)
    P0 = torch.eye(6, dtype=F64)[None] * 1e10
    ok = torch.ones(1, G, dtype=torch.bool)
    out = kf_update(x0, P0, uv[None], normal_flow[None], depth[None], ok, CAM, dt, iters=0, normal=True)
    np.testing.assert_allclose(out.x[0].numpy(), expected, rtol=1e-6, atol=1e-8)
    assert _rel(out.x[0], twist) < 1e-6
    biased = kf_update(x0, P0, uv[None], normal_flow[None], depth[None], ok, CAM, dt, iters=0)
    assert _rel(biased.x[0], twist) > 0.1


def test_centre_parametrisation_recovers_the_centre_velocity():
    """With centre=c the state is [c_dot, w], c_dot = v + w x c; lstsq on L A(c) is the oracle, and
    shift_twist by -c maps it back to the camera-origin twist (and by +c forward)."""
    from torchevtrack.stages.velocity import shift_twist

    gen = torch.Generator().manual_seed(11)
    uv, depth = _scene(gen, 60)
    twist = torch.randn(6, dtype=F64, generator=gen) * SCALE
    c = torch.tensor([[0.05, -0.03, 0.5]], dtype=F64)
    flow = _flow(uv, depth, twist)
    x0 = torch.zeros(1, 6, dtype=F64)
    P0 = torch.eye(6, dtype=F64)[None] * 1e10
    ok = torch.ones(1, 60, dtype=torch.bool)
    out = kf_update(x0, P0, uv[None], flow[None], depth[None], ok, CAM, 0.002, iters=0, centre=c)
    c_dot = twist[:3] + torch.linalg.cross(twist[3:], c[0])
    np.testing.assert_allclose(out.x[0, :3].numpy(), c_dot.numpy(), atol=1e-7)
    np.testing.assert_allclose(out.x[0, 3:].numpy(), twist[3:].numpy(), atol=1e-7)
    back = shift_twist(out.x, -c)[0]
    np.testing.assert_allclose(back.numpy(), twist.numpy(), atol=1e-7)
    np.testing.assert_allclose(shift_twist(twist[None], c)[0, :3].numpy(), c_dot.numpy(), rtol=1e-12)


# -- correction feedback -----------------------------------------------------------------------------
def test_feedback_follows_its_recursion_on_its_axes_only():
    """Against a plain-Python loop of b+ = leak b + gain r; the other axes stay exactly zero."""
    gen = torch.Generator().manual_seed(3)
    fb = CorrectionFeedback(gain=0.2, leak=0.7, axes=["vz", "wy"], max_v=math.inf, max_w=math.inf, batch_size=2)
    rates = torch.randn(30, 2, 6, dtype=torch.float64, generator=gen)
    ref = [[0.0] * 6 for _ in range(2)]
    for r in rates:
        b = fb(r)
        for i in range(2):
            for a in range(6):
                ref[i][a] = 0.7 * ref[i][a] + 0.2 * float(r[i, a]) if a in (2, 4) else 0.0
        assert torch.allclose(b, torch.tensor(ref, dtype=torch.float64), rtol=1e-12, atol=1e-15)
    assert not b[:, [0, 1, 3, 5]].any() and b[:, [2, 4]].abs().min() > 0


def test_feedback_halves_the_lag_of_a_partial_correction():
    """Closed loop on one axis: the truth moves at v, the flow twist misses it, each correction removes a
    fraction alpha of the remaining error. Without feedback the corrected pose lags by (1 - a) v dt / a;
    with feedback of gain / (1 - leak) = k the lag is divided by 1 + k (steady state of the loop)."""
    v, dt, alpha = 0.3, 0.002, 0.4

    def lag(fb):
        truth = corrected = 0.0
        for _ in range(400):
            b = 0.0 if fb is None else float(fb.b[0, 2])
            predicted = corrected + b * dt
            truth += v * dt
            corrected = predicted + alpha * (truth - predicted)
            if fb is not None:
                fb(torch.tensor([[0.0, 0.0, (corrected - predicted) / dt, 0.0, 0.0, 0.0]], dtype=torch.float64))
        return truth - corrected

    no_fb = lag(None)
    assert no_fb == pytest.approx((1 - alpha) * v * dt / alpha, rel=1e-9)
    unbounded = dict(axes=["vz"], max_v=math.inf)
    assert lag(CorrectionFeedback(gain=0.1, leak=0.9, **unbounded)) == pytest.approx(no_fb / 2, rel=1e-6)
    assert lag(CorrectionFeedback(gain=0.3, leak=0.9, **unbounded)) == pytest.approx(no_fb / 4, rel=1e-6)
    # Bounded at 0.1 m/s, the feedback stops there: the lag is that of a prediction missing v - 0.1.
    assert lag(CorrectionFeedback(gain=0.3, leak=0.9, axes=["vz"], max_v=0.1)) == pytest.approx(
        (1 - alpha) * (v - 0.1) * dt / alpha, rel=1e-6)


def test_feedback_limits_bound_each_axis():
    fb = CorrectionFeedback(gain=1.0, leak=0.5, axes=["vx", "vz", "wx", "wz"], max_v=0.2, max_w=1.5)
    b = fb(torch.tensor([[5.0, 5.0, -5.0, -5.0, 5.0, 1.0]], dtype=torch.float64))
    assert b[0].tolist() == [0.2, 0.0, -0.2, -1.5, 0.0, 1.0]


def test_feedback_reset_and_bad_arguments():
    fb = CorrectionFeedback(batch_size=3)
    fb(torch.ones(3, 6, dtype=torch.float64))
    fb.reset(torch.tensor([1]))
    assert fb.b[1].abs().sum() == 0 and fb.b[0].abs().sum() > 0 and fb.b[2].abs().sum() > 0
    fb.reset()
    assert fb.b.abs().sum() == 0
    with pytest.raises(ValueError, match="leak"):
        CorrectionFeedback(leak=1.0)
    with pytest.raises(ValueError, match="limits"):
        CorrectionFeedback(max_w=0.0)
    with pytest.raises(ValueError, match="axes"):
        CorrectionFeedback(axes=["vq"])
    with pytest.raises(ValueError, match="axes"):
        CorrectionFeedback(axes="vz")
    with pytest.raises(ValueError, match="shape"):
        fb(torch.ones(2, 6, dtype=torch.float64))
