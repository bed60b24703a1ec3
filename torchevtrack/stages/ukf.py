"""Stage 6: pose smoothing with a batched unscented Kalman filter on ``R^9 x SO(3)`` (ROFT style).

State ``x`` ``(B, 13)`` = ``[p_dot (m/s), w (rad/s), p (m), q (w, x, y, z)]``: the object origin ``p`` in the
camera frame, its velocity ``p_dot = dp/dt``, the camera-frame angular velocity ``w`` and the orientation
``q``. Errors live in the 12-D tangent ``[dp_dot, dw, dp, dtheta]`` with ``q = exp(dtheta) (x) q_mean``
(``dtheta`` a rotation vector, :func:`torchevtrack.geometry.quat_exp`); covariance ``P`` ``(B, 12, 12)``.

* Process over ``T`` seconds: ``p+ = p + p_dot T``, ``q+ = exp(w T) (x) q``, ``p_dot`` and ``w`` random
  walks. ``Q = diag(q_pdot I3, q_w I3, q_p I3, q_q I3) T`` with spectral densities ``q_pdot``
  ((m/s)^2/s), ``q_w`` ((rad/s)^2/s), ``q_p`` (m^2/s), ``q_q`` (rad^2/s), so tuning does not depend on
  the update rate.
* Measurement: the corrected pose ``[p, q]``; innovation ``[p_meas - p, log(q_meas (x) q^-1)]`` (rotation
  vector, i.e. ``2 log`` of the quaternion), ``R = diag(r_p I3, r_q I3)`` (m^2, rad^2).
* Scaled sigma points (Merwe) with ``alpha = 1, beta = 2, kappa = 0``; the quaternion mean is the top
  eigenvector of ``sum_i Wm_i q_i q_i^T``.

``p_dot`` is the velocity of the object origin. The velocity filter's twist ``[v, w]``
(``dP/dt = v + w x P``, :mod:`torchevtrack.stages.propagate`) maps to it as ``p_dot = v + w x p``;
:meth:`PoseUKF.reset` and :attr:`PoseUKF.twist` convert.

Noise defaults. ROFT uses ``R_p = 1e-3, R_q = 1e-4, P0 = 1e-3``. Here the measurement is the template
correction, which moves in 1 px / 1 deg steps (sub-step with the Newton rule): about 1 mm laterally and a few mm in
depth at 0.5 m, hence ``r_p = 1e-5`` m^2 (3 mm) and ``r_q = 1e-4`` rad^2 (0.6 deg; 3e-4 for the 1 deg step held
fewer wide-dev runs, docs/notebook.md 2026-11-28). ``p0 = 1e-3``
(3 cm, 1.8 deg, 3 cm/s, 1.8 deg/s standard deviations) as ROFT.

Example:
    >>> import torch
    >>> from torchevtrack.stages.ukf import PoseUKF
    >>> ukf = PoseUKF(batch_size=1)
    >>> ukf.reset(torch.tensor([[0.0, 0.0, 0.5, 1.0, 0.0, 0.0, 0.0]], dtype=torch.float64))
    >>> ukf.predict(0.002)
    >>> ukf.update(torch.tensor([[0.001, 0.0, 0.5, 1.0, 0.0, 0.0, 0.0]], dtype=torch.float64))
    >>> ukf.pose.shape
    torch.Size([1, 7])
"""

from __future__ import annotations

import functools
from typing import NamedTuple

import numpy as np
import torch
from torch import nn

from torchevtrack.geometry import (
    nb_cross,
    nb_quat_canonical,
    nb_quat_exp,
    nb_quat_log,
    nb_quat_mul,
    quat_canonical,
    quat_conj,
    quat_exp,
    quat_log,
    quat_mul,
)
from torchevtrack.config import UKFConfig
from torchevtrack.kernels import kernel
from torchevtrack.linalg import cholesky, eigh, lu_solve
from torchevtrack.stages import batch_mask

__all__ = [
    "boxplus",
    "boxminus",
    "merwe_weights",
    "sigma_points",
    "quat_mean",
    "ukf_predict",
    "ukf_update",
    "PoseUKF",
]

N_TANGENT = 12


def boxplus(x: torch.Tensor, dx: torch.Tensor) -> torch.Tensor:
    """State ``x`` moved by a tangent error ``dx``: Euclidean sum, ``q = exp(dtheta) (x) q``.

    Shape: ``(..., 13), (..., 12) -> (..., 13)``.
    """
    q = quat_canonical(quat_mul(quat_exp(dx[..., 9:12]), x[..., 9:13]))
    return torch.cat((x[..., :9] + dx[..., :9], q), dim=-1)


