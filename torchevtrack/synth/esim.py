"""Event simulation from rendered frames (the ESIM algorithm), vectorised in torch.

Each pixel keeps a reference log intensity ``ref``. Between two log frames ``(t0, L0)`` and ``(t1, L1)``
a pixel whose level moved ``n = floor(|L1 - ref| / C)`` thresholds away emits ``n`` events of polarity
``sign(L1 - ref)``; the ``k``-th (``k = 1..n``) sits at level ``ref + pol * k * C`` and at the time where
the linear ramp ``L0 -> L1`` crosses it::

    t_k = t0 + floor((ref + pol * k * C - L0) / (L1 - L0) * (t1 - t0))     (int64 microseconds)

then ``ref += pol * n * C`` (``tau = 0`` when ``L1 == L0``, the rounding corner case where ``ref`` ends up
exactly one threshold away from a constant level). An event closer than ``refractory_us`` to the pixel's previous *emitted*
event is dropped (``ref`` still advances). Events are sorted by time; ties keep pixel order
(``y * W + x``) and then the order ``k`` within the pixel. Log intensity is ``L = log(I + 1e-3)``.

Sensor effects of :class:`ESIM` beyond the contrast events: background-activity noise (a Poisson process of
``noise_rate_hz`` per pixel, uniform polarity) and hot pixels (``hot_pixels`` fixed addresses, each a Poisson
process of ``hot_pixel_rate_hz``). The refractory period applies to every event a pixel emits, whatever its
source: contrast, noise and hot-pixel events of one frame interval are filtered together, in time order,
against each pixel's last emitted event (:func:`refractory_filter`).

Example:
    >>> import torch
    >>> sim = ESIM(1, 1, C=0.2, sigma_C=0.0)
    >>> _ = sim(torch.full((1, 1), 0.2), 0)          # first frame: initialises ref
    >>> ev = sim(torch.full((1, 1), 0.5), 1000)
    >>> len(ev), ev.p.tolist()
    (4, [1, 1, 1, 1])
"""

from __future__ import annotations

import numpy as np
import torch
from torch import nn

from torchevtrack.events import EventStream
from torchevtrack.kernels import kernel

__all__ = ["LOG_EPS", "log_intensity", "esim_step", "noise_events", "hot_pixel_events", "refractory_filter", "ESIM"]

LOG_EPS = 1e-3
_NEVER = -(1 << 62)


def log_intensity(image: torch.Tensor) -> torch.Tensor:
    """``log(I + 1e-3)`` in float64. Shape: ``(..., H, W) -> (..., H, W)``; ``I`` in ``[0, 1]``."""
    return torch.log(image.to(torch.float64) + LOG_EPS)


