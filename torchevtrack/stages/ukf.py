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
correction, which moves in 1 px / 0.5 deg steps: about 1 mm laterally and a few mm in depth at 0.5 m, and
0.5 deg in rotation, hence ``r_p = 1e-5`` m^2 (3 mm) and ``r_q = 1e-4`` rad^2 (0.6 deg). ``p0 = 1e-3``
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

import torch
from torch import nn

from torchevtrack.geometry import quat_canonical, quat_conj, quat_exp, quat_log, quat_mul
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


# Internal constant weights (never modified in place); merwe_weights itself returns fresh tensors.
_merwe_weights_cached = functools.lru_cache(maxsize=16)(merwe_weights)


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


def _mean(X: torch.Tensor, Wm: torch.Tensor) -> torch.Tensor:
    """Weighted mean of sigma states ``(B, S, 13) -> (B, 13)``."""
    return torch.cat((Wm @ X[..., :9], quat_mean(X[..., 9:13], Wm)), dim=-1)


def _noise_cov(d: torch.Tensor, B: int) -> torch.Tensor:
    """Covariance ``(B, n, n)`` from a diagonal ``(n,)`` or a full ``(n, n)`` matrix."""
    M = torch.diag(d) if d.ndim == 1 else d
    return M.expand(B, -1, -1)


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

    Shape: ``(B, 13), (B, 12, 12) -> (B, 13), (B, 12, 12)``.
    """
    _check_state(x, P)
    B = x.shape[0]
    T = torch.as_tensor(T, dtype=x.dtype, device=x.device).expand(B)
    Wm, Wc, spread = _merwe_weights_cached(N_TANGENT, alpha, beta, kappa, x.dtype)
    X = sigma_points(x, P, spread)
    Tb = T[:, None, None]
    p = X[..., 6:9] + X[..., 0:3] * Tb
    q = quat_canonical(quat_mul(quat_exp(X[..., 3:6] * Tb), X[..., 9:13]))
    X = torch.cat((X[..., :6], p, q), dim=-1)
    xm = _mean(X, Wm)
    D = boxminus(X, xm[:, None])
    Q = _noise_cov(q_density.to(x), B) * T[:, None, None]
    Pm = (D.transpose(1, 2) * Wc) @ D + Q
    return xm, 0.5 * (Pm + Pm.transpose(-1, -2))


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

    Shape: ``(B, 13), (B, 12, 12), (B, 7) -> (B, 13), (B, 12, 12)``.
    """
    _check_state(x, P)
    B = x.shape[0]
    if z.shape != (B, 7):
        raise ValueError(f"pose measurement must have shape ({B}, 7), got {tuple(z.shape)}")
    z = z.to(x)
    Wm, Wc, spread = _merwe_weights_cached(N_TANGENT, alpha, beta, kappa, x.dtype)
    X = sigma_points(x, P, spread)
    Zp, Zq = X[..., 6:9], X[..., 9:13]
    zp = Wm @ Zp
    zq = quat_mean(Zq, Wm)
    DZ = torch.cat((Zp - zp[:, None], quat_log(quat_mul(Zq, quat_conj(zq)[:, None]))), dim=-1)
    DX = boxminus(X, x[:, None])
    S = (DZ.transpose(1, 2) * Wc) @ DZ + _noise_cov(R.to(x), B)
    Pxz = (DX.transpose(1, 2) * Wc) @ DZ
    K = torch.linalg.solve(S, Pxz.transpose(-1, -2)).transpose(-1, -2)  # S symmetric
    nu = torch.cat((z[:, :3] - zp, quat_log(quat_mul(z[:, 3:], quat_conj(zq)))), dim=-1)
    x_new = boxplus(x, (K @ nu[..., None])[..., 0])
    P_new = P - K @ S @ K.transpose(-1, -2)
    return x_new, 0.5 * (P_new + P_new.transpose(-1, -2))


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
        q_pdot: float = 1.0,
        q_w: float = 10.0,
        q_p: float = 1e-4,
        q_q: float = 1e-3,
        r_p: float = 1e-5,
        r_q: float = 1e-4,
        p0: float | torch.Tensor = 1e-3,
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
        if twist is not None:
            if tuple(twist.shape) != (self.batch_size, 6):
                raise ValueError(f"twist must have shape ({self.batch_size}, 6), got {tuple(twist.shape)}")
            twist = twist.to(self.x)
            self.x[:, 3:6] = twist[:, 3:]
            self.x[:, 0:3] = twist[:, :3] + torch.linalg.cross(twist[:, 3:], self.x[:, 6:9], dim=-1)
        x, P = ukf_predict(self.x, self.P, T, self.q_density, self.alpha, self.beta, self.kappa)
        self.x.copy_(x)
        self.P.copy_(P)

    def update(self, pose_meas: torch.Tensor) -> None:
        """Fuse measured poses ``(B, 7)`` in place."""
        x, P = ukf_update(self.x, self.P, pose_meas, self.R, self.alpha, self.beta, self.kappa)
        self.x.copy_(x)
        self.P.copy_(P)