def boxminus(x: torch.Tensor, ref: torch.Tensor) -> torch.Tensor:
    """Tangent error of ``x`` with respect to ``ref`` (inverse of :func:`boxplus`).

    Shape: ``(..., 13), (..., 13) -> (..., 12)``.
    """
    dq = quat_log(quat_mul(x[..., 9:13], quat_conj(ref[..., 9:13])))
    return torch.cat((x[..., :9] - ref[..., :9], dq), dim=-1)


def merwe_weights(
    n: int, alpha: float = 1.0, beta: float = 2.0, kappa: float = 0.0, dtype: torch.dtype = torch.float64
) -> tuple[torch.Tensor, torch.Tensor, float]:
    """Mean and covariance weights ``(2n+1,)`` of scaled sigma points, and the spread ``n + lambda``."""
    lam = alpha * alpha * (n + kappa) - n
    c = n + lam
    if c <= 0:
        raise ValueError(f"alpha={alpha}, kappa={kappa} give n + lambda = {c} <= 0")
    Wm = torch.full((2 * n + 1,), 0.5 / c, dtype=dtype)
    Wc = Wm.clone()
    Wm[0] = lam / c
    Wc[0] = lam / c + (1.0 - alpha * alpha + beta)
    return Wm, Wc, c


def sigma_points(x: torch.Tensor, P: torch.Tensor, spread: float) -> torch.Tensor:
    """Sigma points ``[x, x [+] cols(L), x [+] -cols(L)]`` with ``L L^T = spread * P``.

    Shape: ``(B, 13), (B, 12, 12) -> (B, 25, 13)``.
    """
    L = torch.linalg.cholesky(spread * 0.5 * (P + P.transpose(-1, -2)))
    cols = L.transpose(-1, -2)
    dx = torch.cat((torch.zeros_like(cols[:, :1]), cols, -cols), dim=1)
    return boxplus(x[:, None].expand(-1, dx.shape[1], -1), dx)


def quat_mean(q: torch.Tensor, w: torch.Tensor) -> torch.Tensor:
    """Weighted quaternion mean: top eigenvector of ``sum_i w_i q_i q_i^T`` (sign-invariant).

    Shape: ``(B, S, 4), (S,) -> (B, 4)`` canonical (``qw >= 0``).
    """
    M = (q.transpose(-1, -2) * w.to(q)) @ q  # sum_i w_i q_i q_i^T
    _, vecs = torch.linalg.eigh(M)
    return quat_canonical(vecs[..., -1])


# -- compiled filter steps ---------------------------------------------------------------------------
# One filter at a time, float64: the functions above, operation by operation, on (25, 13) sigma points.


@kernel
def _nb_boxplus(x, d, sign, out):
    """``out = x [+] sign * d`` (:func:`boxplus`) for ``x`` ``(13,)``, ``d`` ``(12,)``."""
    for i in range(9):
        out[i] = x[i] + sign * d[i]
    e0, e1, e2, e3 = nb_quat_exp(sign * d[9], sign * d[10], sign * d[11])
    q0, q1, q2, q3 = nb_quat_mul(e0, e1, e2, e3, x[9], x[10], x[11], x[12])
    out[9], out[10], out[11], out[12] = nb_quat_canonical(q0, q1, q2, q3)


@kernel
def _nb_sigma_points(x, P, spread, X, S, L):
    """:func:`sigma_points` of one filter into ``X`` ``(25, 13)`` (scratch ``S``, ``L`` ``(12, 12)``); False if
    ``spread * P`` is not positive definite."""
    h = spread * 0.5
    for i in range(12):
        for j in range(12):
            S[i, j] = h * (P[i, j] + P[j, i])
    if not cholesky(S, L):
        return False
    zero = np.zeros(12)
    _nb_boxplus(x, zero, 1.0, X[0])
    col = np.empty(12)
    for i in range(12):
        for j in range(12):
            col[j] = L[j, i]
        _nb_boxplus(x, col, 1.0, X[1 + i])
        _nb_boxplus(x, col, -1.0, X[13 + i])
    return True