def esim_step(
    L0: torch.Tensor,
    L1: torch.Tensor,
    t0_us: int,
    t1_us: int,
    ref: torch.Tensor,
    C: torch.Tensor,
    last_t_us: torch.Tensor,
    refractory_us: int = 0,
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
    """Events of one frame interval (pure function; inputs are not modified).

    Args:
        L0, L1: log intensity at ``t0_us`` and ``t1_us``, ``(H, W)``.
        t0_us, t1_us: frame times, integer microseconds, ``t1_us > t0_us``.
        ref: reference log level per pixel, ``(H, W)``.
        C: contrast threshold per pixel (> 0), ``(H, W)``.
        last_t_us: time of each pixel's last emitted event, int64 ``(H, W)`` (very negative = never).
        refractory_us: minimum spacing of emitted events at one pixel, microseconds.

    Returns:
        ``x (N,) int64, y (N,) int64, t_us (N,) int64, p (N,) int8 in {0, 1}`` sorted by time, then the
        updated ``ref`` (float64) and ``last_t_us`` (int64), ``(H, W)`` each.
    """
    if L0.ndim != 2 or L0.shape != L1.shape or ref.shape != L0.shape or C.shape != L0.shape:
        raise ValueError(
            f"L0, L1, ref and C must share one (H, W) shape, got {tuple(L0.shape)}, {tuple(L1.shape)}, "
            f"{tuple(ref.shape)}, {tuple(C.shape)}"
        )
    if last_t_us.shape != L0.shape or last_t_us.dtype != torch.int64:
        raise ValueError(f"last_t_us must be int64 of shape {tuple(L0.shape)}, got {last_t_us.dtype} "
                         f"{tuple(last_t_us.shape)}")
    t0_us, t1_us = int(t0_us), int(t1_us)
    if t1_us <= t0_us:
        raise ValueError(f"frame times must increase, got t0={t0_us} us, t1={t1_us} us")
    if refractory_us < 0:
        raise ValueError(f"refractory_us must be >= 0, got {refractory_us}")
    W = L0.shape[1]
    arrays = [np.ascontiguousarray(a.to(torch.float64).numpy()) for a in (L0, L1, ref, C)]
    last = last_t_us.numpy().copy()
    new_ref = np.empty_like(arrays[0])
    ev_pix, t, ev_pol = _nb_esim_step(*arrays, last, t0_us, t1_us, int(refractory_us), new_ref)
    ev_pix, t, ev_pol = torch.from_numpy(ev_pix), torch.from_numpy(t), torch.from_numpy(ev_pol)
    order = torch.sort(t, stable=True).indices
    ev_pix, t, ev_pol = ev_pix[order], t[order], ev_pol[order]
    return ev_pix % W, ev_pix // W, t, ev_pol, torch.from_numpy(new_ref), torch.from_numpy(last)


@kernel
def _nb_esim_step(L0, L1, ref, C, last, t0, t1, refractory, new_ref):
    """The events of :func:`esim_step` in pixel order, then ``k`` (not yet sorted by time): flat pixel index,
    time and polarity (int8 0/1); fills ``new_ref`` and updates ``last`` in place. All float arithmetic in
    float64, in the order the module docstring's formulas give."""
    H, W = L0.shape
    n = np.zeros(H * W, dtype=np.int64)
    total = 0
    for i in range(H):
        for j in range(W):
            d = L1[i, j] - ref[i, j]
            c = C[i, j]
            m = np.int64(np.floor(abs(d) / c))
            pol = 1.0 if d > 0 else (-1.0 if d < 0 else 0.0)
            new_ref[i, j] = ref[i, j] + pol * np.float64(m) * c
            n[i * W + j] = m
            total += m
    pix = np.empty(total, dtype=np.int64)
    t = np.empty(total, dtype=np.int64)
    p = np.empty(total, dtype=np.int8)
    dt = np.float64(t1 - t0)
    e = 0
    for q in range(H * W):
        m = n[q]
        if m == 0:
            continue
        i, j = q // W, q % W
        d = L1[i, j] - ref[i, j]
        pol = 1.0 if d > 0 else -1.0
        l0 = L0[i, j]
        span = L1[i, j] - l0
        for k in range(1, m + 1):
            level = ref[i, j] + pol * np.float64(k) * C[i, j]
            # span == 0: ref sat a whole threshold (up to rounding) off a constant level; the event fires at t0
            tau = (level - l0) / span if span != 0 else 0.0
            tau = min(max(tau, 0.0), 1.0)
            tk = t0 + np.int64(np.floor(tau * dt))
            if refractory > 0:
                if tk - last[i, j] < refractory:
                    continue
                last[i, j] = tk
            elif tk > last[i, j]:
                last[i, j] = tk
            pix[e] = q
            t[e] = tk
            p[e] = 1 if pol > 0 else 0
            e += 1
    return pix[:e], t[:e], p[:e]


def noise_events(
    height: int, width: int, t0_us: int, t1_us: int, rate_hz: float, generator: torch.Generator
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
    """Uniform background-activity noise: Poisson count ``rate_hz * H * W * dt``, uniform pixel, time in
    ``[t0, t1)`` and polarity. Returns ``x, y, t_us (int64), p (int8)``, ``(N,)`` each, sorted by time."""
    lam = torch.tensor(rate_hz * height * width * (t1_us - t0_us) / 1e6, dtype=torch.float64)
    m = int(torch.poisson(lam, generator=generator))
    pix = torch.randint(0, height * width, (m,), generator=generator)
    t = t0_us + torch.randint(0, t1_us - t0_us, (m,), generator=generator)
    p = torch.randint(0, 2, (m,), generator=generator).to(torch.int8)
    order = torch.sort(t, stable=True).indices
    return pix[order] % width, pix[order] // width, t[order], p[order]


def hot_pixel_events(
    pixels: torch.Tensor, t0_us: int, t1_us: int, rate_hz: float, generator: torch.Generator
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Events of hot pixels in ``[t0, t1)``: each of ``pixels`` (flat indices ``y * W + x``, ``(K,)`` int64) fires a
    Poisson count of mean ``rate_hz * dt``, at uniform times and polarities.

    Returns flat pixel indices, ``t_us`` (int64) and ``p`` (int8), ``(N,)`` each, grouped by pixel (not sorted).
    """
    lam = torch.full((pixels.numel(),), rate_hz * (t1_us - t0_us) / 1e6, dtype=torch.float64)
    counts = torch.poisson(lam, generator=generator).to(torch.int64)
    pix = torch.repeat_interleave(pixels, counts)
    t = t0_us + torch.randint(0, t1_us - t0_us, (pix.numel(),), generator=generator)
    p = torch.randint(0, 2, (pix.numel(),), generator=generator).to(torch.int8)
    return pix, t, p


@kernel
def _nb_refractory(pix: np.ndarray, t: np.ndarray, last: np.ndarray, refractory: int, keep: np.ndarray) -> None:
    for i in range(pix.shape[0]):
        p = pix[i]
        if t[i] - last[p] >= refractory:
            keep[i] = True
            last[p] = t[i]
        else:
            keep[i] = False


def refractory_filter(pix: torch.Tensor, t_us: torch.Tensor, last_t_us: torch.Tensor,
                      refractory_us: int) -> torch.Tensor:
    """Which events a pixel emits when it cannot fire twice within ``refractory_us``; updates ``last_t_us``.

    Events come in time order. Per pixel, an event is kept when it comes at least ``refractory_us`` after the
    pixel's last kept event (``last_t_us`` before the first); a dropped event does not restart the period.
    One compiled pass over the events.

    Args:
        pix: flat pixel index of each event ``(N,)`` int64; t_us: its time ``(N,)`` int64, non-decreasing.
        last_t_us: time of each pixel's last emitted event, ``(P,)`` contiguous int64 (very negative = never);
            updated in place.
        refractory_us: microseconds, ``>= 0``.

    Returns:
        ``keep (N,)`` bool.

    Example:
        >>> last = torch.full((1,), -100)
        >>> refractory_filter(torch.tensor([0, 0, 0]), torch.tensor([0, 5, 12]), last, 10).tolist(), last.tolist()
        ([True, False, True], [12])
    """
    if pix.shape != t_us.shape or pix.ndim != 1:
        raise ValueError(f"pix and t_us must be (N,) each, got {tuple(pix.shape)} and {tuple(t_us.shape)}")
    if last_t_us.dtype != torch.int64 or last_t_us.ndim != 1 or not last_t_us.is_contiguous():
        raise ValueError("last_t_us must be a contiguous (P,) int64 tensor")
    if refractory_us < 0:
        raise ValueError(f"refractory_us must be >= 0, got {refractory_us}")
    if t_us.numel() > 1 and bool((t_us[1:] < t_us[:-1]).any()):
        raise ValueError("events must come in time order")
    keep = np.empty(pix.numel(), dtype=np.bool_)
    _nb_refractory(pix.to(torch.int64).numpy(), t_us.to(torch.int64).numpy(), last_t_us.numpy(), int(refractory_us),
                   keep)
    return torch.from_numpy(keep)


class ESIM(nn.Module):
    """Stateful event simulator: feed frames in time order, get the events since the previous frame.

    Args:
        height, width: sensor size.
        C: mean contrast threshold (log units).
        sigma_C: per-pixel threshold spread; each pixel draws ``N(C, sigma_C)`` clipped to ``>= 0.01``.
        refractory_us: per-pixel refractory period, microseconds.
        noise_rate_hz: per-pixel rate of uniform noise events (they do not touch ``ref``).
        hot_pixels: number of hot pixels, distinct addresses drawn (seeded) after the threshold map.
        hot_pixel_rate_hz: firing rate of each hot pixel, events / s.
        seed: seeds the threshold map, the hot-pixel addresses and the noise.

    Buffers: ``ref (H, W)`` float64, ``C (H, W)`` float64, ``last_t_us (H, W)`` int64,
    ``L_prev (H, W)`` float64, ``t_prev_us ()`` int64 (``-1`` before the first frame), ``hot_pix (K,)`` int64
    (flat indices ``y * W + x`` of the hot pixels).
    """

    def __init__(self, height: int, width: int, C: float = 0.2, sigma_C: float = 0.03, refractory_us: int = 0,
                 noise_rate_hz: float = 0.0, seed: int = 0, *, hot_pixels: int = 0,
                 hot_pixel_rate_hz: float = 100.0) -> None:
        super().__init__()
        if height <= 0 or width <= 0:
            raise ValueError(f"sensor size must be positive, got {width}x{height}")
        if not C > 0 or sigma_C < 0:
            raise ValueError(f"need C > 0 and sigma_C >= 0, got C={C}, sigma_C={sigma_C}")
        if refractory_us < 0 or noise_rate_hz < 0:
            raise ValueError(f"refractory_us and noise_rate_hz must be >= 0, got {refractory_us}, {noise_rate_hz}")
        self.height, self.width = int(height), int(width)
        self.refractory_us = int(refractory_us)
        self.noise_rate_hz = float(noise_rate_hz)
        self.generator = torch.Generator().manual_seed(int(seed))
        c_map = C + sigma_C * torch.randn(self.height, self.width, generator=self.generator, dtype=torch.float64)
        self.register_buffer("C", c_map.clamp_min(0.01))
        self.register_buffer("ref", torch.zeros(self.height, self.width, dtype=torch.float64))
        self.register_buffer("L_prev", torch.zeros(self.height, self.width, dtype=torch.float64))
        self.register_buffer("last_t_us", torch.full((self.height, self.width), _NEVER, dtype=torch.int64))
        self.register_buffer("t_prev_us", torch.tensor(-1, dtype=torch.int64))
        if not 0 <= int(hot_pixels) <= self.height * self.width or hot_pixel_rate_hz < 0:
            raise ValueError(f"need 0 <= hot_pixels <= {self.height * self.width} and hot_pixel_rate_hz >= 0, got "
                             f"{hot_pixels}, {hot_pixel_rate_hz}")
        self.hot_pixel_rate_hz = float(hot_pixel_rate_hz)
        hot = torch.zeros(0, dtype=torch.int64)
        if int(hot_pixels) > 0:
            hot = torch.randperm(self.height * self.width, generator=self.generator)[: int(hot_pixels)]
        self.register_buffer("hot_pix", hot)

    def hot_pixel_coords(self) -> list[list[int]]:
        """The hot pixels as ``[[x, y], ...]`` (the order of ``hot_pix``)."""
        return [[int(i) % self.width, int(i) // self.width] for i in self.hot_pix]

    def reset(self) -> None:
        """Forget the previous frame and all event history (the threshold map is kept)."""
        self.ref.zero_()
        self.L_prev.zero_()
        self.last_t_us.fill_(_NEVER)
        self.t_prev_us.fill_(-1)

    def forward(self, image: torch.Tensor, t_us: int, roi: tuple[int, int, int, int] | None = None) -> EventStream:
        """Events between the previous frame and ``image`` (intensity in ``[0, 1]``) at ``t_us``.

        ``image`` is the full ``(H, W)`` frame, or with ``roi = (u0, v0, w, h)`` only that window ``(h, w)``:
        pixels outside it must be unchanged since the previous frame (they cannot emit events then, as
        every pixel's ``ref`` is within one threshold of its level after each step). The first frame
        only initialises ``ref`` and returns no events (it must be a full frame).
        """
        t_us = int(t_us)
        t_prev = int(self.t_prev_us)
        if roi is None:
            roi = (0, 0, self.width, self.height)
        u0, v0, w, h = (int(r) for r in roi)
        if u0 < 0 or v0 < 0 or w <= 0 or h <= 0 or u0 + w > self.width or v0 + h > self.height:
            raise ValueError(f"roi (u0, v0, w, h) = {roi} is not inside the {self.width}x{self.height} sensor")
        if image.shape != (h, w):
            raise ValueError(f"image must have shape ({h}, {w}) for roi {roi}, got {tuple(image.shape)}")
        L = log_intensity(image)
        win = (slice(v0, v0 + h), slice(u0, u0 + w))
        if t_prev < 0:
            if (w, h) != (self.width, self.height):
                raise ValueError("the first frame must cover the whole sensor (roi=None)")
            self.ref.copy_(L)
            self.L_prev.copy_(L)
            self.t_prev_us.fill_(t_us)
            return EventStream.empty()
        if t_us <= t_prev:
            raise ValueError(f"frames must come in increasing time, got t={t_us} us after {t_prev} us")
        extra = self.noise_rate_hz > 0 or (self.hot_pix.numel() > 0 and self.hot_pixel_rate_hz > 0)
        x, y, t, p, ref, last = esim_step(self.L_prev[win], L, t_prev, t_us, self.ref[win], self.C[win],
                                          self.last_t_us[win], 0 if extra else self.refractory_us)
        x, y = x + u0, y + v0
        self.ref[win] = ref
        self.L_prev[win] = L
        self.t_prev_us.fill_(t_us)
        if not extra:
            self.last_t_us[win] = last
            return EventStream(x.to(torch.int16), y.to(torch.int16), t, p)
        # Contrast, noise and hot-pixel events share each pixel's refractory period.
        pix = [y * self.width + x]
        ts, ps = [t], [p]
        if self.noise_rate_hz > 0:
            nx, ny, nt, npol = noise_events(self.height, self.width, t_prev, t_us, self.noise_rate_hz,
                                            self.generator)
            pix.append(ny * self.width + nx)
            ts.append(nt)
            ps.append(npol)
        if self.hot_pix.numel() > 0 and self.hot_pixel_rate_hz > 0:
            hp, ht, hpol = hot_pixel_events(self.hot_pix, t_prev, t_us, self.hot_pixel_rate_hz, self.generator)
            pix.append(hp)
            ts.append(ht)
            ps.append(hpol)
        pix, t, p = torch.cat(pix), torch.cat(ts), torch.cat(ps)
        order = torch.sort(t, stable=True).indices
        pix, t, p = pix[order], t[order], p[order]
        keep = refractory_filter(pix, t, self.last_t_us.view(-1), self.refractory_us)
        pix, t, p = pix[keep], t[keep], p[keep]
        return EventStream((pix % self.width).to(torch.int16), (pix // self.width).to(torch.int16), t, p)
