"""Stage 3: 6D object velocity from sparse optical flow with a robust, batched linear Kalman filter.

State ``x = [v, w]`` (m/s, rad/s): the object twist in the camera frame, every object point moving as
``dP/dt = v + w x P`` (the model of :func:`torchevtrack.camera.interaction_matrix`). ``B`` independent
filters run side by side; the state is float64.

* Motion model: ``x+ = rho x + n``, ``n ~ N(0, Q)``, ``Q = diag(q_v^2 I3, q_w^2 I3)`` (``q_v`` m/s and
  ``q_w`` rad/s standard deviations per update).
* Measurement: flow vector ``F`` (px/s) at pixel ``uv`` with depth ``Z`` (m, rendered at the current pose).
  As in the paper (Eq. 5) it is expressed as a displacement over the update interval ``dT``:
  ``z = F dT = H x + e`` with ``H = L(uv, Z) dT`` (px per update) and ``e ~ N(0, r_px^2 I2)``, so ``r_px``
  is the flow noise in pixels of displacement per update (ROFT: 1 px).
  At 500 Hz (``dT = 2 ms``) ``r_px = 1`` means a flow noise of 500 px/s; ROFT's 1 px at 30 Hz is about
  30 px/s, i.e. ``r_px ~ 0.06`` at 500 Hz. Set ``r_px`` to the real flow noise times ``dT``.
* Robust re-weighting (IRLS, ``iters`` rounds after a plain KF update): with ``r_i`` the norm (px) of the
  vector's residual against the current posterior, ``m`` the median of ``r_i`` over the valid vectors
  of that filter and the robust scale ``s = max(1.4826 m, r_px)``, each vector's information is scaled
  by a Laplacian-kernel weight ``w_i = exp(-max(r_i - m, 0) / (k s))``, i.e. its covariance becomes
  ``R / w_i``. Vectors fitting at least as well as the median keep ``w_i = 1``; gross outliers get
  ``w_i ~ 0``; residuals within the nominal noise ``r_px`` are barely touched. (A Huber weight
  ``min(1, c / r_i)`` needs about 10 rounds to shed 30 % gross outliers; this kernel needs 3.)
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

import torch
from torch import nn

from torchevtrack.camera import Camera, interaction_matrix
from torchevtrack.stages import batch_mask

__all__ = [
    "TWIST_AXES",
    "CorrectionFeedback",
    "VelocityUpdate",
    "VelocityKF",
    "centre_jacobian",
    "feedback_update",
    "kf_predict",
    "kf_update",
    "laplacian_weights",
]

TWIST_AXES = ("vx", "vy", "vz", "wx", "wy", "wz")
"""Names of the twist components ``[c_dot, w]`` about the object centre (camera frame), in state order."""

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
    x: torch.Tensor, P: torch.Tensor, rho: float, Q: torch.Tensor
) -> tuple[torch.Tensor, torch.Tensor]:
    """Prediction ``x+ = rho x``, ``P+ = rho^2 P + Q``.

    Shape: ``(B, 6), (B, 6, 6), float, (6, 6) or (B, 6, 6) -> (B, 6), (B, 6, 6)``.
    """
    if x.shape[-1:] != (6,) or P.shape != x.shape + (6,):
        raise ValueError(f"expected x (B, 6) and P (B, 6, 6), got {tuple(x.shape)} and {tuple(P.shape)}")
    return rho * x, rho * rho * P + Q.to(P)


def laplacian_weights(residual: torch.Tensor, valid: torch.Tensor, r_px: float, k: float = 1.0) -> torch.Tensor:
    """Robust weights ``exp(-max(r - m, 0) / (k * max(1.4826 m, r_px)))``, ``m`` the median valid residual.

    Shape: ``(B, G), (B, G) bool, float -> (B, G)`` (residuals in px); invalid entries get weight 0.
    """
    med = torch.nanmedian(torch.where(valid, residual, torch.nan), dim=-1, keepdim=True).values
    med = torch.nan_to_num(med, nan=0.0)
    w = torch.exp(-(residual - med).clamp_min(0) / (k * (_MAD * med).clamp_min(r_px)))
    return torch.where(valid, w, torch.zeros_like(w))


def centre_jacobian(centre: torch.Tensor) -> torch.Tensor:
    """``A(c)`` mapping the twist about ``c`` ``[c_dot, w]`` to the camera-origin twist ``[v, w]``.

    ``v = c_dot - w x c = c_dot + [c]x w``. Shape: ``(B, 3) -> (B, 6, 6)``.
    """
    B = centre.shape[0]
    A = torch.eye(6, dtype=centre.dtype, device=centre.device).repeat(B, 1, 1)
    cx, cy, cz = centre.unbind(-1)
    zero = torch.zeros_like(cx)
    A[:, :3, 3:] = torch.stack((zero, -cz, cy, cz, zero, -cx, -cy, cx, zero), -1).view(B, 3, 3)
    return A


def _information_solve(
    Y0: torch.Tensor, x0: torch.Tensor, H: torch.Tensor, z: torch.Tensor, info: torch.Tensor
) -> tuple[torch.Tensor, torch.Tensor]:
    """Posterior of prior ``(x0, Y0^-1)`` and measurements ``z = H x + e``, ``e ~ N(0, diag(1 / info))``.

    Shape: ``(B, 6, 6), (B, 6), (B, M, 6), (B, M), (B, M) -> (B, 6), (B, 6, 6)``.
    """
    HtW = (H * info[..., None]).transpose(-1, -2)
    A = Y0 + HtW @ H
    b = (HtW @ (z - (H @ x0[..., None])[..., 0])[..., None])[..., 0]
    LA = torch.linalg.cholesky(0.5 * (A + A.transpose(-1, -2)))
    x = x0 + torch.cholesky_solve(b[..., None], LA)[..., 0]
    P = torch.cholesky_inverse(LA)
    return x, 0.5 * (P + P.transpose(-1, -2))


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
        r_px: flow noise standard deviation, px of displacement per update (``R = r_px^2 I2``).
        iters: robust re-weighting rounds after the plain update (0 = plain linear KF update).
        k: width of the Laplacian weight in robust standard deviations ``max(1.4826 x median, r_px)``.
        min_vectors: filters with fewer valid vectors keep their prior.
        normal: the vectors are normal flows (the flow component along the edge normal, as the
            ``estimate="normal"`` flow stage gives): each vector then measures only ``n . (L x)`` with
            ``n = F / |F|``, one scalar of noise ``r_px`` (the aperture problem leaves the tangential
            component unobserved, so it must not be read as zero).
        centre: ``(B, 3)`` object centre (m, camera frame). If given, the state is the twist about the
            centre, ``[c_dot, w]`` with ``c_dot = v + w x c`` the centre's velocity, and the Jacobian
            becomes ``L A(c)``, ``A = [[I, [c]x], [0, I]]``. For a small object far from the camera,
            ``v`` and ``w`` of the camera-origin twist are nearly collinear in the flow (a lever arm of
            ``|c|``), and the motion-model shrinkage ``rho x`` then pulls ``v`` toward ``-w x c``; about
            the centre the two are nearly independent. Convert back with ``v = c_dot - w x c``.

    Returns:
        :class:`VelocityUpdate`.

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
    if r_px <= 0 or iters < 0 or k <= 0:
        raise ValueError(f"need r_px > 0, iters >= 0, k > 0; got r_px={r_px}, iters={iters}, k={k}")
    dtype = x.dtype
    dt = torch.as_tensor(dt, dtype=dtype, device=x.device).expand(B)
    if not bool((dt > 0).all()):
        raise ValueError(f"dt must be positive seconds, got {dt.tolist()}")
    uv, flow, depth = uv.to(dtype), flow.to(dtype), depth.to(dtype)
    ok = valid & torch.isfinite(depth) & (depth > 0) & torch.isfinite(flow).all(-1) & torch.isfinite(uv).all(-1)
    speed = flow.norm(dim=-1)
    if normal:
        ok = ok & (speed > 0)
    used = ok.sum(-1) >= min_vectors
    ok = ok & used[:, None]
    safe_depth = torch.where(ok, depth, torch.ones_like(depth))
    safe_uv = torch.where(ok[..., None], uv, torch.zeros_like(uv))
    H = interaction_matrix(safe_uv, safe_depth, camera.fx, camera.fy, camera.cx, camera.cy) * dt[:, None, None, None]
    if centre is not None:
        if centre.shape != (B, 3):
            raise ValueError(f"centre must have shape ({B}, 3), got {tuple(centre.shape)}")
        H = H @ centre_jacobian(centre.to(dtype))[:, None]
    z = torch.where(ok[..., None], flow, torch.zeros_like(flow)) * dt[:, None, None]

    LP = torch.linalg.cholesky(0.5 * (P + P.transpose(-1, -2)))
    Y0 = torch.cholesky_inverse(LP)
    if normal:
        n = flow / torch.where(ok, speed, torch.ones_like(speed))[..., None]
        Hf = (n[..., None, :] @ H)[..., 0, :]
        zf = torch.where(ok, speed, torch.zeros_like(speed)) * dt[:, None]
        rows = 1
    else:
        Hf, zf, rows = H.reshape(B, 2 * G, 6), z.reshape(B, 2 * G), 2

    def solve(w: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        xp, Pp = _information_solve(Y0, x, Hf, zf, (w / r_px**2).repeat_interleave(rows, dim=-1))
        residual = (zf - (Hf @ xp[..., None])[..., 0]).reshape(B, G, rows).norm(dim=-1)
        return xp, Pp, residual

    w = ok.to(dtype)
    xp, Pp, residual = solve(w)
    for _ in range(iters):
        w = laplacian_weights(residual, ok, r_px, k)
        xp, Pp, residual = solve(w)
    xp = torch.where(used[:, None], xp, x)
    Pp = torch.where(used[:, None, None], Pp, P)
    return VelocityUpdate(xp, Pp, w, torch.where(ok, residual, torch.zeros_like(residual)), used)


class VelocityKF(nn.Module):
    """Batched velocity Kalman filter (state in buffers ``x`` ``(B, 6)`` and ``P`` ``(B, 6, 6)``, float64).

    Args:
        camera: intrinsics of the flow pixel coordinates.
        rho: velocity decay of the motion model (paper: 0.5).
        q_v, q_w: process noise standard deviations per update (m/s, rad/s). With ``rho = 0.5`` the
            prior mean halves at every step, so these must be of the order of the velocities themselves
            for the filter to follow the flow rather than decay to zero.
        r_px: flow noise standard deviation, px of displacement per update.
        p0_v, p0_w: initial standard deviations (m/s, rad/s) after :meth:`reset`.
        min_vectors: filters with fewer valid vectors only predict.
        iters, k: robust re-weighting rounds and Laplacian width (see :func:`kf_update`).
        normal: the flow vectors are normal flows (see :func:`kf_update`).
        batch_size: number ``B`` of independent filters.
    """

    def __init__(
        self,
        camera: Camera,
        rho: float = 0.5,
        q_v: float = 0.5,
        q_w: float = 3.0,
        r_px: float = 1.0,
        p0_v: float = 1.0,
        p0_w: float = 5.0,
        min_vectors: int = 3,
        iters: int = 3,
        k: float = 1.0,
        normal: bool = False,
        batch_size: int = 1,
    ) -> None:
        super().__init__()
        if not isinstance(camera, Camera):
            raise TypeError(f"camera must be a Camera, got {type(camera).__name__}")
        if not 0.0 <= rho <= 1.0:
            raise ValueError(f"rho must be in [0, 1], got {rho}")
        if min(q_v, q_w, r_px, p0_v, p0_w) <= 0:
            raise ValueError("q_v, q_w, r_px, p0_v and p0_w must be positive standard deviations")
        if batch_size < 1:
            raise ValueError(f"batch_size must be >= 1, got {batch_size}")
        self.camera = camera
        self.rho, self.r_px, self.k = float(rho), float(r_px), float(k)
        self.min_vectors, self.iters, self.normal = int(min_vectors), int(iters), bool(normal)
        f64 = torch.float64
        self.register_buffer("Q", torch.diag(torch.tensor([q_v**2] * 3 + [q_w**2] * 3, dtype=f64)))
        self.register_buffer("P0", torch.diag(torch.tensor([p0_v**2] * 3 + [p0_w**2] * 3, dtype=f64)))
        self.register_buffer("x", torch.zeros(batch_size, 6, dtype=f64))
        self.register_buffer("P", self.P0.expand(batch_size, 6, 6).clone())

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

    def predict(self) -> torch.Tensor:
        """Apply the motion model in place; returns the predicted twist ``(B, 6)``."""
        x, P = kf_predict(self.x, self.P, self.rho, self.Q)
        self.x.copy_(x)
        self.P.copy_(P)
        return self.x

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
            r_px=self.r_px, iters=self.iters, k=self.k, min_vectors=self.min_vectors, normal=self.normal,
            centre=centre,
        )
        self.x.copy_(out.x)
        self.P.copy_(out.P)
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
    b = leak * b + gain * rate
    if limit is not None:
        b = torch.minimum(torch.maximum(b, -limit), limit)
    return torch.where(mask, b, torch.zeros_like(b))


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

    def __init__(self, gain: float = 0.2, leak: float = 0.8, axes=("vz", "wx", "wy"), max_v: float = 0.1,
                 max_w: float = 0.5, batch_size: int = 1) -> None:
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

    def forward(self, rate: torch.Tensor, symmetry_axis: torch.Tensor | None = None) -> torch.Tensor:
        """Take the corrections' rate ``(B, 6)`` (twist about the centre) and return the new feedback ``b``.

        ``symmetry_axis`` ``(B, 3)``: unit camera-frame axes through the object centres about which the
        objects look the same (zero rows: none). The corrections cannot observe a turn about such an axis,
        so that component of their rate is noise and is removed before it enters the feedback.
        """
        if rate.shape != self.b.shape:
            raise ValueError(f"rate must have shape {tuple(self.b.shape)}, got {tuple(rate.shape)}")
        rate = rate.to(self.b)
        if symmetry_axis is not None:
            a = symmetry_axis.to(rate)
            w = rate[:, 3:]
            rate = torch.cat((rate[:, :3], w - (w * a).sum(-1, keepdim=True) * a), -1)
        self.b.copy_(feedback_update(self.b, rate, self.gain, self.leak, self.mask, self.limit))
        return self.b

    def reset(self, mask: torch.Tensor | None = None) -> None:
        """Zero the feedback of every element, or of those selected by ``mask`` (``(B,)`` bool or ``(K,)`` indices)."""
        self.b.masked_fill_(batch_mask(mask, self.b.shape[0])[:, None], 0.0)

    def extra_repr(self) -> str:
        return f"gain={self.gain}, leak={self.leak}, axes={self.axes}, max_v={float(self.limit[0])}, " \
               f"max_w={float(self.limit[3])}"
