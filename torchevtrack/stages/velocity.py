"""Stage 3: 6D object velocity from sparse optical flow with a robust, batched linear Kalman filter.

State ``x = [v, w]`` (m/s, rad/s): the object twist in the camera frame, every object point moving as
``dP/dt = v + w x P`` (the model of :func:`torchevtrack.camera.interaction_matrix`). ``B`` independent
filters run side by side; the state is float64.

* Motion model: ``x+ = D x + n``, ``n ~ N(0, Q)``, ``Q = diag(q_v^2 I3, q_w^2 I3)`` (``q_v`` m/s and
  ``q_w`` rad/s standard deviations per update), ``D = diag(rho)`` but for the pitch and yaw rates, whose decay
  rises toward ``rho_turn`` as the rotation rate keeps its direction (:func:`turn_decay`): a hand-held turn is
  sustained, and the flow of a small object reads its pitch and yaw at a fraction of the rate, so a prior that
  loses a quarter per update never reaches it; a motion that keeps reversing decays at ``rho``.
* Measurement: flow vector ``F`` (px/s) at pixel ``uv`` with depth ``Z`` (m, rendered at the current pose).
  As in the paper (Eq. 5) it is expressed as a displacement over the update interval ``dT``:
  ``z = F dT = H x + e`` with ``H = L(uv, Z) dT`` (px per update) and ``e ~ N(0, s_i^2 I2)``,
  ``s_i = sqrt(r_px^2 + (r_rel |F| dT)^2)``: a floor ``r_px`` in pixels of displacement per update plus a
  part proportional to the vector's own displacement (the triplet flow's error grows with the speed it
  reads). At 500 Hz (``dT = 2 ms``) ``r_px = 1`` means a flow noise of 500 px/s; ROFT's 1 px at 30 Hz is
  about 30 px/s, i.e. ``r_px ~ 0.06`` at 500 Hz.
* Robust re-weighting (IRLS, ``iters`` rounds after a plain KF update): with ``r_i`` the norm of the
  vector's residual against the current posterior in units of its ``s_i``, ``m`` the median of ``r_i``
  over the valid vectors of that filter and the robust scale ``s = max(1.4826 m, 1)``, each vector's
  information is scaled by a Laplacian-kernel weight ``w_i = exp(-max(r_i - m, 0) / (k s))``, i.e. its
  covariance becomes ``s_i^2 I / w_i``. Vectors fitting at least as well as the median keep ``w_i = 1``;
  gross outliers get ``w_i ~ 0``; residuals within the nominal noise are barely touched. (A Huber weight
  ``min(1, c / r_i)`` needs about 10 rounds to shed 30 % gross outliers; this kernel needs 3.) The first round
  weighs against the prior ``x`` instead when the prior's median residual is the lower one: a few vectors of
  near-zero flow in a wrong direction (a corner in a block) have the smallest ``s_i`` and can drag the plain update
  so far that the median vector no longer fits it, and the re-weighting would then keep the dragged twist.
* The update is solved in information form, ``6 x 6`` per filter, whatever the number of vectors.

:class:`CorrectionFeedback` (optional, used by the tracker with ``velocity.feedback_gain > 0``) adds a
leaky integral of the template corrections' rate to the filtered twist on the axes the flow hardly
observes (depth rate, pitch, yaw).

Example:
    >>> import torch
    >>> from torchevtrack.camera import Camera
    >>> from torchevtrack.stages.velocity import VelocityKF
    >>> cam = Camera.default()
    >>> kf = VelocityKF(cam, r_px=0.1, batch_size=1)
    >>> gen = torch.Generator().manual_seed(0)
    >>> size = torch.tensor([640.0, 480.0], dtype=torch.float64)
    >>> uv = torch.rand(1, 50, 2, dtype=torch.float64, generator=gen) * size
    >>> depth = 0.4 + 0.2 * torch.rand(1, 50, dtype=torch.float64, generator=gen)
    >>> twist = torch.tensor([0.1, 0.0, 0.0, 0.0, 0.0, 1.0], dtype=torch.float64)
    >>> flow = (cam.interaction_matrix(uv, depth) @ twist[:, None])[..., 0]  # px/s
    >>> for _ in range(5):
    ...     _ = kf.predict()
    ...     _ = kf.update(uv, flow, depth, torch.ones(1, 50, dtype=torch.bool), dt=0.002)
    >>> torch.allclose(kf.x[0], twist, atol=1e-2)
    True
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np
import torch
from torch import nn

from torchevtrack.camera import Camera
from torchevtrack.config import TWIST_AXES, VelocityConfig
from torchevtrack.kernels import kernel
from torchevtrack.linalg import cholesky, cholesky_inverse, cholesky_solve
from torchevtrack.stages import batch_mask

__all__ = [
    "TWIST_AXES",
    "CorrectionFeedback",
    "FeedbackArrays",
    "KFArrays",
    "VelocityUpdate",
    "VelocityKF",
    "feedback_step",
    "shift_twist",
    "shift_twist_kernel",
    "feedback_update",
    "kf_predict",
    "kf_update",
    "sample_depth",
    "velocity_step",
]


_MAD = 1.4826  # median absolute deviation -> standard deviation for Gaussian noise


class VelocityUpdate(NamedTuple):
    """Result of :func:`kf_update`.

    Attributes:
        x: ``(B, 6)`` posterior twist.
        P: ``(B, 6, 6)`` posterior covariance.
        weights: ``(B, G)`` robust weights in ``[0, 1]`` of the last round (0 for invalid vectors).
        residual: ``(B, G)`` residual norm against the posterior, px of displacement per update.
        used: ``(B,)`` bool, whether the filter had enough valid vectors to be updated.
    """

    x: torch.Tensor
    P: torch.Tensor
    weights: torch.Tensor
    residual: torch.Tensor
    used: torch.Tensor


def kf_predict(
    x: torch.Tensor, P: torch.Tensor, rho: float | torch.Tensor, Q: torch.Tensor
) -> tuple[torch.Tensor, torch.Tensor]:
    """Prediction ``x+ = D x``, ``P+ = D P D + Q`` with ``D = diag(rho)``: one decay for every axis (a float) or
    one per element and axis (``(B, 6)``, :func:`turn_decay`).

    Shape: ``(B, 6), (B, 6, 6), float or (B, 6), (6, 6) or (B, 6, 6) -> (B, 6), (B, 6, 6)``.
    """
    if x.shape[-1:] != (6,) or P.shape != x.shape + (6,):
        raise ValueError(f"expected x (B, 6) and P (B, 6, 6), got {tuple(x.shape)} and {tuple(P.shape)}")
    if isinstance(rho, torch.Tensor):
        if rho.shape != x.shape:
            raise ValueError(f"expected a decay rho of shape {tuple(x.shape)}, got {tuple(rho.shape)}")
        d = rho.to(x)
        return d * x, d[:, :, None] * P * d[:, None, :] + Q.to(P)
    return rho * x, rho * rho * P + Q.to(P)


def turn_persistence(turn: torch.Tensor) -> torch.Tensor:
    """How steadily each filter's rotation rate keeps its direction: ``|m| / s`` in ``[0, 1]`` from the running
    means ``turn = [m, s]`` of :func:`turn_update` (``m`` the mean rate vector, ``s`` the mean of its norm; 0 before
    any rotation). 1 for a turn about a fixed axis, near 0 for a rate that keeps reversing.

    Shape: ``(B, 4) -> (B,)`` float64.
    """
    turn = turn.to(torch.float64)
    m, s = turn[:, :3].norm(dim=1), turn[:, 3]
    return torch.where(s > 0, (m / s.clamp(min=1e-300)).clamp(max=1.0), 0.0)


def turn_update(turn: torch.Tensor, x: torch.Tensor, ema: float) -> torch.Tensor:
    """The running means of :func:`turn_persistence` after a posterior twist ``x`` ``[v, w]``: ``m <- (1 - ema) m
    + ema w``, ``s <- (1 - ema) s + ema |w|`` (``ema`` per update; 0.04 at 500 Hz averages over ~50 ms).

    Shape: ``(B, 4), (B, 6), float -> (B, 4)`` float64 (rad/s).
    """
    out = _f64(turn).copy()
    _turn_kernel(out, _f64(x), float(ema))
    return torch.from_numpy(out)


def turn_decay(turn: torch.Tensor, rho: float, rho_turn: float) -> torch.Tensor:
    """The motion model's decay per axis: ``rho`` on ``v`` and the roll rate ``wz``; on the pitch and yaw rates
    (``wx, wy``, which the flow of a small object reads at a fraction of a turn) ``rho + (rho_turn - rho) p``
    with ``p`` the :func:`turn_persistence` of ``turn``: a steady turn keeps its rate from update to update, a
    motion that keeps reversing decays as before.

    Shape: ``(B, 4), float, float -> (B, 6)`` float64.
    """
    p = turn_persistence(turn)
    d = torch.full((turn.shape[0], 6), float(rho), dtype=torch.float64)
    d[:, 3:5] = (rho + (rho_turn - rho) * p)[:, None]
    return d


def shift_twist(twist: torch.Tensor, point: torch.Tensor) -> torch.Tensor:
    """The twist ``[v, w]`` (``dP/dt = v + w x P``) as the velocity of ``point`` and ``w``: ``[v + w x point, w]``.

    With ``point = c`` this is the state of :func:`kf_update` with ``centre=c`` (the twist about the centre,
    ``[c_dot, w]``); ``shift_twist(x, -c)`` maps that state back to ``[v, w]``. Float64, one compiled pass.

    Shape: ``(B, 6), (B, 3) -> (B, 6)`` (m/s, rad/s; point in metres).
    """
    if twist.ndim != 2 or twist.shape[-1] != 6 or point.shape != (twist.shape[0], 3):
        raise ValueError(f"expected twist (B, 6) and point (B, 3), got {tuple(twist.shape)} and {tuple(point.shape)}")
    out = np.empty((twist.shape[0], 6))
    shift_twist_kernel(_f64(twist), _f64(point), out)
    return torch.from_numpy(out)


@kernel
def shift_twist_kernel(twist, c, out):
    """:func:`shift_twist` of ``twist`` ``(B, 6)`` to the points ``c`` ``(B, 3)`` into ``out`` ``(B, 6)``, all float64
    numpy arrays (``out`` may be ``twist``), unchecked; for compiled callers (:func:`velocity_step`,
    :func:`~torchevtrack.update.output`)."""
    for b in range(out.shape[0]):
        w0, w1, w2 = twist[b, 3], twist[b, 4], twist[b, 5]
        out[b, 0] = twist[b, 0] + (w1 * c[b, 2] - w2 * c[b, 1])
        out[b, 1] = twist[b, 1] + (w2 * c[b, 0] - w0 * c[b, 2])
        out[b, 2] = twist[b, 2] + (w0 * c[b, 1] - w1 * c[b, 0])
        out[b, 3], out[b, 4], out[b, 5] = w0, w1, w2


@kernel(inline="always")
def _residuals(Hs, zs, x, sig, rows, n, out):
    """Into ``out[:n]``: the norm of each of ``n`` vectors' residual ``z - H x`` (``rows`` rows each of ``Hs``,
    ``zs``) in units of its noise standard deviation ``sig``."""
    for i in range(n):
        s = 0.0
        for q in range(rows):
            r = i * rows + q
            e = zs[r]
            for j in range(6):
                e -= Hs[r, j] * x[j]
            s += e * e
        out[i] = np.sqrt(s) / sig[i]


@kernel(inline="always")
def _lower_median(values, n, buf):
    """The lower median of ``values[:n]`` (0 for ``n = 0``), sorted in ``buf``."""
    if n == 0:
        return 0.0
    buf[:n] = values[:n]
    return np.sort(buf[:n])[(n - 1) // 2]


@kernel
def _kf_update_kernel(x, P, uv, flow, depth, valid, dt, centre, has_centre, fx, fy, cx, cy, r_px, r_rel, iters, k,
                      min_vectors, normal, x_out, P_out, w_out, res_out, used_out):
    """:func:`kf_update`, one filter at a time (float64 throughout). Returns -1, or the index of a filter whose
    prior or posterior covariance is not positive definite."""
    B, G = valid.shape
    rows = 1 if normal else 2
    Hs = np.empty((G * rows, 6))
    zs = np.empty(G * rows)
    ok = np.empty(G, dtype=np.bool_)
    w = np.empty(G)
    res = np.empty(G)
    res_prior = np.empty(G)
    sig = np.empty(G)  # each vector's noise standard deviation, px of displacement per update
    med_buf = np.empty(G)
    L = np.empty((6, 6))
    Y0 = np.empty((6, 6))
    A = np.empty((6, 6))
    rhs = np.empty(6)
    step = np.empty(6)
    xp = np.empty(6)
    for b in range(B):
        n_ok = 0
        for i in range(G):
            f0, f1 = np.float64(flow[b, i, 0]), np.float64(flow[b, i, 1])
            u, v, Z = np.float64(uv[b, i, 0]), np.float64(uv[b, i, 1]), np.float64(depth[b, i])
            good = valid[b, i] and np.isfinite(Z) and Z > 0.0 and np.isfinite(f0) and np.isfinite(f1) \
                and np.isfinite(u) and np.isfinite(v)
            if good and normal:
                good = np.sqrt(f0 * f0 + f1 * f1) > 0.0
            ok[i] = good
            if good:
                n_ok += 1
        used = n_ok >= min_vectors
        used_out[b] = used
        if not used:
            for j in range(6):
                x_out[b, j] = x[b, j]
                for m in range(6):
                    P_out[b, j, m] = P[b, j, m]
            for i in range(G):
                w_out[b, i] = 0.0
                res_out[b, i] = 0.0
            continue
        # Measurement rows: z = H x + e, H = L(uv, Z) dT (A(c) on the right about the centre).
        T = dt[b]
        M = 0
        for i in range(G):
            if not ok[i]:
                continue
            f0, f1 = np.float64(flow[b, i, 0]), np.float64(flow[b, i, 1])
            d = r_rel * np.sqrt(f0 * f0 + f1 * f1) * T
            sig[M // rows] = np.sqrt(r_px * r_px + d * d)
            uu, vv = np.float64(uv[b, i, 0]) - cx, np.float64(uv[b, i, 1]) - cy
            iz = 1.0 / np.float64(depth[b, i])
            h0 = (fx * iz * T, 0.0, -uu * iz * T, -uu * vv / fy * T, (fx + uu * uu / fx) * T, -vv * fx / fy * T)
            h1 = (0.0, fy * iz * T, -vv * iz * T, -(fy + vv * vv / fy) * T, uu * vv / fx * T, uu * fy / fx * T)
            if normal:
                s = np.sqrt(f0 * f0 + f1 * f1)
                n0, n1 = f0 / s, f1 / s
                for j in range(6):
                    Hs[M, j] = n0 * h0[j] + n1 * h1[j]
                zs[M] = s * T
                M += 1
            else:
                for j in range(6):
                    Hs[M, j] = h0[j]
                    Hs[M + 1, j] = h1[j]
                zs[M] = f0 * T
                zs[M + 1] = f1 * T
                M += 2
        if has_centre:  # H A(c): the angular columns gain H[:, :3] [c]x
            c0, c1, c2 = centre[b, 0], centre[b, 1], centre[b, 2]
            for r in range(M):
                a0, a1, a2 = Hs[r, 0], Hs[r, 1], Hs[r, 2]
                Hs[r, 3] = (a1 * c2 - a2 * c1) + Hs[r, 3]
                Hs[r, 4] = (a2 * c0 - a0 * c2) + Hs[r, 4]
                Hs[r, 5] = (a0 * c1 - a1 * c0) + Hs[r, 5]
        if not cholesky(P[b], L):
            return b
        cholesky_inverse(L, Y0)
        n_ok_rows = M // rows
        for i in range(n_ok_rows):
            w[i] = 1.0
        med_prior = 0.0
        if iters > 0:  # the prior's residuals, the first round's reference when they fit the median vector better
            _residuals(Hs, zs, x[b], sig, rows, n_ok_rows, res_prior)
            med_prior = _lower_median(res_prior, n_ok_rows, med_buf)
        for it in range(iters + 1):
            if it > 0:  # Laplacian re-weighting against the previous posterior (or the prior)
                med = _lower_median(res, n_ok_rows, med_buf)
                if it == 1 and med_prior < med:
                    med = med_prior
                    res[:n_ok_rows] = res_prior[:n_ok_rows]
                scale = k * max(_MAD * med, 1.0)
                for i in range(n_ok_rows):
                    w[i] = np.exp(-max(res[i] - med, 0.0) / scale)
            # Information form: A = Y0 + H^T W H, rhs = H^T W (z - H x0)
            for j in range(6):
                rhs[j] = 0.0
                for m in range(6):
                    A[j, m] = 0.0
            for r in range(M):
                wi = w[r // rows] / (sig[r // rows] * sig[r // rows])
                e = zs[r]
                for j in range(6):
                    e -= Hs[r, j] * x[b, j]
                for j in range(6):
                    hw = Hs[r, j] * wi
                    rhs[j] += hw * e
                    for m in range(j + 1):
                        A[j, m] += hw * Hs[r, m]
            for j in range(6):
                for m in range(j + 1):
                    A[j, m] += Y0[j, m]
                    A[m, j] = A[j, m]
            if not cholesky(A, L):
                return b
            cholesky_solve(L, rhs, step)
            for j in range(6):
                xp[j] = x[b, j] + step[j]
            _residuals(Hs, zs, xp, sig, rows, n_ok_rows, res)
        cholesky_inverse(L, P_out[b])
        for j in range(6):
            x_out[b, j] = xp[j]
        i_ok = 0
        for i in range(G):
            if ok[i]:
                w_out[b, i] = w[i_ok]
                res_out[b, i] = res[i_ok] * sig[i_ok]
                i_ok += 1
            else:
                w_out[b, i] = 0.0
                res_out[b, i] = 0.0
    return -1


def _f32_or_f64(t: torch.Tensor) -> np.ndarray:
    """A numpy view of a CPU tensor (float32 and float64 kept, anything else as float64)."""
    if t.dtype not in (torch.float32, torch.float64) or t.requires_grad:
        t = t.detach().double()
    return t.numpy()


def _f64(t: torch.Tensor) -> np.ndarray:
    """A float64 numpy view (or copy) of a CPU tensor."""
    return t.numpy() if t.dtype == torch.float64 and not t.requires_grad else t.detach().double().numpy()


def kf_update(
    x: torch.Tensor,
    P: torch.Tensor,
    uv: torch.Tensor,
    flow: torch.Tensor,
    depth: torch.Tensor,
    valid: torch.Tensor,
    camera: Camera,
    dt: torch.Tensor | float,
    r_px: float = 1.0,
    r_rel: float = 0.0,
    iters: int = 3,
    k: float = 1.0,
    min_vectors: int = 3,
    normal: bool = False,
    centre: torch.Tensor | None = None,
) -> VelocityUpdate:
    """Robust Kalman update of the twist with padded flow vectors.

    Args:
        x, P: prior twist ``(B, 6)`` (m/s, rad/s) and covariance ``(B, 6, 6)``.
        uv: ``(B, G, 2)`` pixel coordinates of the flow vectors.
        flow: ``(B, G, 2)`` optical flow, px/s.
        depth: ``(B, G)`` depth (m) at ``uv``; ``<= 0`` or non-finite marks background (ignored).
        valid: ``(B, G)`` bool mask of real (non-padding) vectors.
        camera: intrinsics of the pixel coordinates.
        dt: update interval ``dT`` (s), a float or ``(B,)``; scales flow and Jacobian to px per update.
        r_px: flow noise standard deviation, px of displacement per update (``R = r_px^2 I2`` with ``r_rel = 0``).
        r_rel: the part of the noise proportional to the vector's displacement ``|F| dT``: vector ``i`` has
            ``R_i = (r_px^2 + (r_rel |F_i| dT)^2) I2``.
        iters: robust re-weighting rounds after the plain update (0 = plain linear KF update).
        k: width of the Laplacian weight in robust standard deviations ``max(1.4826 x median, 1)`` of the
            residuals in units of each vector's noise.
        min_vectors: filters with fewer valid vectors keep their prior.
        normal: the vectors are normal flows (the flow component along the edge normal, as the
            ``estimate="normal"`` flow stage gives): each vector then measures only ``n . (L x)`` with
            ``n = F / |F|``, one scalar of noise ``s_i`` (the aperture problem leaves the tangential
            component unobserved, so it must not be read as zero).
        centre: ``(B, 3)`` object centre (m, camera frame). If given, the state is the twist about the
            centre, ``[c_dot, w]`` with ``c_dot = v + w x c`` the centre's velocity, and the Jacobian
            becomes ``L A(c)``, ``A = [[I, [c]x], [0, I]]``. For a small object far from the camera,
            ``v`` and ``w`` of the camera-origin twist are nearly collinear in the flow (a lever arm of
            ``|c|``), and the motion-model shrinkage ``rho x`` then pulls ``v`` toward ``-w x c``; about
            the centre the two are nearly independent. Convert back with ``v = c_dot - w x c``.

    Returns:
        :class:`VelocityUpdate`.

    The filters are updated one at a time in a compiled kernel (float64; the ``6 x 6`` information
    matrix, its Cholesky factor and the re-weighting rounds of one filter never leave it).

    Shape: ``(B, 6), (B, 6, 6), (B, G, 2), (B, G, 2), (B, G), (B, G) -> VelocityUpdate``.
    """
    if x.ndim != 2 or x.shape[-1] != 6 or P.shape != x.shape + (6,):
        raise ValueError(f"expected x (B, 6) and P (B, 6, 6), got {tuple(x.shape)} and {tuple(P.shape)}")
    B = x.shape[0]
    if uv.ndim != 3 or uv.shape[0] != B or uv.shape[-1] != 2:
        raise ValueError(f"uv must have shape (B={B}, G, 2), got {tuple(uv.shape)}")
    G = uv.shape[1]
    if flow.shape != uv.shape:
        raise ValueError(f"flow must have shape {tuple(uv.shape)} like uv, got {tuple(flow.shape)}")
    if depth.shape != (B, G) or valid.shape != (B, G):
        raise ValueError(
            f"depth and valid must have shape ({B}, {G}), got {tuple(depth.shape)} and {tuple(valid.shape)}"
        )
    if valid.dtype != torch.bool:
        raise TypeError(f"valid must be a bool tensor, got {valid.dtype}")
    if r_px <= 0 or r_rel < 0 or iters < 0 or k <= 0:
        raise ValueError(f"need r_px > 0, r_rel >= 0, iters >= 0, k > 0; got r_px={r_px}, r_rel={r_rel}, "
                         f"iters={iters}, k={k}")
    if isinstance(dt, torch.Tensor):
        dt = dt.to(torch.float64).expand(B)
        if not bool((dt > 0).all()):
            raise ValueError(f"dt must be positive seconds, got {dt.tolist()}")
        dt_np = dt.contiguous().numpy()
    else:
        if not dt > 0:
            raise ValueError(f"dt must be positive seconds, got {dt}")
        dt_np = np.full(B, dt, dtype=np.float64)
    if centre is not None and centre.shape != (B, 3):
        raise ValueError(f"centre must have shape ({B}, 3), got {tuple(centre.shape)}")
    x_out, P_out = np.empty((B, 6)), np.empty((B, 6, 6))
    w_out, res_out, used = np.empty((B, G)), np.empty((B, G)), np.empty(B, dtype=np.bool_)
    bad = _kf_update_kernel(_f64(x), _f64(P), _f32_or_f64(uv), _f32_or_f64(flow), _f32_or_f64(depth),
                            valid.numpy(), dt_np, _NO_CENTRE if centre is None else _f64(centre), centre is not None,
                            float(camera.fx), float(camera.fy), float(camera.cx), float(camera.cy), float(r_px),
                            float(r_rel), int(iters), float(k), int(min_vectors), bool(normal), x_out, P_out, w_out,
                            res_out, used)
    if bad >= 0:
        raise torch.linalg.LinAlgError(f"kf_update: the covariance of filter {bad} is not positive-definite")
    out = VelocityUpdate(*(torch.from_numpy(a) for a in (x_out, P_out, w_out, res_out, used)))
    if x.dtype != torch.float64:
        out = out._replace(**{f: getattr(out, f).to(x.dtype) for f in ("x", "P", "weights", "residual")})
    return out


_NO_CENTRE = np.zeros((1, 3))


def sample_depth(depth: torch.Tensor, origin: torch.Tensor, uv: torch.Tensor, valid: torch.Tensor,
                 radius: int) -> torch.Tensor:
    """Mean object depth around flow pixels, for :func:`kf_update`.

    For each ``valid`` vector, the mean of the positive depths at the pixels ``round(uv) + (du, dv)``,
    ``du, dv`` in ``-radius, -radius + 2, ..., radius`` (a sparse neighbourhood: flow lies on edges, where
    the pixel itself may fall just off the silhouette), read from ``depth`` whose top-left pixel is
    ``origin`` (pixels outside it count as background); 0 where there is no object pixel around, and for
    the vectors that are not valid (the filter ignores them). Sums in float64.

    Shape: ``depth (B, h, w)``, ``origin (B, 2)`` integer ``(u0, v0)``, ``uv (B, G, 2)``, ``valid (B, G)`` bool
    -> ``(B, G)`` float64 metres.
    """
    if depth.ndim != 3 or origin.shape != (depth.shape[0], 2) or uv.ndim != 3 or uv.shape[-1] != 2 \
            or valid.shape != uv.shape[:2] or uv.shape[0] != depth.shape[0] or valid.dtype != torch.bool:
        raise ValueError("expected depth (B, h, w), origin (B, 2), uv (B, G, 2) and a bool valid (B, G), got "
                         f"{tuple(depth.shape)}, {tuple(origin.shape)}, {tuple(uv.shape)}, {valid.dtype} "
                         f"{tuple(valid.shape)}")
    out = np.empty(valid.shape)
    _sample_depth_kernel(_f32_or_f64(depth), origin.long().numpy(), _f32_or_f64(uv), valid.numpy(), int(radius), out)
    return torch.from_numpy(out)


@kernel
def _sample_depth_kernel(depth, origin, uv, valid, r, out):
    B, h, w = depth.shape
    for b in range(B):
        for g in range(valid.shape[1]):
            out[b, g] = 0.0
            if not valid[b, g]:
                continue
            u0 = np.int64(np.rint(uv[b, g, 0])) - origin[b, 0]
            v0 = np.int64(np.rint(uv[b, g, 1])) - origin[b, 1]
            s, n = 0.0, 0
            for dv in range(-r, r + 1, 2):
                v = v0 + dv
                if v < 0 or v >= h:
                    continue
                for du in range(-r, r + 1, 2):
                    u = u0 + du
                    if u < 0 or u >= w:
                        continue
                    z = np.float64(depth[b, v, u])
                    if z > 0.0:
                        s += z
                        n += 1
            if n > 0:
                out[b, g] = s / n


@kernel(inline="always")
def _persistence(turn, b):
    """:func:`turn_persistence` of element ``b`` (the compiled kernels' copy)."""
    s = turn[b, 3]
    if not s > 0.0:
        return 0.0
    m = np.sqrt(turn[b, 0] ** 2 + turn[b, 1] ** 2 + turn[b, 2] ** 2)
    return min(m / s, 1.0)


@kernel
def _kf_predict_kernel(x, P, rho, rho_turn, turn, Q):
    """:func:`kf_predict` with :func:`turn_decay`'s decays, in place (``Q`` ``(6, 6)``)."""
    d = np.empty(6)
    for b in range(x.shape[0]):
        p = _persistence(turn, b)
        for i in range(6):
            d[i] = rho
        d[3] = d[4] = rho + (rho_turn - rho) * p
        for i in range(6):
            x[b, i] = d[i] * x[b, i]
            for j in range(6):
                P[b, i, j] = d[i] * P[b, i, j] * d[j] + Q[i, j]


@kernel
def _turn_kernel(turn, x, ema):
    """:func:`turn_update` in place on ``turn``."""
    for b in range(x.shape[0]):
        w0, w1, w2 = x[b, 3], x[b, 4], x[b, 5]
        turn[b, 0] += ema * (w0 - turn[b, 0])
        turn[b, 1] += ema * (w1 - turn[b, 1])
        turn[b, 2] += ema * (w2 - turn[b, 2])
        turn[b, 3] += ema * (np.sqrt(w0 * w0 + w1 * w1 + w2 * w2) - turn[b, 3])


class KFArrays(NamedTuple):
    """A :class:`VelocityKF` as compiled kernels take it (:meth:`VelocityKF.arrays`): its state ``x`` ``(B, 6)`` and
    ``P`` ``(B, 6, 6)`` (views of its buffers, written in place), motion model ``rho``, ``rho_turn``, the running
    means ``turn`` ``(B, 4)`` (:func:`turn_decay`; a view, written in place), ``turn_ema`` and ``Q`` ``(6, 6)``, the
    camera ``fx, fy, cx, cy`` (px) and the update's options (:func:`kf_update`)."""

    x: np.ndarray
    P: np.ndarray
    rho: float
    rho_turn: float
    turn: np.ndarray
    turn_ema: float
    Q: np.ndarray
    fx: float
    fy: float
    cx: float
    cy: float
    r_px: float
    r_rel: float
    iters: int
    k: float
    min_vectors: int
    normal: bool


@kernel
def velocity_step(f, field, depth, origin, max_speed, radius, dt, centre, feedback, twist, n_vectors):
    """The velocity stage of one update on the filters' :class:`KFArrays` ``f`` in place, unchecked:
    :meth:`VelocityKF.predict`; the valid vectors of the flow ``field`` (a :class:`~torchevtrack.stages.flow.FlowField`
    of numpy arrays) slower than ``max_speed`` (px/s); their depth from the render ``depth`` ``(B, h, w)`` at
    ``origin`` ``(B, 2)`` (:func:`sample_depth` with ``radius``); :meth:`VelocityKF.update` over ``dt`` ``(B,)`` s about
    the object centres ``centre`` ``(B, 3)``; plus the feedback twist ``(B, 6)`` (or ``None``); the sum back about the
    camera (:func:`shift_twist`) into ``twist`` ``(B, 6)`` ``[v, w]`` and the vectors weighed into ``n_vectors``
    ``(B,)``. Returns -1, or the index of a filter whose covariance is not positive definite."""
    valid, flow = field.valid, field.flow
    B, G = valid.shape
    _kf_predict_kernel(f.x, f.P, f.rho, f.rho_turn, f.turn, f.Q)
    limit = np.float32(max_speed)
    slow = np.empty((B, G), dtype=np.bool_)
    for b in range(B):
        for g in range(G):
            f0, f1 = flow[b, g, 0], flow[b, g, 1]
            slow[b, g] = valid[b, g] and np.sqrt(f0 * f0 + f1 * f1) < limit
    z = np.empty((B, G))
    _sample_depth_kernel(depth, origin, field.uv, slow, radius, z)
    w, res, used = np.empty((B, G)), np.empty((B, G)), np.empty(B, dtype=np.bool_)
    bad = _kf_update_kernel(f.x, f.P, field.uv, flow, z, slow, dt, centre, True, f.fx, f.fy, f.cx, f.cy, f.r_px,
                            f.r_rel, f.iters, f.k, f.min_vectors, f.normal, f.x, f.P, w, res,
                            used)  # in place: each read first
    if bad >= 0:
        return bad
    _turn_kernel(f.turn, f.x, f.turn_ema)
    twist_c = f.x.copy()
    if feedback is not None:
        twist_c += feedback
    shift_twist_kernel(twist_c, -centre, twist)  # [c_dot, w] about the centre -> [v, w]
    for b in range(B):
        n_vectors[b] = np.count_nonzero(w[b] > 0)
    return -1


class VelocityKF(nn.Module):
    """Batched velocity Kalman filter (state in buffers ``x`` ``(B, 6)`` and ``P`` ``(B, 6, 6)``, float64).

    Args:
        camera: intrinsics of the flow pixel coordinates.
        rho: velocity decay of the motion model per update (paper: 0.5; default 0.75).
        rho_turn: the pitch and yaw rates' decay in a steady turn (:func:`turn_decay`; ``rho_turn = rho``: one
            decay for all axes, the paper's model).
        turn_ema: weight of each update in the running means of the rotation rate (:func:`turn_update`).
        q_v, q_w: process noise standard deviations per update (m/s, rad/s). With ``rho = 0.5`` the
            prior mean halves at every step (``rho = 0.75``: a quarter is lost), so these must be of the order
            of the velocities themselves for the filter to follow the flow rather than decay to zero.
        r_px: flow noise standard deviation, px of displacement per update.
        r_rel: noise part proportional to each vector's displacement (see :func:`kf_update`).
        p0_v, p0_w: initial standard deviations (m/s, rad/s) after :meth:`reset`.
        min_vectors: filters with fewer valid vectors only predict.
        iters, k: robust re-weighting rounds and Laplacian width (see :func:`kf_update`).
        normal: the flow vectors are normal flows (see :func:`kf_update`).
        batch_size: number ``B`` of independent filters.
    """

    def __init__(
        self,
        camera: Camera,
        rho: float = VelocityConfig.rho,
        rho_turn: float = VelocityConfig.rho_turn,
        turn_ema: float = VelocityConfig.turn_ema,
        q_v: float = VelocityConfig.q_v,
        q_w: float = VelocityConfig.q_w,
        r_px: float = VelocityConfig.r_px,
        r_rel: float = VelocityConfig.r_rel,
        p0_v: float = 1.0,
        p0_w: float = 5.0,
        min_vectors: int = VelocityConfig.min_vectors,
        iters: int = 3,
        k: float = VelocityConfig.robust_k,
        normal: bool = False,
        batch_size: int = 1,
    ) -> None:
        super().__init__()
        if not isinstance(camera, Camera):
            raise TypeError(f"camera must be a Camera, got {type(camera).__name__}")
        if not 0.0 <= rho <= 1.0:
            raise ValueError(f"rho must be in [0, 1], got {rho}")
        if not 0.0 <= rho_turn <= 1.0:
            raise ValueError(f"rho_turn must be in [0, 1], got {rho_turn}")
        if not 0.0 < turn_ema <= 1.0:
            raise ValueError(f"turn_ema must be in (0, 1], got {turn_ema}")
        if min(q_v, q_w, r_px, p0_v, p0_w) <= 0:
            raise ValueError("q_v, q_w, r_px, p0_v and p0_w must be positive standard deviations")
        if not r_rel >= 0:
            raise ValueError(f"r_rel must be >= 0, got {r_rel}")
        if not k > 0:
            raise ValueError(f"k must be positive, got {k}")
        if batch_size < 1:
            raise ValueError(f"batch_size must be >= 1, got {batch_size}")
        self.camera = camera
        self.rho, self.r_px, self.r_rel, self.k = float(rho), float(r_px), float(r_rel), float(k)
        self.rho_turn, self.turn_ema = float(rho_turn), float(turn_ema)
        self.min_vectors, self.iters, self.normal = int(min_vectors), int(iters), bool(normal)
        f64 = torch.float64
        self.register_buffer("Q", torch.diag(torch.tensor([q_v**2] * 3 + [q_w**2] * 3, dtype=f64)))
        self.register_buffer("P0", torch.diag(torch.tensor([p0_v**2] * 3 + [p0_w**2] * 3, dtype=f64)))
        self.register_buffer("x", torch.zeros(batch_size, 6, dtype=f64))
        self.register_buffer("P", self.P0.expand(batch_size, 6, 6).clone())
        self.register_buffer("turn", torch.zeros(batch_size, 4, dtype=f64))  # turn_update's running means

    @classmethod
    def from_config(cls, camera: Camera, cfg: VelocityConfig, normal: bool = True,
                    batch_size: int = 1) -> "VelocityKF":
        """The filter of the config section ``velocity`` for ``B`` streams; ``normal``: the flow gives normal flow
        (``flow.estimate == "normal"``)."""
        return cls(camera, rho=cfg.rho, rho_turn=cfg.rho_turn, turn_ema=cfg.turn_ema, q_v=cfg.q_v, q_w=cfg.q_w,
                   r_px=cfg.r_px, r_rel=cfg.r_rel, min_vectors=cfg.min_vectors, k=cfg.robust_k, normal=normal,
                   batch_size=batch_size)

    @property
    def batch_size(self) -> int:
        return self.x.shape[0]

    def reset(self, twist: torch.Tensor | None = None, mask: torch.Tensor | None = None) -> None:
        """Restart every filter, or those selected by ``mask`` (``(B,)`` bool or ``(K,)`` indices), at
        ``twist`` ``(B, 6)`` (default zero; rows of unselected elements are ignored) with covariance ``P0``."""
        if twist is not None and tuple(twist.shape) != (self.batch_size, 6):
            raise ValueError(f"twist must have shape ({self.batch_size}, 6), got {tuple(twist.shape)}")
        m = batch_mask(mask, self.batch_size)
        self.x.copy_(torch.where(m[:, None], 0.0 if twist is None else twist.to(self.x), self.x))
        self.P.copy_(torch.where(m[:, None, None], self.P0, self.P))
        self.turn.masked_fill_(m[:, None], 0.0)

    def take(self, other: "VelocityKF", mask: torch.Tensor | None = None) -> None:
        """Take the state (``x``, ``P``, the turn's running means) of the elements of ``mask`` (default all) from
        ``other``, a filter of the same batch size (:meth:`~torchevtrack.tracker.EventPoseTracker.adopt`)."""
        if other.batch_size != self.batch_size:
            raise ValueError(f"other has batch size {other.batch_size}, not {self.batch_size}")
        m = batch_mask(mask, self.batch_size)
        for name in ("x", "P", "turn"):
            getattr(self, name)[m] = getattr(other, name)[m]

    def arrays(self) -> KFArrays:
        """The filters for compiled kernels (:func:`velocity_step`): numpy views of the buffers."""
        c = self.camera
        return KFArrays(self.x.numpy(), self.P.numpy(), self.rho, self.rho_turn, self.turn.numpy(), self.turn_ema,
                        self.Q.numpy(), c.fx, c.fy, c.cx, c.cy, self.r_px, self.r_rel, self.iters, self.k,
                        self.min_vectors, self.normal)

    def predict(self) -> torch.Tensor:
        """Apply the motion model (:func:`kf_predict` with :func:`turn_decay`'s decays) in place; returns the
        predicted twist ``(B, 6)``."""
        x, P, Q, turn = self.x, self.P, self.Q, self.turn
        if Q.shape == (6, 6) and x.dtype == P.dtype == Q.dtype == turn.dtype == torch.float64:
            _kf_predict_kernel(x.numpy(), P.numpy(), self.rho, self.rho_turn, turn.numpy(), Q.numpy())
        else:
            x_new, P_new = kf_predict(x, P, turn_decay(turn, self.rho, self.rho_turn), Q)
            x.copy_(x_new)
            P.copy_(P_new)
        return x

    def update(
        self,
        uv: torch.Tensor,
        flow: torch.Tensor,
        depth: torch.Tensor,
        valid: torch.Tensor,
        dt: torch.Tensor | float,
        centre: torch.Tensor | None = None,
    ) -> VelocityUpdate:
        """Fuse padded flow vectors in place (see :func:`kf_update` for shapes, units and ``centre``)."""
        out = kf_update(
            self.x, self.P, uv, flow, depth, valid, self.camera, dt,
            r_px=self.r_px, r_rel=self.r_rel, iters=self.iters, k=self.k, min_vectors=self.min_vectors,
            normal=self.normal, centre=centre,
        )
        self.x.copy_(out.x)
        self.P.copy_(out.P)
        self.turn.copy_(turn_update(self.turn, self.x, self.turn_ema))
        return out


def feedback_update(b: torch.Tensor, rate: torch.Tensor, gain: float, leak: float, mask: torch.Tensor,
                    limit: torch.Tensor | None = None) -> torch.Tensor:
    """One step of the correction feedback: ``b+ = clip(leak b + gain rate, -limit, limit)`` on the ``mask``
    axes (0 elsewhere).

    ``rate`` is the correction of this update as a twist (the correction divided by the period), so for a
    constant rate ``r`` the feedback settles at ``gain r / (1 - leak)`` (within the limit) with time
    constant ``1 / (1 - leak)`` updates.

    Shape: ``(B, 6), (B, 6), float, float, (6,) bool, (6,) or None -> (B, 6)`` (m/s, rad/s).
    """
    out = np.empty((b.shape[0], 6)) if b.ndim == 2 else None
    _feedback_into(b, rate, None, gain, leak, mask, limit, out)
    return torch.from_numpy(out).to(b.dtype)


def _feedback_into(b, rate, axis, gain, leak, mask, limit, out) -> None:
    """:func:`feedback_update` of ``b`` ``(B, 6)`` into ``out`` (which may be ``b``), with the component of the
    angular rate along ``axis`` ``(B, 3)`` (if given) removed first."""
    if b.ndim != 2 or b.shape[-1] != 6 or rate.shape != b.shape:
        raise ValueError(f"b and rate must have shape (B, 6), got {tuple(b.shape)} and {tuple(rate.shape)}")
    if axis is not None and axis.shape != (b.shape[0], 3):
        raise ValueError(f"symmetry_axis must have shape ({b.shape[0]}, 3), got {tuple(axis.shape)}")
    lim = _NO_LIMIT if limit is None else _f64(limit.expand(6))
    _feedback_kernel(_f64(b), _f64(rate), _NO_AXIS if axis is None else _f64(axis), axis is not None, float(gain),
                     float(leak), mask.detach().expand(6).numpy(), lim, limit is not None,
                     out if isinstance(out, np.ndarray) else out.numpy())


_NO_AXIS = np.zeros((1, 3))
_NO_LIMIT = np.zeros(6)


@kernel
def _feedback_kernel(b, rate, axis, has_axis, gain, leak, mask, limit, has_limit, out):
    for i in range(b.shape[0]):
        r = rate[i].copy()
        if has_axis:  # w - (w . a) a
            s = r[3] * axis[i, 0] + r[4] * axis[i, 1] + r[5] * axis[i, 2]
            r[3], r[4], r[5] = r[3] - s * axis[i, 0], r[4] - s * axis[i, 1], r[5] - s * axis[i, 2]
        for j in range(6):
            v = leak * b[i, j] + gain * r[j]
            if has_limit:
                v = np.minimum(np.maximum(v, -limit[j]), limit[j])
            out[i, j] = v if mask[j] else 0.0


class FeedbackArrays(NamedTuple):
    """A :class:`CorrectionFeedback` as compiled kernels take it (:meth:`CorrectionFeedback.arrays`): its feedback
    ``b`` ``(B, 6)`` (a view of the buffer, written in place), ``gain``, ``leak``, the axes ``mask`` ``(6,)`` bool and
    the ``limit`` ``(6,)``."""

    b: np.ndarray
    gain: float
    leak: float
    mask: np.ndarray
    limit: np.ndarray


@kernel
def feedback_step(f, rate, axis):
    """:meth:`CorrectionFeedback.forward` of the corrections' ``rate`` ``(B, 6)`` about the centres on the feedback's
    :class:`FeedbackArrays` ``f`` in place, unchecked; ``axis`` ``(B, 3)`` symmetry axes or ``None``."""
    if axis is None:
        _feedback_kernel(f.b, rate, np.zeros((1, 3)), False, f.gain, f.leak, f.mask, f.limit, True, f.b)
    else:
        _feedback_kernel(f.b, rate, axis, True, f.gain, f.leak, f.mask, f.limit, True, f.b)


class CorrectionFeedback(nn.Module):
    """Velocity from the template corrections, for the twist components the flow hardly observes.

    The flow of an object seen from a distance barely tells depth rate from nothing, nor pitch and
    yaw about the object centre from a sideways shift; on those axes the predicted pose falls behind
    the object and each template correction pulls it back by a little. A leaky integral of those
    corrections (:func:`feedback_update`), added to the filtered twist, moves the prediction along
    by the motion the corrections keep finding. The leak keeps it from integrating a steady bias
    of the corrections themselves (a pure integrator, ``leak = 1``, drifts away on such a bias), and
    the limits bound its authority (anti-windup): where the corrections cannot see an axis well
    (the tilt of a can), an unbounded feedback integrates their noise into a runaway.

    Args:
        gain: fraction of each correction's rate taken into the feedback.
        leak: per-update retention of the feedback in ``[0, 1)``.
        axes: names from :data:`TWIST_AXES` the feedback acts on.
        max_v, max_w: largest feedback on a velocity (m/s) and an angular-rate (rad/s) axis (``inf``: none).
        batch_size: number ``B`` of independent elements.

    Buffers:
        b: ``(B, 6)`` float64 feedback twist ``[c_dot, w]`` about the object centre (m/s, rad/s).

    Example:
        >>> import torch
        >>> fb = CorrectionFeedback(gain=0.05, leak=0.9, axes=("vz",))
        >>> for _ in range(200):
        ...     _ = fb(torch.tensor([[0.1, 0.0, 0.2, 0.0, 0.0, 0.0]], dtype=torch.float64))
        >>> [round(v, 3) for v in fb.b[0].tolist()]  # gain / (1 - leak) = 0.5 of the rate on vz only
        [0.0, 0.0, 0.1, 0.0, 0.0, 0.0]
    """

    def __init__(self, gain: float = VelocityConfig.feedback_gain, leak: float = VelocityConfig.feedback_leak,
                 axes=("vz", "wx", "wy"), max_v: float = VelocityConfig.feedback_max_v,
                 max_w: float = VelocityConfig.feedback_max_w, batch_size: int = 1) -> None:
        super().__init__()
        if not gain >= 0.0 or not 0.0 <= leak < 1.0 or not max_v > 0 or not max_w > 0:
            raise ValueError(f"need gain >= 0, 0 <= leak < 1 and positive limits, got gain={gain}, leak={leak}, "
                             f"max_v={max_v}, max_w={max_w}")
        unknown = [a for a in axes if a not in TWIST_AXES]
        if unknown or isinstance(axes, str):
            raise ValueError(f"axes must be a list of names from {TWIST_AXES}, got {axes!r}")
        if batch_size < 1:
            raise ValueError(f"batch_size must be >= 1, got {batch_size}")
        self.gain, self.leak, self.axes = float(gain), float(leak), tuple(axes)
        self.register_buffer("mask", torch.tensor([a in axes for a in TWIST_AXES]), persistent=False)
        self.register_buffer("limit", torch.tensor([float(max_v)] * 3 + [float(max_w)] * 3, dtype=torch.float64),
                             persistent=False)
        self.register_buffer("b", torch.zeros(batch_size, 6, dtype=torch.float64))

    @classmethod
    def from_config(cls, cfg: VelocityConfig, batch_size: int = 1) -> "CorrectionFeedback":
        """The feedback of the config section ``velocity`` (its ``feedback_*`` keys) for ``B`` streams."""
        return cls(cfg.feedback_gain, cfg.feedback_leak, cfg.feedback_axes, cfg.feedback_max_v, cfg.feedback_max_w,
                   batch_size=batch_size)

    def forward(self, rate: torch.Tensor, symmetry_axis: torch.Tensor | None = None) -> torch.Tensor:
        """Take the corrections' rate ``(B, 6)`` (twist about the centre) and return the new feedback ``b``.

        ``symmetry_axis`` ``(B, 3)``: unit camera-frame axes through the object centres about which the
        objects look the same (zero rows: none). The corrections cannot observe a turn about such an axis,
        so that component of their rate is noise and is removed before it enters the feedback.
        """
        if rate.shape != self.b.shape:
            raise ValueError(f"rate must have shape {tuple(self.b.shape)}, got {tuple(rate.shape)}")
        _feedback_into(self.b, rate, symmetry_axis, self.gain, self.leak, self.mask, self.limit, self.b)
        return self.b

    def arrays(self) -> FeedbackArrays:
        """The feedback for compiled kernels (:func:`feedback_step`): numpy views of the buffers."""
        return FeedbackArrays(self.b.numpy(), self.gain, self.leak, self.mask.numpy(), self.limit.numpy())

    def reset(self, mask: torch.Tensor | None = None) -> None:
        """Zero the feedback of every element, or of those selected by ``mask`` (``(B,)`` bool or ``(K,)`` indices)."""
        self.b.masked_fill_(batch_mask(mask, self.b.shape[0])[:, None], 0.0)

    def take(self, other: "CorrectionFeedback", mask: torch.Tensor | None = None) -> None:
        """Take the feedback of the elements of ``mask`` (default all) from ``other`` (the same batch size)."""
        if other.b.shape != self.b.shape:
            raise ValueError(f"other has batch size {other.b.shape[0]}, not {self.b.shape[0]}")
        m = batch_mask(mask, self.b.shape[0])
        self.b[m] = other.b[m]

    def extra_repr(self) -> str:
        return f"gain={self.gain}, leak={self.leak}, axes={self.axes}, max_v={float(self.limit[0])}, " \
               f"max_w={float(self.limit[3])}"