@kernel
def _nb_quat_mean(X, Wm, out):
    """:func:`quat_mean` of the quaternions ``X[:, 9:13]`` into ``out`` ``(4,)``."""
    M = np.zeros((4, 4))
    for s in range(X.shape[0]):
        for i in range(4):
            a = X[s, 9 + i] * Wm[s]
            for j in range(4):
                M[i, j] += a * X[s, 9 + j]
    d, V = np.empty(4), np.empty((4, 4))
    eigh(M, d, V)
    top = 0
    for i in range(1, 4):
        if d[i] > d[top]:
            top = i
    out[0], out[1], out[2], out[3] = nb_quat_canonical(V[0, top], V[1, top], V[2, top], V[3, top])


@kernel
def _nb_rot_error(X, s, q, out, k):
    """``out[k:k+3] = log(X[s, 9:13] (x) q^-1)``."""
    a0, a1, a2, a3 = nb_quat_mul(X[s, 9], X[s, 10], X[s, 11], X[s, 12], q[0], -q[1], -q[2], -q[3])
    out[k], out[k + 1], out[k + 2] = nb_quat_log(a0, a1, a2, a3)


@kernel
def _nb_weighted_mean(X, w, start, out):
    """``out[i] = sum_s w[s] X[s, start + i]`` over the sigma points ``s`` in order (one chain per ``i``)."""
    out[:] = 0.0
    for s in range(X.shape[0]):
        for i in range(out.shape[0]):
            out[i] += w[s] * X[s, start + i]


@kernel
def _nb_weighted_outer(A, Bm, w, out):
    """``out[i, j] = sum_s (A[s, i] w[s]) Bm[s, j]`` over the sigma points ``s`` in order: a weighted
    (cross-)covariance of deviations."""
    out[:] = 0.0
    for s in range(A.shape[0]):
        for i in range(out.shape[0]):
            dw = A[s, i] * w[s]
            for j in range(out.shape[1]):
                out[i, j] += dw * Bm[s, j]


@kernel
def _nb_symmetrise(M, out):
    """``out = (M + M^T) / 2``."""
    for i in range(M.shape[0]):
        for j in range(M.shape[1]):
            out[i, j] = 0.5 * (M[i, j] + M[j, i])


@kernel
def _ukf_predict_kernel(x, P, T, q, q_diag, twist, has_twist, Wm, Wc, spread, x_out, P_out):
    """:func:`ukf_predict` (with the known twist of :meth:`PoseUKF.predict`) of every filter. The outputs are
    written once all filters are done (they may alias the inputs); returns -1, or the failing filter."""
    B = x.shape[0]
    Sc, L = np.empty((12, 12)), np.empty((12, 12))
    X = np.empty((25, 13))
    D = np.empty((25, 12))
    xb = np.empty(13)
    xn, Pn = np.empty((B, 13)), np.empty((B, 12, 12))
    Pm = np.empty((12, 12))
    for b in range(B):
        for i in range(13):
            xb[i] = x[b, i]
        if has_twist:  # p_dot = v + w x p, w given
            c0, c1, c2 = nb_cross(twist[b, 3], twist[b, 4], twist[b, 5], xb[6], xb[7], xb[8])
            xb[0], xb[1], xb[2] = twist[b, 0] + c0, twist[b, 1] + c1, twist[b, 2] + c2
            xb[3], xb[4], xb[5] = twist[b, 3], twist[b, 4], twist[b, 5]
        if not _nb_sigma_points(xb, P[b], spread, X, Sc, L):
            return b
        Tb = T[b]
        for s in range(25):  # p+ = p + p_dot T, q+ = exp(w T) (x) q
            X[s, 6], X[s, 7], X[s, 8] = X[s, 6] + X[s, 0] * Tb, X[s, 7] + X[s, 1] * Tb, X[s, 8] + X[s, 2] * Tb
            e0, e1, e2, e3 = nb_quat_exp(X[s, 3] * Tb, X[s, 4] * Tb, X[s, 5] * Tb)
            q0, q1, q2, q3 = nb_quat_mul(e0, e1, e2, e3, X[s, 9], X[s, 10], X[s, 11], X[s, 12])
            X[s, 9], X[s, 10], X[s, 11], X[s, 12] = nb_quat_canonical(q0, q1, q2, q3)
        _nb_weighted_mean(X, Wm, np.int64(0), xn[b, :9])
        _nb_quat_mean(X, Wm, xn[b, 9:13])
        for s in range(25):
            for i in range(9):
                D[s, i] = X[s, i] - xn[b, i]
            _nb_rot_error(X, s, xn[b, 9:13], D[s], np.int64(9))
        _nb_weighted_outer(D, D, Wc, Pm)
        for i in range(12):
            for j in range(12):
                Pm[i, j] += ((q[0, i] if i == j else 0.0) if q_diag else q[i, j]) * Tb
        _nb_symmetrise(Pm, Pn[b])
    x_out[:] = xn
    P_out[:] = Pn
    return -1


