"""Burst guard: tell a window whose event count is far above the recent rate (a flash, a camera bump) before any
stage sees its events, so it can be dropped at O(1) cost instead of flooding the EROS, the flow and the template.

Rule per update and batch element (:func:`burst_step`), for a window of ``n`` events over ``dt_us``:

* ``rate`` is an exponential moving average (weight ``ema``) of the events per second of the accepted windows
  (started by the first accepted window; NaN before).
* the window is a **burst** when ``n > min_fraction * H * W`` (a fraction of the sensor's pixels, so ordinary
  motion, even fast and at 1280x720, never qualifies) **and** ``n > ratio * rate * dt`` (far above this
  element's recent rate; always true before any window was accepted).
* a burst does not enter the rate, so a flash stays a flash. After ``max_run`` consecutive bursts the scene is
  taken to have changed for good: that window is accepted and restarts the rate at its own.

A burst window's events should reach no stage: :func:`keep_events` selects the others. With one element this is
a slice of length 0 (no copy); with several, one pass over the batch indices.

Example:
    >>> import torch
    >>> from torchevtrack.stages.burst import BurstGuard
    >>> g = BurstGuard(480, 640)
    >>> [bool(g(torch.tensor([n]), 2000)) for n in (4000, 5000, 2_000_000, 4500)]
    [False, False, True, False]
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np
import torch
from torch import nn

from torchevtrack.stages import batch_mask

__all__ = ["BurstGuard", "BurstState", "burst_step", "keep_events"]


class BurstState(NamedTuple):
    """Guard state after one window, all ``(B,)``: ``burst`` bool (this window), ``rate`` float64 events/s of the
    accepted windows (NaN: none yet), ``run`` int64 consecutive bursts so far."""

    burst: torch.Tensor
    rate: torch.Tensor
    run: torch.Tensor


def burst_step(n_events: torch.Tensor, dt_us: int, rate: torch.Tensor, run: torch.Tensor, *, floor: float,
               ratio: float, ema: float, max_run: int) -> BurstState:
    """One window of the rule (module docstring) for ``B`` elements; pure, returns the new state.

    Args:
        n_events: ``(B,)`` integer events of each element in the window; dt_us: window length (us, > 0).
        rate: ``(B,)`` float64 events/s (NaN: none yet); run: ``(B,)`` int64 consecutive bursts before this one.
        floor: ``min_fraction * H * W`` events; ratio, ema, max_run: see :class:`BurstGuard`.

    Shape: ``(B,)`` inputs, :class:`BurstState` of ``(B,)`` tensors. (numpy inside: a window costs microseconds.)
    """
    if not dt_us > 0:
        raise ValueError(f"dt_us must be positive, got {dt_us}")
    n = n_events.numpy().astype(np.float64)
    r, k = rate.numpy(), run.numpy()
    dt = dt_us * 1e-6
    fresh = np.isnan(r)
    burst = (n > floor) & (fresh | (n > ratio * np.where(fresh, 0.0, r) * dt)) & (k < max_run)
    restart = fresh | (k >= max_run)  # the first window, or the new normal after a long run
    new_rate = np.where(restart, n / dt, (1 - ema) * np.where(fresh, 0.0, r) + ema * n / dt)
    return BurstState(torch.from_numpy(burst), torch.from_numpy(np.where(burst, r, new_rate)),
                      torch.from_numpy(np.where(burst, k + 1, 0).astype(np.int64)))


def keep_events(b: torch.Tensor | None, n: int, burst: torch.Tensor) -> slice | torch.Tensor:
    """Which of a packed window's ``n`` events to keep given the elements' ``burst`` flags ``(B,)``.

    Returns a ``slice`` (``b`` is ``None``: one element; all or nothing, no copy) or an ``(n,)`` bool mask
    ``~burst[b]``; index every event field with it.
    """
    if b is None:
        return slice(0, 0) if bool(burst[0]) else slice(0, n)
    return ~burst[b.long()]


class BurstGuard(nn.Module):
    """Streaming burst detector for ``B`` event streams (module docstring).

    Args:
        height, width: sensor size (pixels); batch_size: ``B``.
        min_fraction: a burst holds more events than this fraction of the sensor's pixels (default 0.05: 15 k
            events at 640x480, 46 k at 1280x720, i.e. 7.7 M and 23 M events/s in 2 ms windows).
        ratio: ... and more than this many times the recent rate's count for the window (default 10).
        ema: weight of a window in the recent rate (default 0.05, ~20 windows).
        max_run: consecutive bursts after which a window is accepted as the new normal (default 25).

    Buffers:
        rate: ``(B,)`` float64 events/s (NaN before the first accepted window); run: ``(B,)`` int64;
        burst: ``(B,)`` bool, the last window's flags.

    ``forward(n_events (B,), dt_us) -> burst (B,) bool``; then :func:`keep_events` selects the events to pass on.
    """

    rate: torch.Tensor
    run: torch.Tensor
    burst: torch.Tensor

    def __init__(self, height: int, width: int, *, min_fraction: float = 0.05, ratio: float = 10.0,
                 ema: float = 0.05, max_run: int = 25, batch_size: int = 1):
        super().__init__()
        for name, v in (("height", height), ("width", width), ("batch_size", batch_size), ("max_run", max_run)):
            if isinstance(v, bool) or not isinstance(v, int) or v <= 0:
                raise ValueError(f"{name} must be a positive int, got {v!r}")
        if not (min_fraction > 0 and ratio > 1 and 0 < ema <= 1):
            raise ValueError(f"need min_fraction > 0, ratio > 1 and 0 < ema <= 1, got {min_fraction}, {ratio}, {ema}")
        self.floor, self.ratio, self.ema, self.max_run = float(min_fraction) * height * width, float(ratio), \
            float(ema), max_run
        self.register_buffer("rate", torch.full((batch_size,), float("nan"), dtype=torch.float64))
        self.register_buffer("run", torch.zeros(batch_size, dtype=torch.int64))
        self.register_buffer("burst", torch.zeros(batch_size, dtype=torch.bool))

    def forward(self, n_events: torch.Tensor, dt_us: int) -> torch.Tensor:
        n_events = torch.as_tensor(n_events)
        if n_events.shape != self.rate.shape or n_events.is_floating_point() or n_events.dtype == torch.bool:
            raise ValueError(f"n_events must be an integer {tuple(self.rate.shape)} tensor, got {n_events.dtype} "
                             f"{tuple(n_events.shape)}")
        s = burst_step(n_events, dt_us, self.rate, self.run, floor=self.floor, ratio=self.ratio, ema=self.ema,
                       max_run=self.max_run)
        self.rate.numpy()[:], self.run.numpy()[:] = s.rate.numpy(), s.run.numpy()
        self.burst.numpy()[:] = s.burst.numpy()
        return s.burst

    def reset(self, mask: torch.Tensor | None = None) -> None:
        """Forget the rate of every element, or of those selected by ``mask`` (``(B,)`` bool or ``(K,)`` indices)."""
        m = batch_mask(mask, self.rate.shape[0])
        self.rate.masked_fill_(m, float("nan"))
        self.run.masked_fill_(m, 0)
        self.burst.masked_fill_(m, False)

    def extra_repr(self) -> str:
        return f"floor={self.floor:.0f} events, ratio={self.ratio}, ema={self.ema}, max_run={self.max_run}, " \
               f"batch_size={self.rate.shape[0]}"