@kernel
def _ukf_update_kernel(x, P, z, R, r_diag, Wm, Wc, spread, x_out, P_out):
    """:func:`ukf_update` of every filter. The outputs are written once all filters are done (they may alias the
    inputs); returns -1, or the failing filter."""
    B = x.shape[0]
    Sc, L = np.empty((12, 12)), np.empty((12, 12))
    X = np.empty((25, 13))
    DZ, DX = np.empty((25, 6)), np.empty((25, 12))
    zp, zq = np.empty(3), np.empty(4)
    S, Pzx, Pxz, Kt = np.empty((6, 6)), np.empty((6, 12)), np.empty((12, 6)), np.empty((6, 12))
    KS = np.empty((12, 6))
    nu, dx = np.empty(6), np.empty(12)
    xn, Pn = np.empty((B, 13)), np.empty((B, 12, 12))
    Pm = np.empty((12, 12))
    for b in range(B):
        if not _nb_sigma_points(x[b], P[b], spread, X, Sc, L):
            return b
        _nb_weighted_mean(X, Wm, np.int64(6), zp)
        _nb_quat_mean(X, Wm, zq)
        for s in range(25):
            for i in range(3):
                DZ[s, i] = X[s, 6 + i] - zp[i]
            _nb_rot_error(X, s, zq, DZ[s], np.int64(3))
            for i in range(9):
                DX[s, i] = X[s, i] - x[b, i]
            _nb_rot_error(X, s, x[b, 9:13], DX[s], np.int64(9))
        _nb_weighted_outer(DZ, DZ, Wc, S)
        _nb_weighted_outer(DX, DZ, Wc, Pxz)
        Pzx[:] = Pxz.T
        for i in range(6):
            for j in range(6):
                S[i, j] += (R[0, i] if i == j else 0.0) if r_diag else R[i, j]
        if not lu_solve(S, Pzx, Kt):  # K^T = S^-1 Pxz^T
            return b
        for i in range(3):
            nu[i] = z[b, i] - zp[i]
        a0, a1, a2, a3 = nb_quat_mul(z[b, 3], z[b, 4], z[b, 5], z[b, 6], zq[0], -zq[1], -zq[2], -zq[3])
        nu[3], nu[4], nu[5] = nb_quat_log(a0, a1, a2, a3)
        for i in range(12):
            m = 0.0
            for j in range(6):
                m += Kt[j, i] * nu[j]
            dx[i] = m
        _nb_boxplus(x[b], dx, 1.0, xn[b])
        for i in range(12):  # K S
            for j in range(6):
                m = 0.0
                for k in range(6):
                    m += Kt[k, i] * S[k, j]
                KS[i, j] = m
        for i in range(12):  # P - (K S) K^T
            for j in range(12):
                m = 0.0
                for k in range(6):
                    m += KS[i, k] * Kt[k, j]
                Pm[i, j] = P[b, i, j] - m
        _nb_symmetrise(Pm, Pn[b])
    x_out[:] = xn
    P_out[:] = Pn
    return -1


class UKFArrays(NamedTuple):
    """A :class:`PoseUKF` as compiled kernels take it (:meth:`PoseUKF.arrays`): its state ``x`` ``(B, 13)`` and ``P``
    ``(B, 12, 12)`` (views of its buffers, written in place), process densities ``q`` (``(1, 12)`` with ``q_diag``,
    or ``(12, 12)``), measurement covariance ``r`` (``(1, 6)`` with ``r_diag``, or ``(6, 6)``), and the sigma-point
    weights ``Wm``, ``Wc`` ``(25,)`` and ``spread``."""

    x: np.ndarray
    P: np.ndarray
    q: np.ndarray
    q_diag: bool
    r: np.ndarray
    r_diag: bool
    Wm: np.ndarray
    Wc: np.ndarray
    spread: float


@kernel
def ukf_step(f, dt, twist, z):
    """:meth:`PoseUKF.predict` over ``dt`` ``(B,)`` seconds with the known ``twist`` ``(B, 6)``, then
    :meth:`PoseUKF.update` with the measured poses ``z`` ``(B, 7)``, on the filters' :class:`UKFArrays` ``f`` in place,
    unchecked. Returns -1, or the failing filter: its index in the prediction, ``B`` + its index in the update."""
    bad = _ukf_predict_kernel(f.x, f.P, dt, f.q, f.q_diag, twist, True, f.Wm, f.Wc, f.spread, f.x, f.P)
    if bad >= 0:
        return bad
    bad = _ukf_update_kernel(f.x, f.P, z, f.r, f.r_diag, f.Wm, f.Wc, f.spread, f.x, f.P)
    return bad if bad < 0 else f.x.shape[0] + bad


@functools.lru_cache(maxsize=16)
def _weights_np(alpha: float, beta: float, kappa: float) -> tuple[np.ndarray, np.ndarray, float]:
    """:func:`merwe_weights` of the tangent space as read-only numpy arrays (cached: a filter's are fixed)."""
    Wm, Wc, spread = merwe_weights(N_TANGENT, alpha, beta, kappa)
    Wm, Wc = Wm.numpy(), Wc.numpy()
    Wm.flags.writeable = Wc.flags.writeable = False
    return Wm, Wc, spread


def _f64(t: torch.Tensor) -> np.ndarray:
    """A float64 numpy view (or copy) of a CPU tensor."""
    return t.numpy() if t.dtype == torch.float64 and not t.requires_grad else t.detach().double().numpy()


def _per_filter(T: torch.Tensor | float, B: int) -> np.ndarray:
    """Seconds ``T`` (float or ``(B,)``) as a float64 ``(B,)`` array."""
    if isinstance(T, torch.Tensor):
        return np.ascontiguousarray(np.broadcast_to(_f64(T), (B,)))
    return np.full(B, float(T))


def _cov_arg(c: torch.Tensor) -> tuple[np.ndarray, bool]:
    """A noise covariance given as a diagonal ``(n,)`` or a full ``(n, n)`` matrix: a 2-D array and a diagonal flag."""
    c = _f64(c)
    return (c[None], True) if c.ndim == 1 else (c, False)


def _raise_not_pd(name: str, b: int) -> None:
    raise torch.linalg.LinAlgError(f"{name}: the covariance of filter {b} is not positive-definite")


def _predict_into(x, P, T, q_density, alpha, beta, kappa, twist, x_out, P_out) -> None:
    _check_state(x, P)
    B = x.shape[0]
    Wm, Wc, spread = _weights_np(float(alpha), float(beta), float(kappa))
    q, q_diag = _cov_arg(q_density)
    tw = _NO_TWIST if twist is None else _f64(twist)
    bad = _ukf_predict_kernel(_f64(x), _f64(P), _per_filter(T, B), q, q_diag, tw, twist is not None, Wm, Wc, spread,
                              x_out, P_out)
    if bad >= 0:
        _raise_not_pd("ukf_predict", bad)


def _update_into(x, P, z, R, alpha, beta, kappa, x_out, P_out) -> None:
    _check_state(x, P)
    B = x.shape[0]
    if z.shape != (B, 7):
        raise ValueError(f"pose measurement must have shape ({B}, 7), got {tuple(z.shape)}")
    Wm, Wc, spread = _weights_np(float(alpha), float(beta), float(kappa))
    r, r_diag = _cov_arg(R)
    bad = _ukf_update_kernel(_f64(x), _f64(P), _f64(z), r, r_diag, Wm, Wc, spread, x_out, P_out)
    if bad >= 0:
        _raise_not_pd("ukf_update", bad)


_NO_TWIST = np.zeros((1, 6))


def ukf_predict(
    x: torch.Tensor,
    P: torch.Tensor,
    T: torch.Tensor | float,
    q_density: torch.Tensor,
    alpha: float = 1.0,
    beta: float = 2.0,
    kappa: float = 0.0,
) -> tuple[torch.Tensor, torch.Tensor]:
    """Unscented prediction over ``T`` seconds.

    Args:
        x, P: state ``(B, 13)`` and tangent covariance ``(B, 12, 12)``.
        T: seconds, float or ``(B,)``.
        q_density: process noise spectral densities ``(12,)`` (diagonal) or ``(12, 12)``; ``Q = q_density T``.

    Each filter runs in a compiled kernel (float64), sigma points as :func:`sigma_points`, means as :func:`quat_mean`.

    Shape: ``(B, 13), (B, 12, 12) -> (B, 13), (B, 12, 12)``.
    """
    B = x.shape[0] if x.ndim else 0
    x_out, P_out = np.empty((B, 13)), np.empty((B, 12, 12))
    _predict_into(x, P, T, q_density, alpha, beta, kappa, None, x_out, P_out)
    return torch.from_numpy(x_out).to(x.dtype), torch.from_numpy(P_out).to(x.dtype)


def ukf_update(
    x: torch.Tensor,
    P: torch.Tensor,
    z: torch.Tensor,
    R: torch.Tensor,
    alpha: float = 1.0,
    beta: float = 2.0,
    kappa: float = 0.0,
) -> tuple[torch.Tensor, torch.Tensor]:
    """Unscented update with a pose measurement ``z = [p, q]``.

    Args:
        x, P: state ``(B, 13)`` and tangent covariance ``(B, 12, 12)``.
        z: measured poses ``(B, 7)`` ``[p (m), q (w, x, y, z)]``.
        R: measurement covariance ``(6,)`` (diagonal) or ``(6, 6)``, order ``[p (m^2), rotation vector (rad^2)]``.

    Each filter runs in a compiled kernel (float64); the gain solves ``S K^T = P_xz^T`` (LU, partial pivoting).

    Shape: ``(B, 13), (B, 12, 12), (B, 7) -> (B, 13), (B, 12, 12)``.
    """
    B = x.shape[0] if x.ndim else 0
    x_out, P_out = np.empty((B, 13)), np.empty((B, 12, 12))
    _update_into(x, P, z, R, alpha, beta, kappa, x_out, P_out)
    return torch.from_numpy(x_out).to(x.dtype), torch.from_numpy(P_out).to(x.dtype)


def _check_state(x: torch.Tensor, P: torch.Tensor) -> None:
    if x.ndim != 2 or x.shape[-1] != 13 or P.shape != (x.shape[0], 12, 12):
        raise ValueError(f"expected x (B, 13) and P (B, 12, 12), got {tuple(x.shape)} and {tuple(P.shape)}")


class PoseUKF(nn.Module):
    """Batched pose smoother; buffers ``x`` ``(B, 13)`` and ``P`` ``(B, 12, 12)`` (float64).

    Args:
        batch_size: number ``B`` of independent filters.
        q_pdot, q_w, q_p, q_q: process noise spectral densities ((m/s)^2/s, (rad/s)^2/s, m^2/s, rad^2/s).
        r_p, r_q: measurement variances of position (m^2) and rotation (rad^2).
        p0: initial variance of every tangent component after :meth:`reset` (float or ``(12,)``).
        alpha, beta, kappa: sigma-point parameters.
    """

    def __init__(
        self,
        batch_size: int = 1,
        q_pdot: float = UKFConfig.q_pdot,
        q_w: float = UKFConfig.q_w,
        q_p: float = UKFConfig.q_p,
        q_q: float = UKFConfig.q_q,
        r_p: float = UKFConfig.r_p,
        r_q: float = UKFConfig.r_q,
        p0: float | torch.Tensor = UKFConfig.p0,
        alpha: float = 1.0,
        beta: float = 2.0,
        kappa: float = 0.0,
    ) -> None:
        super().__init__()
        if batch_size < 1:
            raise ValueError(f"batch_size must be >= 1, got {batch_size}")
        if min(q_pdot, q_w, q_p, q_q) < 0 or min(r_p, r_q) <= 0:
            raise ValueError("process densities must be >= 0 and measurement variances > 0")
        merwe_weights(N_TANGENT, alpha, beta, kappa)  # validates the sigma-point parameters
        self.alpha, self.beta, self.kappa = float(alpha), float(beta), float(kappa)
        f64 = torch.float64
        p0 = torch.as_tensor(p0, dtype=f64).expand(N_TANGENT).clone()
        if (p0 <= 0).any():
            raise ValueError(f"p0 must be positive variances, got {p0.tolist()}")
        self.register_buffer("q_density", torch.tensor([q_pdot] * 3 + [q_w] * 3 + [q_p] * 3 + [q_q] * 3, dtype=f64))
        self.register_buffer("R", torch.tensor([r_p] * 3 + [r_q] * 3, dtype=f64))
        self.register_buffer("P0", torch.diag(p0))
        x = torch.zeros(batch_size, 13, dtype=f64)
        x[:, 9] = 1.0
        self.register_buffer("x", x)
        self.register_buffer("P", self.P0.expand(batch_size, -1, -1).clone())

    @classmethod
    def from_config(cls, cfg: UKFConfig, batch_size: int = 1) -> "PoseUKF":
        """The smoother of the config section ``ukf`` (:class:`~torchevtrack.config.UKFConfig`) for ``B`` streams."""
        return cls(batch_size, q_pdot=cfg.q_pdot, q_w=cfg.q_w, q_p=cfg.q_p, q_q=cfg.q_q, r_p=cfg.r_p, r_q=cfg.r_q,
                   p0=cfg.p0)

    @property
    def batch_size(self) -> int:
        return self.x.shape[0]

    @property
    def pose(self) -> torch.Tensor:
        """Current poses ``(B, 7)`` ``[p, q]``."""
        return self.x[:, 6:13]

    @property
    def twist(self) -> torch.Tensor:
        """Current camera-frame twist ``(B, 6)`` ``[v, w]`` with ``v = p_dot - w x p`` (velocity-filter convention)."""
        w = self.x[:, 3:6]
        return torch.cat((self.x[:, 0:3] - torch.linalg.cross(w, self.x[:, 6:9], dim=-1), w), dim=-1)

    def reset(self, pose: torch.Tensor, twist: torch.Tensor | None = None, mask: torch.Tensor | None = None) -> None:
        """Restart at ``pose`` ``(B, 7)`` with an optional twist ``(B, 6)`` ``[v, w]`` (``dP/dt = v + w x P``).

        ``mask`` (``(B,)`` bool or ``(K,)`` indices) restarts only the selected filters; the rows of
        ``pose`` and ``twist`` of the other elements are ignored.
        """
        B = self.batch_size
        if tuple(pose.shape) != (B, 7):
            raise ValueError(f"pose must have shape ({B}, 7), got {tuple(pose.shape)}")
        if twist is not None and tuple(twist.shape) != (B, 6):
            raise ValueError(f"twist must have shape ({B}, 6), got {tuple(twist.shape)}")
        pose = pose.to(self.x)
        x = torch.zeros_like(self.x)
        x[:, 6:9] = pose[:, :3]
        x[:, 9:13] = quat_canonical(pose[:, 3:])
        if twist is not None:
            twist = twist.to(self.x)
            x[:, 3:6] = twist[:, 3:]
            x[:, 0:3] = twist[:, :3] + torch.linalg.cross(twist[:, 3:], pose[:, :3], dim=-1)
        m = batch_mask(mask, B)
        self.x.copy_(torch.where(m[:, None], x, self.x))
        self.P.copy_(torch.where(m[:, None, None], self.P0, self.P))

    def predict(self, T: torch.Tensor | float, twist: torch.Tensor | None = None) -> None:
        """Propagate every filter by ``T`` seconds (float or ``(B,)``) in place.

        ``twist`` ``(B, 6)`` ``[v, w]`` (``dP/dt = v + w x P``) is a known motion input: it replaces the
        velocity part of the state before the prediction, so the filter smooths the pose measurements
        around the motion the velocity stage measured instead of around its own constant-velocity guess
        (which lags by many pixels when the object accelerates).
        """
        if twist is not None and tuple(twist.shape) != (self.batch_size, 6):
            raise ValueError(f"twist must have shape ({self.batch_size}, 6), got {tuple(twist.shape)}")
        _predict_into(self.x, self.P, T, self.q_density, self.alpha, self.beta, self.kappa, twist, self.x.numpy(),
                      self.P.numpy())

    def arrays(self) -> UKFArrays:
        """The filters for compiled kernels (:func:`ukf_step`): numpy views of the buffers, valid until they are
        replaced (``.to``, ``load_state_dict`` keeps them)."""
        Wm, Wc, spread = _weights_np(self.alpha, self.beta, self.kappa)
        (q, q_diag), (r, r_diag) = _cov_arg(self.q_density), _cov_arg(self.R)
        return UKFArrays(self.x.numpy(), self.P.numpy(), q, q_diag, r, r_diag, Wm, Wc, spread)

    def update(self, pose_meas: torch.Tensor) -> None:
        """Fuse measured poses ``(B, 7)`` in place."""
        _update_into(self.x, self.P, pose_meas, self.R, self.alpha, self.beta, self.kappa, self.x.numpy(),
                     self.P.numpy())
